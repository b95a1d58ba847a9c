"""Pointer read-out: the velocity of a Gaussian mixture whose components are copied out of the map.

(docs/design.md, "Learning the routines"). From the CDiT rows h (B, Q, N, D), the context tokens
(B, S, D), their normalised boxes (B, S, 4), x_t (B, Q, N, 4) and t (B, Q):

    a_s  = softmax_s(<W_a h, K_a ctx_s> / √D)            anchor logits (which table)
    b_s  = softmax_s(<W_b h, K_b ctx_s> / √D)            source pointer (whose size)
    μ_s  = A · c(box_s) + B · Σ_j b_j c(box_j) + β       component means, in centre form
                                                         c(y, x, h, w) = (y + h/2, x + w/2, h, w),
                                                         then back to (y, x, h, w) and flow space
    σ²   = exp(log σ²₀ + Dense₀(c))                      per-query, per-number widths
                                                         (× the object's (h, w, h, w)² with
                                                         ``widths="relative"``)
    var_s = t² σ² + (1 − t)²                             X_t | component s ~ N(t μ_s, var)
    w_s  ∝ exp(ℓ_s) · N(x_t; t μ_s, var)                 ℓ_s = anchor logit: the mixture weight
    v    = Σ_s w_s [(1 − t) μ_s − ((1 − t) − t σ²) x_t] / var  +  Dense₀(h)

For fixed weights, means and widths this is exactly E[X_1 − X_0 | X_t = x_t] for X_1 ~ Σ_s π_s
N(μ_s, σ²), finite at t = 1. Initialisation: A = diag(1, 1, 0, 0), B = diag(0, 0, 1, 1), β = 0.
"""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp

from flowmaps_jax.boxes import from_centre, to_centre
from flowmaps_jax.model.embeddings import FlatDense
from flowmaps_jax.model.precision import compute_dtype, einsum

_INIT_LOG_VAR = 2.0 * math.log(0.02)  # a component's initial std in flow units
INIT_REL_STD = (0.25, 0.25, 0.05, 0.05)  # relative widths: fractions of the object's (h, w, h, w)


def diagonal_init(*values):
    """A flax initialiser returning diag(values) (ignores the key)."""
    return lambda key, shape, dtype=jnp.float32: jnp.diag(jnp.asarray(values, dtype))


def _pointer_logits(h, context, name: str, dim: int, precision: str = "float32"):
    """Scores <W h_row, K ctx_s> / √dim: h (B, Q, N, D), context (B, S, D) → (B, Q, N, S)."""
    query = FlatDense(dim, name=f"{name}_query", precision=precision)(h)
    key = FlatDense(dim, name=f"{name}_key", precision=precision)(context)
    return einsum("bqnd,bsd->bqns", query, key, compute_dtype(precision)) / math.sqrt(dim)


def mixture_velocity(logits, means, log_var, x_t, t):
    """v (B, Q, N, 4) = E[X_1 − X_0 | X_t = x_t] of the linear path towards a Gaussian mixture:
    logits (B, Q, N, S) log-weights, means (B, Q, N, S, 4), log_var (B, Q, 1 or N, 1, 4), x_t
    (B, Q, N, 4), t (B, Q)."""
    tt = t[:, :, None, None, None]
    var0 = jnp.exp(log_var)
    var = jnp.square(tt) * var0 + jnp.square(1.0 - tt)  # (B, Q, 1, 1, 4)
    x = x_t[:, :, :, None, :]  # (B, Q, N, 1, 4)
    resid = x - tt * means
    log_lik = -0.5 * jnp.sum(jnp.square(resid) / var + jnp.log(var), axis=-1)  # (B, Q, N, S)
    weights = jax.nn.softmax(logits + log_lik, axis=-1)
    v_comp = ((1.0 - tt) * means - ((1.0 - tt) - tt * var0) * x) / var  # (B, Q, N, S, 4)
    return jnp.einsum("bqns,bqnsd->bqnd", weights, v_comp)


class PointerReadout(nn.Module):
    """The pointer head (module docstring). ``precision`` applies to the D-wide products; the
    box-space arithmetic stays float32."""

    dim: int
    box_scale: float = 1.0
    box_offset: float = 0.0
    width_scale: float = 1.0  # log σ² = width_scale · θ: Adam moves the widths this much faster
    precision: str = "float32"
    widths: str = "absolute"  # or "relative": σ = exp(θ/2) × the object's (h, w, h, w)

    @nn.compact
    def __call__(self, h, c, context, mask, boxes, x_t, t):
        big_negative = jnp.finfo(h.dtype).min / 4
        keep = mask[:, None, None, :]  # (B, 1, 1, S)
        logits = lambda name: _pointer_logits(h, context, name, self.dim, self.precision)  # noqa: E731
        anchor = jnp.where(keep, logits("anchor"), big_negative)
        self.sow("intermediates", "anchor_logits", anchor)  # for the optional pointer loss
        source = jnp.where(keep, logits("source"), big_negative)
        source = jax.nn.softmax(source, axis=-1)
        a_map = self.param("anchor_map", diagonal_init(1.0, 1.0, 0.0, 0.0), (4, 4))
        b_map = self.param("source_map", diagonal_init(0.0, 0.0, 1.0, 1.0), (4, 4))
        bias = self.param("mean_bias", nn.initializers.zeros_init(), (4,))
        centres = to_centre(boxes)  # (B, S, 4)
        shared = jnp.einsum("bqns,bsd->bqnd", source, centres) @ b_map  # (B, Q, N, 4)
        means = (centres @ a_map)[:, None, None] + (shared + bias)[:, :, :, None, :]
        means = self.box_scale * (from_centre(means) - self.box_offset)  # the flow's space
        zeros = nn.initializers.zeros_init()
        shift = FlatDense(4, kernel_init=zeros, precision=self.precision,
                          name="log_var_shift")(nn.silu(c))[:, :, None, None, :]  # (B, Q, 1, 1, 4)
        if self.widths == "relative":  # fractions of the object's size (the source's h, w)
            init = [2.0 * math.log(r) / self.width_scale for r in INIT_REL_STD]
            theta = self.param("log_var", lambda key, shape: jnp.asarray(init, jnp.float32),
                               (4,))
            hw = jnp.array([2, 3, 2, 3])
            size = jnp.maximum(shared[..., hw] + bias[hw], 1e-4)  # (B, Q, N, 4)
            log_var = (self.width_scale * theta + shift
                       + 2.0 * jnp.log(self.box_scale * size)[:, :, :, None, :])  # (B, Q, N, 1, 4)
        else:
            theta = self.param("log_var",
                               nn.initializers.constant(_INIT_LOG_VAR / self.width_scale), (4,))
            log_var = self.width_scale * theta + shift
        v = mixture_velocity(anchor, means, log_var, x_t, t)
        return v + FlatDense(4, kernel_init=zeros, precision=self.precision, name="residual")(h)
