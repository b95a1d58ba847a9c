"""Route read-out: the pointer head with a one-step transition over the map's tables, raised to Δτ.

(docs/design.md, "The posterior at every horizon"). From the context tokens ctx (B, S, D), the
query's descriptor embedding e (B, Q, D) and Δτ (B, Q):

    T_ij  = softmax_j(<FiLM_e(MLP(ctx_i)), W ctx_j> / √D)  over the map's tables j (B, Q, S, S)
    π_0   = one-hot of the table the queried object stands on at τ (nearest table centre)
    π     = π_0 T^Δτ                                     table weights (B, Q, S)
    μ_s   = from_centre(A · c(box_s) + B · c(object box) + β)   the object on table s
    σ     = exp(θ / 2) ⊙ (h, w, h, w) of the object       widths relative to the object's size
    v     = mixture velocity of Σ_s π_s N(μ_s, σ²) (:func:`.readout.mixture_velocity`) + Dense₀(h)

The mixture is free of x_t and t, so with a zero residual its log-density is the flow's in
closed form. Initialisation: A = diag(1, 1, 0, 0), B = diag(0, 0, 1, 1), β = 0; widths 0.25 ×
side (position) and 0.05 × side (size); near-uniform transition logits.
"""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp

from flowmaps_jax.boxes import from_centre, to_centre
from flowmaps_jax.model.embeddings import FlatDense
from flowmaps_jax.model.precision import compute_dtype, einsum
from flowmaps_jax.model.readout import INIT_REL_STD, diagonal_init, mixture_velocity
from flowmaps_jax.tokens import FURNITURE, OBJECT

_TINY = 1e-30


def object_box(boxes, descriptor, kind, mask, query_descriptor):
    """The box (B, Q, 4) of the object token named by each query_descriptor (B, Q) (zeros if
    none); boxes (B, S, 4), descriptor / kind / mask (B, S)."""
    match = (mask & (kind == OBJECT))[:, None, :] & (
        query_descriptor[:, :, None] == descriptor[:, None, :])
    match = match.astype(jnp.float32)
    return jnp.einsum("bqs,bsk->bqk", match, boxes) / jnp.maximum(match.sum(-1, keepdims=True), 1.0)


def start_table(boxes, tables, obj_box):
    """One-hot (B, Q, S) of the table whose centre is nearest the object's centre at τ."""
    d = jnp.sum(jnp.square(to_centre(obj_box)[:, :, None, :2] - to_centre(boxes)[:, None, :, :2]),
                axis=-1)  # (B, Q, S)
    nearest = jnp.argmin(jnp.where(tables[:, None, :], d, jnp.inf), axis=-1)
    return jax.nn.one_hot(nearest, boxes.shape[1], dtype=jnp.float32)


def propagate(start, transition, steps, max_steps: int):
    """π_0 T^steps for per-query step counts: start (B, Q, S), transition (B, Q, S, S) row-
    stochastic, steps (B, Q) ints in [0, max_steps] → (B, Q, S)."""
    def step(w, k):
        moved = jnp.einsum("bqs,bqst->bqt", w, transition)
        return jnp.where((k < steps)[..., None], moved, w), None

    out, _ = jax.lax.scan(step, start, jnp.arange(max_steps))
    return out


class RouteReadout(nn.Module):
    """The route head (module doc). ``tau_max`` bounds Δτ (the scan length)."""

    dim: int
    tau_max: int
    box_scale: float = 1.0
    box_offset: float = 0.0
    width_scale: float = 1.0  # log σ² = width_scale · θ: Adam moves the widths this much faster
    precision: str = "float32"

    def table_weights(self, query_embedding, context, query_descriptor, dtau):
        """(π (B, Q, S) table weights, object box (B, Q, 4), tables (B, S) bool)."""
        tables = context.mask & (context.kind == FURNITURE)
        obj = object_box(context.boxes, context.descriptor, context.kind, context.mask,
                         query_descriptor)
        ctx = context.tokens
        hidden = FlatDense(self.dim, precision=self.precision, name="route_from")(
            nn.silu(FlatDense(self.dim, precision=self.precision, name="route_hidden")(ctx)))
        film = FlatDense(2 * self.dim, kernel_init=nn.initializers.zeros_init(),
                         precision=self.precision, name="route_query")(query_embedding)
        scale, shift = jnp.split(film[:, :, None, :], 2, axis=-1)  # (B, Q, 1, D) each
        rows = hidden[:, None] * (1.0 + scale) + shift  # (B, Q, S, D): "from table i, for q"
        cols = FlatDense(self.dim, precision=self.precision, name="route_to")(ctx)  # (B, S, D)
        logits = einsum("bqid,bjd->bqij", rows, cols, compute_dtype(self.precision))
        logits = logits.astype(jnp.float32) / math.sqrt(self.dim)
        logits = jnp.where(tables[:, None, None, :], logits, -jnp.inf)
        transition = jax.nn.softmax(logits, axis=-1)  # (B, Q, S, S)
        start = start_table(context.boxes, tables, obj)
        weights = propagate(start, transition, dtau, self.tau_max - 1)
        return weights, obj, tables

    @nn.compact
    def __call__(self, h, query_embedding, context, query_descriptor, dtau, x_t, t,
                 mixture_only: bool = False):
        """v (B, Q, N, 4); or with ``mixture_only`` the mixture itself: (log-weights (B, Q, S),
        −inf off the tables; means (B, Q, S, 4) and log-variances (B, Q, 4) in flow space)."""
        weights, obj, tables = self.table_weights(query_embedding, context, query_descriptor,
                                                  dtau)
        big_negative = jnp.finfo(jnp.float32).min / 4
        anchor = jnp.where(tables[:, None, :], jnp.log(jnp.maximum(weights, _TINY)),
                           big_negative)[:, :, None, :]  # (B, Q, 1, S)
        self.sow("intermediates", "anchor_logits", anchor)  # for the optional pointer loss
        a_map = self.param("anchor_map", diagonal_init(1.0, 1.0, 0.0, 0.0), (4, 4))
        b_map = self.param("source_map", diagonal_init(0.0, 0.0, 1.0, 1.0), (4, 4))
        bias = self.param("mean_bias", nn.initializers.zeros_init(), (4,))
        means = (to_centre(context.boxes) @ a_map)[:, None] + (
            to_centre(obj) @ b_map + bias)[:, :, None, :]  # (B, Q, S, 4) centre form
        means = self.box_scale * (from_centre(means) - self.box_offset)  # the flow's space
        init = [2.0 * math.log(r) / self.width_scale for r in INIT_REL_STD]
        theta = self.param("log_rel_var", lambda key, shape: jnp.asarray(init, jnp.float32), (4,))
        side = self.box_scale * jnp.maximum(obj[..., (2, 3, 2, 3)], 1e-4)  # (B, Q, 4)
        log_var = self.width_scale * theta + 2.0 * jnp.log(side)
        if mixture_only:
            log_w = jnp.where(tables[:, None, :], jnp.log(jnp.maximum(weights, _TINY)), -jnp.inf)
            return log_w, means, log_var
        n = x_t.shape[2]
        shape = (*anchor.shape[:2], n, anchor.shape[-1])
        v = mixture_velocity(jnp.broadcast_to(anchor, shape),
                             jnp.broadcast_to(means[:, :, None], (*shape, 4)),
                             log_var[:, :, None, None, :], x_t, t)
        zeros = nn.initializers.zeros_init()
        return v + FlatDense(4, kernel_init=zeros, precision=self.precision, name="residual")(h)



def mixture_log_prob(log_w, means, log_var, z):
    """log Σ_s w_s N(z; μ_s, diag σ²) of points z (B, Q, N, 4), for the mixture of
    :meth:`RouteReadout.__call__` with ``mixture_only`` (log_w (B, Q, S), means (B, Q, S, 4),
    log_var (B, Q, 4)) → (B, Q, N)."""
    var = jnp.exp(log_var)[:, :, None, None, :]
    diff = z[:, :, :, None, :] - means[:, :, None]
    comp = -0.5 * jnp.sum(diff**2 / var + jnp.log(2.0 * jnp.pi * var), axis=-1)  # (B, Q, N, S)
    return jax.nn.logsumexp(comp + log_w[:, :, None, :], axis=-1)
