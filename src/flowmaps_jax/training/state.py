"""Training state and the jitted update: optimiser, EMA, train step, validation loss.

Pure functions of explicit pytrees. :class:`TrainState`: step, params, EMA params, optimiser
state, ``rng`` (dropout, flow noise) and ``data_key`` (batches); step i's batch and noise come
from ``fold_in(data_key, i)`` and ``fold_in(rng, i)``, so a restored state continues exactly.
:func:`make_train_step` / :func:`make_fused_train_step` (the batch drawn inside the same
compiled function) donate the state; :func:`make_eval_loss` scores EMA params on fixed batches
with a fixed key and no dropout. Given a ``mesh``, the state is replicated and each batch split
along its scene axis; the batch is drawn whole from the same key, so the numbers do not depend
on the device count (up to summation order). The family is hidden behind an
:class:`~flowmaps_jax.training.objectives.Objective` (``init`` + ``loss``).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct
from jax.sharding import Mesh

from flowmaps_jax import distributed
from flowmaps_jax.training.config import RUN_CONFIGS, TrainConfig
from flowmaps_jax.training.objectives import Objective, objective_for
from flowmaps_jax.validation import check_instance
from flowmaps_jax.worlds import world

# batch_fn(key, data) -> batch, traceable (the run's world's ``batch_fn``)
BatchFn = Any

_EVAL_NOISE_SALT = 0x5EED + 1
"""The validation passes' flow noise: ``PRNGKey(seed + _EVAL_NOISE_SALT)``, fixed for a run."""

Params = Any


@struct.dataclass
class TrainState:
    """Everything a run needs to continue exactly (all arrays; a pytree).

    step: () int32, optimiser steps taken so far.
    params / ema_params: model parameters and their exponential moving average.
    opt_state: optax state (AdamW moments, schedule count, ...).
    rng: (2,) uint32 PRNG key for dropout and flow noise; step i uses fold_in(rng, i).
    data_key: (2,) uint32 PRNG key for batches; step i draws batch fold_in(data_key, i).
    The keys are raw key data (uint32) so checkpoints store them as plain arrays.
    """

    step: jax.Array
    params: Params
    ema_params: Params
    opt_state: optax.OptState
    rng: jax.Array
    data_key: jax.Array


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
               objective: Objective | None = None, mesh: Mesh | None = None,
               start_params: Params | None = None) -> TrainState:
    """Fresh state at step 0: params from ``key`` (default ``PRNGKey(cfg.seed)``), EMA = params.

    start_params: weights to start from (``cfg.init_from``), laid over the fresh params by
    :func:`overlay_params`. The arrays are committed to the first device, or replicated over
    ``mesh``."""
    check_instance("cfg", cfg, RUN_CONFIGS)
    objective = objective or objective_for(cfg)
    if key is None:
        key = jax.random.PRNGKey(cfg.seed)
    param_key, rng, data_key = jax.random.split(key, 3)
    params = objective.init(param_key)
    if start_params is not None:
        params = overlay_params(params, start_params)
    opt_state = make_optimizer(cfg).init(params)
    state = TrainState(step=jnp.zeros((), jnp.int32), params=params,
                       ema_params=jax.tree.map(jnp.copy, params), opt_state=opt_state,
                       rng=rng, data_key=data_key)
    # Commit the arrays to the device, as a restored checkpoint's are: jit specialises on
    # committed-ness, so a fresh and a resumed run then share one compiled train step.
    if mesh is None:
        return jax.device_put(state, state_sharding(None))
    return distributed.replicate(state, mesh)


def overlay_params(fresh: Params, start: Params, where: str = "init_from") -> Params:
    """``fresh`` with every leaf that ``start`` holds replaced by ``start``'s (a warm start).

    Leaves are matched by their path in the tree. ``start`` may lack leaves of ``fresh`` (they
    keep their fresh value: e.g. the age embedding a history model adds to a one-map model);
    every leaf it holds must be one of ``fresh`` with the same shape, else ValueError naming
    ``where`` (the weights belong to another architecture). Traceable: ``jax.eval_shape`` of it
    is the check alone (``training.loop`` runs it before anything is written)."""
    fresh_shapes = {path: tuple(x.shape)
                    for path, x in jax.tree_util.tree_flatten_with_path(fresh)[0]}
    start_leaves = jax.tree_util.tree_flatten_with_path(start)[0]
    unfit = [(path, tuple(value.shape)) for path, value in start_leaves
             if fresh_shapes.get(path) != tuple(value.shape)]
    if unfit:
        path, shape = unfit[0]
        name, want = jax.tree_util.keystr(path), fresh_shapes.get(path)
        raise ValueError(f"{where}: the model has no parameter {name} ({len(unfit)} unmatched); "
                         f"the weights are another architecture" if want is None else
                         f"{where}: parameter {name} has shape {shape}, the model's is {want}")
    by_path = dict(start_leaves)
    return jax.tree_util.tree_map_with_path(
        lambda path, x: jnp.asarray(by_path[path], x.dtype) if path in by_path else x, fresh)


def state_sharding(mesh: Mesh | None) -> jax.sharding.Sharding:
    """Where a TrainState lives: replicated over ``mesh``, or on this process's first device."""
    if mesh is None:
        return jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    return distributed.replicated(mesh)


def abstract_state(cfg: TrainConfig, objective: Objective | None = None,
                   mesh: Mesh | None = None) -> TrainState:
    """Shapes, dtypes and shardings of :func:`init_state` without computing anything: the
    restore target of a checkpoint. The sharding is that of this process (``mesh`` or the first
    device), not the one the checkpoint was saved with, so a state saved on N devices restores
    on any other number."""
    shapes = jax.eval_shape(lambda: init_state(cfg, objective=objective))
    sharding = state_sharding(mesh)
    return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding),
                        shapes)


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
    check_batch = world(cfg.world).check_batch

    def update(state: TrainState, batch, key: jax.Array):
        # At trace time (shapes are static): a wrong batch is a ValueError naming the array.
        check_instance("state", state, TrainState)
        check_batch(batch)
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


def make_train_step(cfg: TrainConfig, objective: Objective | None = None,
                    mesh: Mesh | None = None):
    """Jitted ``(state, batch, key) -> (state, metrics)``; ``state`` is donated.

    metrics: dict of scalars ``loss``, ``grad_norm``, ``lr`` (of the step taken) plus the
    objective's diagnostics. With ``mesh``, ``batch`` is a global array split over the mesh by
    scenes (multi-host runs assemble it from each host's share) and the state is replicated.
    """
    update = _update_fn(cfg, objective or objective_for(cfg))
    if mesh is None:
        return jax.jit(update, donate_argnums=0)
    rep, rows = distributed.replicated(mesh), distributed.batch_sharding(mesh)
    return jax.jit(update, donate_argnums=0, in_shardings=(rep, rows, rep),
                   out_shardings=(rep, rep))


def make_fused_train_step(cfg: TrainConfig, objective: Objective | None = None,
                          batch_fn: BatchFn | None = None, mesh: Mesh | None = None):
    """Jitted ``(state, scenes) -> (state, metrics)``: draws the step's batch and takes the step.

    The batch of step i is ``batch_fn(fold_in(data_key, i), scenes)`` and the noise key
    ``fold_in(rng, i)``, all inside one compiled function (no host round trip); ``state`` is
    donated. ``scenes`` is an argument (not a constant) so it is not baked into the program.
    With ``mesh``, state and scenes are replicated and the drawn batch is split over the
    devices by scenes (one host; multi-host runs use :func:`make_train_step`).
    """
    update = _update_fn(cfg, objective or objective_for(cfg))
    batch_fn = batch_fn or world(cfg.world).batch_fn(cfg)

    def fused(state: TrainState, scenes):
        batch_key, noise_key = step_keys(state)
        batch = batch_fn(batch_key, scenes)
        if mesh is not None:
            batch = jax.lax.with_sharding_constraint(batch, distributed.batch_sharding(mesh))
        return update(state, batch, noise_key)

    if mesh is None:
        return jax.jit(fused, donate_argnums=0)
    rep = distributed.replicated(mesh)
    return jax.jit(fused, donate_argnums=0, in_shardings=(rep, rep), out_shardings=(rep, rep))


# --------------------------------------------------------------------------------------------
# Validation


def make_eval_loss(cfg: TrainConfig, objective: Objective | None = None,
                   mesh: Mesh | None = None):
    """Jitted ``(params, val_batches) -> mean loss`` over stacked batches (leading axis): the
    objective's ``selection`` diagnostic where it has one (the mixture head's table
    cross-entropy, which tracks the posterior), else its loss. The ``best`` checkpoint is the
    step where this is lowest.

    Deterministic: no dropout, and the flow noise of batch j is always ``fold_in(eval_key, j)``,
    so calls at different training steps differ only through ``params`` (pass the EMA params).
    With ``mesh``, params are replicated and each batch is split over the devices by scenes.
    """
    objective = objective or objective_for(cfg)
    eval_key = jax.random.PRNGKey(cfg.seed + _EVAL_NOISE_SALT)

    def eval_loss(params, batches):
        num = jax.tree.leaves(batches)[0].shape[0]
        keys = jax.vmap(lambda j: jax.random.fold_in(eval_key, j))(jnp.arange(num))

        def one(args):
            batch, key = args
            if mesh is not None:
                batch = jax.lax.with_sharding_constraint(batch,
                                                         distributed.batch_sharding(mesh))
            loss, aux = objective.loss(params, batch, key, False)
            return aux.get("selection", loss)  # the family's checkpoint-selection criterion

        return jnp.mean(jax.lax.map(one, (batches, keys)))

    if mesh is None:
        return jax.jit(eval_loss)
    rep = distributed.replicated(mesh)
    return jax.jit(eval_loss, in_shardings=(rep, rep), out_shardings=rep)
