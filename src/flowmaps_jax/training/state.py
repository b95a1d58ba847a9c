"""Training state and the jitted update: optimiser, EMA, train step, validation loss. Step i's
batch and noise come from ``fold_in(data_key, i)`` and ``fold_in(rng, i)``, so a restored state
continues exactly; with a ``mesh`` the state is replicated and each batch split by scenes."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct
from jax.sharding import Mesh

from flowmaps_jax import distributed
from flowmaps_jax.training.config import TrainConfig, run_configs
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
    """Everything a run needs to continue exactly: step () int32, params / ema_params,
    opt_state (optax), rng and data_key (2,) uint32 raw PRNG keys (noise and batches)."""

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
    """Fresh state at step 0 from ``key`` (default ``PRNGKey(cfg.seed)``), EMA = params, with
    ``start_params`` laid over (:func:`overlay_params`); on the first device or over ``mesh``."""
    check_instance("cfg", cfg, run_configs())
    objective = objective or objective_for(cfg)
    if key is None:
        key = jax.random.PRNGKey(cfg.seed)
    param_key, rng, data_key = jax.random.split(key, 3)
    params = objective.init(param_key)
    if start_params is not None:
        params = overlay_params(params, start_params)
    opt_state = make_optimizer(cfg).init(params)
    state = TrainState(step=jnp.zeros((), jnp.int32), params=params,  # EMA: a copy, no program
                       ema_params=jax.device_put(params, may_alias=False), opt_state=opt_state,
                       rng=rng, data_key=data_key)
    # Committed, as a restored state is: fresh and resumed runs share one compiled step.
    if mesh is None:
        return jax.device_put(state, state_sharding(None))
    return distributed.replicate(state, mesh)


def overlay_params(fresh: Params, start: Params, where: str = "init_from") -> Params:
    """``fresh`` with every leaf ``start`` holds (matched by path) replaced by ``start``'s;
    leaves ``start`` lacks keep their fresh value. A leaf not in ``fresh`` or of another shape is
    a ValueError naming ``where``. Traceable (``jax.eval_shape`` of it is the check alone)."""
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
    """Shapes, dtypes and this process's shardings of :func:`init_state`: a restore target."""
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
    """Jitted ``(state, batch, key) -> (state, metrics)``, ``state`` donated; metrics: scalars
    ``loss``, ``grad_norm``, ``lr`` and the objective's diagnostics."""
    update = _update_fn(cfg, objective or objective_for(cfg))
    if mesh is None:
        return jax.jit(update, donate_argnums=0)
    rep, rows = distributed.replicated(mesh), distributed.batch_sharding(mesh)
    return jax.jit(update, donate_argnums=0, in_shardings=(rep, rows, rep),
                   out_shardings=(rep, rep))


def make_fused_train_step(cfg: TrainConfig, objective: Objective | None = None,
                          batch_fn: BatchFn | None = None, mesh: Mesh | None = None):
    """Jitted ``(state, scenes) -> (state, metrics)``: draws step i's batch
    ``batch_fn(fold_in(data_key, i), scenes)`` and takes the step in one program (one host)."""
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
    """Jitted ``(params, val_batches) -> mean loss`` over stacked batches: the objective's
    ``selection`` diagnostic where it has one, else its loss (the ``best`` checkpoint's
    criterion). Deterministic: no dropout, batch j's noise ``fold_in(eval_key, j)``.
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
