"""Training state and the jitted update: optimiser, EMA, train step, validation loss.

Everything here is a pure function of explicit pytrees:

* :class:`TrainState` holds the step counter, params, EMA params, optimiser state and two PRNG
  keys (``rng`` for dropout / flow noise, ``data_key`` for batches). The batch and the noise of
  step ``i`` come from ``fold_in(data_key, i)`` and ``fold_in(rng, i)``, so a restored state
  continues a run exactly.
* :func:`make_train_step` returns one ``jax.jit``-compiled ``(state, batch, key) -> (state,
  metrics)`` doing loss, gradients, the optax update and the EMA update, with the state donated.
* :func:`make_fused_train_step` additionally draws the batch inside the same compiled function
  from the scenes arrays (no host round trip): ``(state, scenes) -> (state, metrics)``. With
  ``data="endless"`` the scenes argument is swapped for fresh environments every few steps
  (:func:`endless_scenes`).
* :func:`make_eval_loss` scores EMA params on fixed validation batches with a fixed key and no
  dropout, so values are comparable across evaluations.

The model kind (FlowMaps flow matching or the MLP Gaussian baseline) is hidden behind an
:class:`Objective` (``init`` + ``loss``); tests may pass a stand-in objective.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from flowmaps_jax.config import TrainConfig
from flowmaps_jax.tokens import (
    TrainBatch,
    assert_batch_shapes,
    from_centre,
    to_centre,
    trim_padding,
)

Params = Any
# loss(params, batch, key, train) -> (scalar loss, dict of scalar diagnostics)
LossFn = Callable[[Params, TrainBatch, jax.Array, bool], tuple[jax.Array, dict]]
# batch_fn(key, scenes) -> TrainBatch, traceable
BatchFn = Callable[[jax.Array, Any], TrainBatch]

# Fixed seed offset of the validation key: evaluations at different steps use the same noise.
_EVAL_KEY_SALT = 0x5EED


@struct.dataclass
class TrainState:
    """Everything a run needs to continue exactly (all arrays; a pytree).

    step: () int32, optimiser steps taken so far.
    params / ema_params: model parameters and their exponential moving average.
    opt_state: optax state (AdamW moments, schedule count, ...).
    rng: (2,) uint32 PRNG key for dropout and flow noise; step i uses fold_in(rng, i).
    data_key: (2,) uint32 PRNG key for batches; step i draws batch fold_in(data_key, i).
    """

    step: jax.Array
    params: Params
    ema_params: Params
    opt_state: optax.OptState
    rng: jax.Array
    data_key: jax.Array


@dataclasses.dataclass(frozen=True)
class Objective:
    """How to initialise and score one model kind.

    init(key) -> params.
    loss(params, batch, key, train) -> (loss, aux): scalar training loss and a dict of scalar
        diagnostics; ``train=False`` must be deterministic given ``key`` (no dropout).
    """

    init: Callable[[jax.Array], Params]
    loss: LossFn


def objective_for(cfg: TrainConfig) -> Objective:
    """The FlowMaps (``flow.cfm_loss``) or MLP-baseline (``model.baseline_loss``) objective."""
    # Imported here so config/checkpoint code does not pay for building the model modules.
    from flowmaps_jax import flow, model

    if cfg.model_kind == "flowmaps":
        def init(key):
            return model.init_params(key, cfg.model)

        def loss(params, batch, key, train):
            value, aux = flow.cfm_loss(params, cfg.model, batch, key, cfg.t_sampler,
                                       deterministic=not train, pointer_loss=cfg.pointer_loss)
            return value, _scalars(aux)

        return Objective(init=init, loss=loss)
    if cfg.model_kind == "mlp":
        def init(key):
            return model.init_baseline(key, cfg.model)

        def loss(params, batch, key, train):
            value, aux = model.baseline_loss(params, cfg.model, batch, key if train else None)
            return value, _scalars(aux)

        return Objective(init=init, loss=loss)
    raise ValueError(f"model_kind must be 'flowmaps' or 'mlp'; got {cfg.model_kind!r}")


def _scalars(aux: dict) -> dict:
    """The scalar diagnostics of a loss's aux dict (per-query arrays and ``loss`` dropped)."""
    return {k: v for k, v in aux.items() if k != "loss" and jnp.ndim(v) == 0}


# --------------------------------------------------------------------------------------------
# Optimiser and EMA


def make_schedule(cfg: TrainConfig) -> optax.Schedule:
    """Learning rate per step: linear warm-up to ``lr`` then cosine decay to 0 at ``steps``."""
    if cfg.warmup_steps > 0:
        return optax.warmup_cosine_decay_schedule(
            init_value=0.0, peak_value=cfg.lr, warmup_steps=cfg.warmup_steps,
            decay_steps=cfg.steps, end_value=0.0)
    return optax.cosine_decay_schedule(init_value=cfg.lr, decay_steps=cfg.steps)


def make_optimizer(cfg: TrainConfig) -> optax.GradientTransformation:
    """AdamW(b1, b2, weight_decay) on the cosine schedule, after optional global-norm clipping."""
    adamw = optax.adamw(make_schedule(cfg), b1=cfg.b1, b2=cfg.b2, weight_decay=cfg.weight_decay)
    if cfg.clip_norm is None:
        return adamw
    return optax.chain(optax.clip_by_global_norm(cfg.clip_norm), adamw)


def ema_update(ema_params: Params, params: Params, decay: float) -> Params:
    """One EMA step, ``decay * ema + (1 - decay) * params`` leaf-wise (optax.incremental_update)."""
    return optax.incremental_update(params, ema_params, step_size=1.0 - decay)


# --------------------------------------------------------------------------------------------
# State


def init_state(cfg: TrainConfig, key: jax.Array | None = None,
               objective: Objective | None = None) -> TrainState:
    """Fresh state at step 0: params from ``key`` (default ``PRNGKey(cfg.seed)``), EMA = params."""
    if not isinstance(cfg, TrainConfig):
        raise ValueError(f"cfg must be a TrainConfig; got {type(cfg).__name__}")
    objective = objective or objective_for(cfg)
    if key is None:
        key = jax.random.PRNGKey(cfg.seed)
    param_key, rng, data_key = jax.random.split(key, 3)
    params = objective.init(param_key)
    opt_state = make_optimizer(cfg).init(params)
    state = TrainState(step=jnp.zeros((), jnp.int32), params=params,
                       ema_params=jax.tree.map(jnp.copy, params), opt_state=opt_state,
                       rng=rng, data_key=data_key)
    # Commit the arrays to the device, as a restored checkpoint's are: jit specialises on
    # committed-ness, so a fresh and a resumed run then share one compiled train step.
    return jax.device_put(state, jax.devices()[0])


def abstract_state(cfg: TrainConfig, objective: Objective | None = None) -> TrainState:
    """Shapes/dtypes of :func:`init_state` without computing anything (a restore target)."""
    return jax.eval_shape(lambda: init_state(cfg, objective=objective))


def step_keys(state: TrainState) -> tuple[jax.Array, jax.Array]:
    """(batch key, noise key) of the step about to be taken: pure functions of (keys, step)."""
    return (jax.random.fold_in(state.data_key, state.step),
            jax.random.fold_in(state.rng, state.step))


# --------------------------------------------------------------------------------------------
# Train step


def _update_fn(cfg: TrainConfig, objective: Objective):
    """The un-jitted update ``(state, batch, key) -> (state, metrics)``."""
    tx = make_optimizer(cfg)
    schedule = make_schedule(cfg)

    def update(state: TrainState, batch: TrainBatch, key: jax.Array):
        _check_step_inputs(state, batch)  # trace time only: shapes are static
        grad_fn = jax.value_and_grad(objective.loss, has_aux=True)
        (loss, aux), grads = grad_fn(state.params, batch, key, True)
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        ema_params = ema_update(state.ema_params, params, cfg.ema_decay)
        metrics = {"loss": loss, "grad_norm": optax.tree.norm(grads),
                   "lr": schedule(state.step), **aux}
        new_state = state.replace(step=state.step + 1, params=params, ema_params=ema_params,
                                  opt_state=opt_state)
        return new_state, metrics

    return update


def _check_step_inputs(state, batch) -> None:
    """Raise ValueError (not an XLA error) for a wrong state type or inconsistent batch shapes."""
    if not isinstance(state, TrainState):
        raise ValueError(f"state must be a TrainState; got {type(state).__name__}")
    if not isinstance(batch, TrainBatch):
        raise ValueError(f"batch must be a tokens.TrainBatch; got {type(batch).__name__}")
    try:
        assert_batch_shapes(batch)
    except AssertionError as err:
        raise ValueError(f"batch has inconsistent shapes: {err}") from None


def make_train_step(cfg: TrainConfig, objective: Objective | None = None):
    """Jitted ``(state, batch, key) -> (state, metrics)``; ``state`` is donated.

    metrics: dict of scalars ``loss``, ``grad_norm``, ``lr`` (of the step taken) plus the
    objective's diagnostics.
    """
    return jax.jit(_update_fn(cfg, objective or objective_for(cfg)), donate_argnums=0)


def default_batch_fn(cfg: TrainConfig) -> BatchFn:
    """``batch_fn(key, scenes)``: B scenes drawn from ``scenes`` with Q queries each.

    Token padding beyond the F + M real tokens is trimmed (exact: padding is masked anyway).
    """
    from flowmaps_jax.flowsim.scenes import make_train_batch

    b, q, sim = cfg.batch_size, cfg.queries_per_scene, cfg.flowsim
    real_tokens = sim.num_furniture + sim.num_objects  # the rest of the S slots is padding

    def batch_fn(key, scenes):
        if cfg.target_noise > 0:
            key, noise_key = jax.random.split(key)
        batch = make_train_batch(key, scenes, b, q, sim, cfg.short_horizon_frac,
                                 cfg.short_horizon_max)
        batch = batch.replace(tokens=trim_padding(batch.tokens, real_tokens))
        if cfg.target_noise > 0:
            batch = batch.replace(target=jitter_targets(noise_key, batch.target,
                                                        cfg.target_noise))
        return batch

    return batch_fn


def jitter_targets(key: jax.Array, boxes: jnp.ndarray, scale: float) -> jnp.ndarray:
    """Boxes (..., 4) moved by ``scale`` × the protocol's ground-truth std
    (:func:`metrics.gt_mixture_sigma`): a draw from the smoothed q around each box at scale 1."""
    from flowmaps_jax import metrics

    centres = to_centre(boxes)
    noise = jax.random.normal(key, boxes.shape, boxes.dtype)
    return from_centre(centres + scale * metrics.gt_mixture_sigma(boxes) * noise)


_CHUNK_SALT = 0x7FFFFFFF


def endless_chunk_steps(cfg: TrainConfig) -> int:
    """With ``data="endless"``, steps served by one chunk of ``train_envs`` fresh environments
    (each environment is then drawn about once)."""
    return max(1, cfg.train_envs // cfg.batch_size)


def endless_scenes(cfg: TrainConfig, data_key: jax.Array, step: int):
    """Fresh FlowSim environments (``cfg.train_envs`` of them) for the chunk holding ``step``.

    Chunk c = step // endless_chunk_steps(cfg) is generated from a key derived from
    (data_key, c) only, so a resumed run regenerates exactly the same environments.
    """
    from flowmaps_jax.flowsim.generate import generate

    chunk = int(step) // endless_chunk_steps(cfg)
    raw = jax.random.fold_in(jax.random.fold_in(data_key, _CHUNK_SALT), chunk)
    # An uncommitted typed key, as the fixed splits use, so that generation and the train step
    # (which specialise on key type and device commitment) reuse their compiled code.
    key = jax.random.wrap_key_data(jnp.asarray(np.asarray(raw)))
    return generate(key, cfg.train_envs, cfg.flowsim)


def make_fused_train_step(cfg: TrainConfig, objective: Objective | None = None,
                          batch_fn: BatchFn | None = None):
    """Jitted ``(state, scenes) -> (state, metrics)``: draws the step's batch and takes the step.

    The batch of step i is ``batch_fn(fold_in(data_key, i), scenes)`` and the noise key
    ``fold_in(rng, i)``, all inside one compiled function (no host round trip); ``state`` is
    donated. ``scenes`` is an argument (not a constant) so it is not baked into the program.
    """
    update = _update_fn(cfg, objective or objective_for(cfg))
    batch_fn = batch_fn or default_batch_fn(cfg)

    def fused(state: TrainState, scenes):
        batch_key, noise_key = step_keys(state)
        return update(state, batch_fn(batch_key, scenes), noise_key)

    return jax.jit(fused, donate_argnums=0)


# --------------------------------------------------------------------------------------------
# Validation


def make_val_batches(cfg: TrainConfig, scenes, batch_fn: BatchFn | None = None) -> TrainBatch:
    """``cfg.val_batches`` fixed batches stacked on a leading axis, drawn with a fixed key.

    Built once per run (not a hot path); each batch reuses the compiled batch sampler.
    """
    batch_fn = batch_fn or default_batch_fn(cfg)
    keys = jax.random.split(jax.random.PRNGKey(cfg.seed + _EVAL_KEY_SALT), cfg.val_batches)
    batches = [batch_fn(key, scenes) for key in keys]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *batches)


def make_eval_loss(cfg: TrainConfig, objective: Objective | None = None):
    """Jitted ``(params, val_batches) -> mean loss`` over stacked batches (leading axis).

    Deterministic: no dropout, and the flow noise of batch j is always ``fold_in(eval_key, j)``,
    so calls at different training steps differ only through ``params`` (pass the EMA params).
    """
    objective = objective or objective_for(cfg)
    eval_key = jax.random.PRNGKey(cfg.seed + _EVAL_KEY_SALT + 1)

    def eval_loss(params, batches: TrainBatch):
        num = jax.tree.leaves(batches)[0].shape[0]
        keys = jax.vmap(lambda j: jax.random.fold_in(eval_key, j))(jnp.arange(num))

        def one(args):
            batch, key = args
            return objective.loss(params, batch, key, False)[0]

        return jnp.mean(jax.lax.map(one, (batches, keys)))

    return jax.jit(eval_loss)
