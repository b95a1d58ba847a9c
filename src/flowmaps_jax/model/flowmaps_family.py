"""The FlowMaps family: its training loss, its jitted inference cores and :data:`FAMILY`.
The flow runs in z = box_scale · (box − box_offset); shapes: tokens (B, S), queries (B, Q), keys
(B,), boxes (B, Q, N, 4) normalised (y, x, h, w), log-densities (B, Q, N). No validation: the
checked wrapper is :class:`flowmaps_jax.predictor.Predictor`."""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp

from flowmaps_jax import flow
from flowmaps_jax.boxes import to_centre
from flowmaps_jax.model import mixture
from flowmaps_jax.model.config import ModelConfig
from flowmaps_jax.model.family import LossOptions, ModelFamily, scene_noise
from flowmaps_jax.model.flowmaps import (
    encode,
    horizon_index,
    init_params,
    make_velocity_fn,
    object_table_logits,
    placement_velocity,
    route_mixture,
    select_horizon,
    table_logits,
    velocity,
    velocity_and_anchor_logits,
)
from flowmaps_jax.model.route import mixture_log_prob
from flowmaps_jax.tokens import FURNITURE, Queries, SceneTokens, TrainBatch

DEFAULT_NUM_STEPS = 10
"""ODE grid points (the reference's ``linspace(0, 1, 10)``): 18 midpoint evaluations."""


def to_flow_space(box: jnp.ndarray, config: ModelConfig) -> jnp.ndarray:
    """Normalised boxes (..., 4) → the flow's data space z = box_scale · (box − box_offset)."""
    return config.box_scale * (box - config.box_offset)


def from_flow_space(z: jnp.ndarray, config: ModelConfig) -> jnp.ndarray:
    """Inverse of :func:`to_flow_space`: z (..., 4) → normalised boxes (..., 4)."""
    return z / config.box_scale + config.box_offset


def flow_space_log_det(config: ModelConfig) -> float:
    """log |det ∂z/∂box| = 4 · log(box_scale): add to log p(z) to get log p(box)."""
    return 4 * math.log(config.box_scale)


# --------------------------------------------------------------------------- the loss


def supporting_token(tokens: SceneTokens, boxes: jnp.ndarray) -> jnp.ndarray:
    """Index (B, Q) of the furniture token nearest each box's centre (B, Q, 4): its table."""
    centre, token_centre = to_centre(boxes)[..., :2], to_centre(tokens.boxes)[..., :2]
    d = jnp.sum(jnp.square(centre[:, :, None] - token_centre[:, None]), -1)  # (B, Q, S)
    ok = (tokens.mask.astype(bool) & (tokens.kind == FURNITURE))[:, None, :]
    return jnp.argmin(jnp.where(ok, d, jnp.inf), axis=-1)


def cfm_loss(params, config: ModelConfig, batch: TrainBatch, key: jax.Array,
             t_sampler: str = "beta", deterministic: bool = False, pointer_loss: float = 0.0):
    """Conditional flow-matching loss ``(loss, aux)``: the squared error of v(x_t, t) to
    X_1 − X_0 on the linear path, averaged; ``pointer_loss`` > 0 adds that weight × the anchor
    cross-entropy against the target's table. aux: ``loss``, ``mse_per_query`` (B, Q)
    (+ ``pointer_ce``). ``deterministic=True``: no dropout.
    """
    noise_key, t_key, enc_key, vel_key = jax.random.split(key, 4)
    if deterministic:
        enc_key = vel_key = None
    x1 = to_flow_space(batch.target, config)  # (B, Q, 4)
    x0 = jax.random.normal(noise_key, x1.shape, x1.dtype)
    t = flow.sample_t(t_key, x1.shape[:2], t_sampler)  # (B, Q)
    x_t = flow.linear_path(x0, x1, t)[:, :, None, :]  # (B, Q, 1, 4)
    context = encode(params, config, batch.tokens, dropout_key=enc_key)
    extra = {}
    if pointer_loss > 0:
        v, logits = velocity_and_anchor_logits(params, config, context, x_t, t, batch.queries,
                                               dropout_key=vel_key)
        table = supporting_token(batch.tokens, batch.target)  # (B, Q)
        log_w = jax.nn.log_softmax(logits[:, :, 0], axis=-1)  # (B, Q, S)
        extra["pointer_ce"] = -jnp.mean(jnp.take_along_axis(log_w, table[..., None], axis=-1))
    else:
        v = velocity(params, config, context, x_t, t, batch.queries, dropout_key=vel_key)
    mse = jnp.mean(jnp.square(v[:, :, 0] - flow.target_velocity(x0, x1)), axis=-1)  # (B, Q)
    loss = jnp.mean(mse) + pointer_loss * extra.get("pointer_ce", 0.0)
    return loss, {"loss": loss, "mse_per_query": mse, **extra}


def mixture_loss(params, config: ModelConfig, batch: TrainBatch, key: jax.Array,
                 t_sampler: str = "beta", deterministic: bool = False, table_loss: float = 1.0,
                 num_objects: int = 3):
    """The mixture head's loss ``(loss, aux)``: ``table_loss`` × the table cross-entropy plus
    the placement flow's flow-matching loss on the target's table, in its local frame. aux:
    ``loss``, ``mse_per_query`` (B, Q), ``table_ce`` and ``selection`` (= ``table_ce``).
    """
    noise_key, t_key, enc_key, w_key, vel_key = jax.random.split(key, 5)
    if deterministic:
        enc_key = w_key = vel_key = None
    context = encode(params, config, batch.tokens, dropout_key=enc_key)
    table = supporting_token(batch.tokens, batch.target)  # (B, Q)
    objects = mixture.scene_objects(batch.tokens, num_objects)  # (B, M)
    logits = object_table_logits(params, config, context, objects, dropout_key=w_key)
    which = jnp.argmax(batch.queries.descriptor[:, :, None] == objects[:, None, :], axis=-1)
    logits = jnp.take_along_axis(logits, which[:, :, None, None], axis=1)  # (B, Q, S, T)
    dtau = horizon_index(batch.queries.tau_q, batch.tokens.tau, config.tau_max)
    log_w = jax.nn.log_softmax(select_horizon(logits, dtau), axis=-1)
    ce = -jnp.mean(jnp.take_along_axis(log_w, table[..., None], axis=-1))
    means, scale, _ = mixture.placement_frame(context, batch.queries.descriptor)
    rows = table[:, :, None]  # (B, Q, 1)
    z1 = mixture.to_local(batch.target[:, :, None], mixture.gather_rows(means, rows), scale)
    z1 = z1[:, :, 0]  # (B, Q, 4)
    z0 = jax.random.normal(noise_key, z1.shape, z1.dtype)
    t = flow.sample_t(t_key, z1.shape[:2], t_sampler)
    z_t = flow.linear_path(z0, z1, t)[:, :, None, :]
    v = placement_velocity(params, config, context, z_t, t, batch.queries, rows,
                           dropout_key=vel_key)
    mse = jnp.mean(jnp.square(v[:, :, 0] - flow.target_velocity(z0, z1)), axis=-1)  # (B, Q)
    loss = jnp.mean(mse) + table_loss * ce
    return loss, {"loss": loss, "mse_per_query": mse, "table_ce": ce, "selection": ce}


def flowmaps_loss(params, config: ModelConfig, batch: TrainBatch, key: jax.Array, train: bool,
                  options: LossOptions):
    """``ModelFamily.loss``: :func:`mixture_loss` for the mixture head, else :func:`cfm_loss`."""
    if config.head == "mixture":
        return mixture_loss(params, config, batch, key, options.t_sampler,
                            deterministic=not train, table_loss=options.pointer_loss,
                            num_objects=options.num_objects)
    return cfm_loss(params, config, batch, key, options.t_sampler, deterministic=not train,
                    pointer_loss=options.pointer_loss)


# --------------------------------------------------------------------------- inference cores


def _field_and_noise(params, config: ModelConfig, tokens: SceneTokens, queries: Queries,
                     keys: jax.Array, num_samples: int):
    """The velocity field for B scenes and its start noise X_0 (B, Q, N, 4) from keys (B,)."""
    context = encode(params, config, tokens)
    x0 = scene_noise(keys, (queries.tau_q.shape[1], num_samples, 4))
    return make_velocity_fn(params, config, context, queries), x0


@functools.partial(jax.jit, static_argnames=("config", "num_samples", "num_steps", "method"))
def flow_sample(params, config: ModelConfig, tokens: SceneTokens, queries: Queries,
                keys: jax.Array, num_samples: int, num_steps: int = DEFAULT_NUM_STEPS,
                method: str = "midpoint") -> jnp.ndarray:
    """FlowMaps samples (B, Q, N, 4); keys (B,) one PRNG key per scene."""
    if config.head == "mixture":
        return _mixture_sample(params, config, tokens, queries, keys, num_samples, num_steps,
                               method)
    velocity_fn, x0 = _field_and_noise(params, config, tokens, queries, keys, num_samples)
    return from_flow_space(flow.integrate(velocity_fn, x0, num_steps, method), config)


@functools.partial(jax.jit, static_argnames=("config", "num_steps", "method"))
def flow_log_prob(params, config: ModelConfig, tokens: SceneTokens, queries: Queries,
                  x: jnp.ndarray, num_steps: int = DEFAULT_NUM_STEPS,
                  method: str = "midpoint") -> jnp.ndarray:
    """Exact log-density (B, Q, N) of boxes x (B, Q, N, 4) (backward ODE, change of variables)."""
    if config.head == "mixture":
        return _mixture_log_prob(params, config, tokens, queries, x, num_steps, method)
    context = encode(params, config, tokens)
    velocity_fn = make_velocity_fn(params, config, context, queries)
    z = to_flow_space(x, config)
    return flow.log_prob(velocity_fn, z, num_steps, method) + flow_space_log_det(config)


@functools.partial(jax.jit, static_argnames=("config",))
def table_weights(params, config: ModelConfig, tokens: SceneTokens, queries: Queries
                  ) -> jnp.ndarray:
    """The weight (B, Q, S) a read-out head puts on each token (pointer: the anchor softmax at
    t = 0, x = 0)."""
    context = encode(params, config, tokens)
    if config.head == "mixture":
        return jax.nn.softmax(table_logits(params, config, context, queries), axis=-1)
    if config.head == "route":
        log_w, _, _ = route_mixture(params, config, context, queries)
        return jnp.exp(log_w)
    b, q = queries.tau_q.shape
    _, logits = velocity_and_anchor_logits(params, config, context, jnp.zeros((b, q, 1, 4)),
                                           jnp.zeros((b, q)), queries)
    return jax.nn.softmax(logits[:, :, 0], axis=-1)


@functools.partial(jax.jit, static_argnames=("config",))
def route_mixture_log_prob(params, config: ModelConfig, tokens: SceneTokens, queries: Queries,
                           x: jnp.ndarray) -> jnp.ndarray:
    """Closed-form log-density (B, Q, N) of boxes x (B, Q, N, 4) under the route head's mixture
    (exact while the head's residual is zero)."""
    log_w, means, log_var = route_mixture(params, config, encode(params, config, tokens), queries)
    return mixture_log_prob(log_w, means, log_var, to_flow_space(x, config)) + \
        flow_space_log_det(config)


@functools.partial(jax.jit, static_argnames=("config", "num_samples", "num_steps", "method"))
def flow_sample_with_log_prob(params, config: ModelConfig, tokens: SceneTokens, queries: Queries,
                              keys: jax.Array, num_samples: int,
                              num_steps: int = DEFAULT_NUM_STEPS, method: str = "midpoint"
                              ) -> tuple[jnp.ndarray, jnp.ndarray]:
    """:func:`flow_sample`'s samples (B, Q, N, 4) with their exact log-density (B, Q, N), from
    one solve of the augmented ODE."""
    if config.head == "mixture":  # the density needs every near table's term: a second solve
        boxes = _mixture_sample(params, config, tokens, queries, keys, num_samples, num_steps,
                                method)
        return boxes, _mixture_log_prob(params, config, tokens, queries, boxes, num_steps,
                                        method)
    velocity_fn, x0 = _field_and_noise(params, config, tokens, queries, keys, num_samples)
    z, log_p = flow.sample_with_log_prob(velocity_fn, x0, num_steps, method)
    return from_flow_space(z, config), log_p + flow_space_log_det(config)


def _placement_fn(params, config: ModelConfig, context, queries: Queries, table):
    """``fn(z (B, Q, N, 4), t scalar) -> v``: the placement flow on the rows' tables (B, Q, N)."""
    def velocity_fn(z, t):
        t_bq = jnp.broadcast_to(jnp.asarray(t, z.dtype), z.shape[:2])
        return placement_velocity(params, config, context, z, t_bq, queries, table)
    return velocity_fn


def _mixture_sample(params, config: ModelConfig, tokens: SceneTokens, queries: Queries,
                    keys: jax.Array, num_samples: int, num_steps: int, method: str):
    """The mixture head's samples (B, Q, N, 4): a table s ~ π per row, then the placement flow
    in s's frame."""
    context = encode(params, config, tokens)
    logits = table_logits(params, config, context, queries)  # (B, Q, S)
    q = queries.tau_q.shape[1]
    x0 = scene_noise(keys, (q, num_samples, 4))
    table = jax.vmap(lambda k, lg: jax.random.categorical(
        jax.random.fold_in(k, 1), lg[:, None, :], axis=-1, shape=(q, num_samples)))(keys, logits)
    means, scale, _ = mixture.placement_frame(context, queries.descriptor)
    z = flow.integrate(_placement_fn(params, config, context, queries, table), x0, num_steps,
                       method)
    return mixture.from_local(z, mixture.gather_rows(means, table), scale)


def _mixture_log_prob(params, config: ModelConfig, tokens: SceneTokens, queries: Queries,
                      x: jnp.ndarray, num_steps: int, method: str):
    """log Σ_s π_s p_θ(x | s) (B, Q, N) over the ``mixture.MIXTURE_TERMS`` tables nearest each
    box: one backward solve of N × terms rows, each in its table's frame."""
    context = encode(params, config, tokens)
    log_w = jax.nn.log_softmax(table_logits(params, config, context, queries), axis=-1)
    means, scale, _ = mixture.placement_frame(context, queries.descriptor)
    index, valid = mixture.nearest_tables(x, context)  # (B, Q, N, K)
    b, q, n, k = index.shape
    table = index.reshape(b, q, n * k)
    boxes = jnp.repeat(x, k, axis=2)  # (B, Q, N·K, 4), row n·K + j is box n at table j
    z = mixture.to_local(boxes, mixture.gather_rows(means, table), scale)
    log_pz = flow.log_prob(_placement_fn(params, config, context, queries, table), z, num_steps,
                           method) + mixture.local_log_det(scale)
    terms = log_pz.reshape(b, q, n, k) + mixture.gather_rows(log_w, table).reshape(b, q, n, k)
    return jax.nn.logsumexp(jnp.where(valid, terms, -jnp.inf), axis=-1)


def _row_bytes(config: ModelConfig) -> int:
    """Working memory of one sampled box: dim × (mlp_ratio + 4) float32 activations."""
    return 4 * config.dim * (config.mlp_ratio + 4)


FAMILY = ModelFamily(
    name="flowmaps", init=init_params, loss=flowmaps_loss, sample=flow_sample,
    sample_with_log_prob=flow_sample_with_log_prob, log_prob=flow_log_prob,
    label=lambda config: "FlowMaps", row_bytes=_row_bytes, uses_solver=True,
    table_weights=table_weights,
    has_table_weights=lambda config: config.head in ("pointer", "route", "mixture"))
"""FlowMaps (flow matching, CDiT velocity network); the head is ``ModelConfig.head``."""
