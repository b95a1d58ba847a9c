"""FlowSim scenes: the ``Scenes`` pytree and ``generate(key, num_envs, config)``.

Every environment gets its own key (``jax.random.split(key, num_envs)``); its layout attempts use
``fold_in(layout_key, attempt)``, so an environment's content depends only on its own key, never on
the batch it was generated in. Layout attempts run in fixed-size blocks of environments inside one
``lax.while_loop``: first every environment's first attempt, then the (about 10 %) failed ones
are redrawn until all succeed or ``config.layout_budget`` redraws are used up (then ``generate``
raises). Visiting orders and rollouts (``lax.scan`` over time, see ``dynamics.rollout``) are
vectorised over the whole batch.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from flowmaps_jax.flowsim import dynamics, layout
from flowmaps_jax.flowsim.config import (
    DEFAULT_CONFIG,
    FlowSimConfig,
    SimShape,
    sim_params,
    sim_shape,
)


@struct.dataclass
class Scenes:
    """E environments with F furniture pieces, M objects (one per category), T timesteps.

    furniture_boxes: (E, F, 4) float32 pixels (y0, x0, y1, x1), y1/x1 exclusive (h = y1 - y0).
    furniture_kind: (E, F) int32 descriptor id of each piece's furniture kind.
    object_kind: (E, M) int32 descriptor id of each object (category order of the config).
    object_size: (E, M) float32 side of each object's square box in pixels.
    visit_order: (E, M, F) int32 furniture indices in visiting order, padded with -1.
    num_slots: (E, M) int32 number of valid entries in visit_order (furniture of that kind).
    slot: (E, T, M) int32 position along visit_order at each timestep (0 at t = 0).
    object_boxes: (E, T, M, 4) float32 pixels (y0, x0, y1, x1), centred on the current table.
    layout_redraws: (E,) int32 how many times each environment's layout was redrawn.
    """

    furniture_boxes: jnp.ndarray
    furniture_kind: jnp.ndarray
    object_kind: jnp.ndarray
    object_size: jnp.ndarray
    visit_order: jnp.ndarray
    num_slots: jnp.ndarray
    slot: jnp.ndarray
    object_boxes: jnp.ndarray
    layout_redraws: jnp.ndarray

    @property
    def num_envs(self) -> int:
        return self.furniture_boxes.shape[0]


BLOCK = 512
"""Layout attempts run in blocks of this many environments inside one ``lax.while_loop``: first
the blocks of first attempts, then blocks of redraws of the failed ones. One block shape means
one compiled attempt, and a block's working set stays in cache."""


def _place_furniture(layout_keys, params, shape: SimShape):
    """Layouts for per-environment keys (E,), redrawing failed attempts (environment axis last).

    Attempt a of environment e uses ``fold_in(layout_keys[e], a)``, so the result does not depend
    on the batch. Returns (boxes (F, 4, E) int32, kind (F, E) int32 kind index, redraws (E,)
    int32, ok (E,) bool — False only if ``layout_budget`` redraws did not suffice).
    """
    num_envs = layout_keys.shape[0]
    block = min(num_envs, BLOCK)
    num_words = layout.layout_num_words(shape)
    lanes = jnp.arange(block)

    def pending(attempts, ok):
        return ~ok & (attempts >= 1) & (attempts <= params["layout_budget"])

    def cond(state):
        cursor, _, _, attempts, ok = state
        return (cursor < num_envs) | jnp.any(pending(attempts, ok))

    def body(state):
        cursor, boxes, kind, attempts, ok = state
        index = jax.lax.cond(
            cursor < num_envs,
            lambda: cursor + lanes,  # next block of first attempts
            lambda: jnp.nonzero(pending(attempts, ok), size=block, fill_value=num_envs)[0])
        index = jnp.where(index < num_envs, index, num_envs)  # out of range: dropped below
        safe = jnp.minimum(index, num_envs - 1)
        keys = jax.vmap(jax.random.fold_in)(layout_keys[safe], attempts[safe])
        new_boxes, new_kind, new_ok = layout.attempt_layouts(
            layout.random_words(keys, num_words), params, shape)
        return (cursor + block,
                boxes.at[:, :, index].set(new_boxes, mode="drop"),
                kind.at[:, index].set(new_kind, mode="drop"),
                attempts.at[index].add(1, mode="drop"),
                ok.at[index].set(new_ok, mode="drop"))

    f = shape.num_furniture
    state = (jnp.int32(0), jnp.zeros((f, 4, num_envs), jnp.int32),
             jnp.zeros((f, num_envs), jnp.int32), jnp.zeros((num_envs,), jnp.int32),
             jnp.zeros((num_envs,), bool))
    _, boxes, kind, attempts, ok = jax.lax.while_loop(cond, body, state)
    return boxes, kind, attempts - 1, ok


@functools.partial(jax.jit, static_argnames=("shape",))
def scenes_from_env_keys(env_keys, params, shape: SimShape):
    """Scenes for one PRNG key per environment (E,). Returns (Scenes, ok (E,) bool).

    Environment e depends only on ``env_keys[e]`` (not on E or its position in the batch).
    ``params`` / ``shape``: ``sim_params`` / ``sim_shape`` of the config. Does not raise:
    check ``ok`` (``generate`` does).
    """
    num_envs = env_keys.shape[0]
    layout_keys = jax.vmap(jax.random.fold_in, in_axes=(0, None))(env_keys, 0)
    dynamics_keys = jax.vmap(jax.random.fold_in, in_axes=(0, None))(env_keys, 1)
    boxes, kind, redraws, ok = _place_furniture(layout_keys, params, shape)

    order, num_slots = layout.visit_orders(boxes, kind, params, shape)
    size = layout.object_sizes(boxes, order, params)
    words = layout.random_words(dynamics_keys, dynamics.rollout_num_words(shape))
    slot = dynamics.rollout(words, num_slots, params, shape)
    # From here on environment-first (the public layout); object boxes are a gather.
    boxes, order, slot, size = (jnp.transpose(boxes, (2, 0, 1)), jnp.transpose(order, (2, 0, 1)),
                                jnp.transpose(slot, (2, 0, 1)), size.T)
    scenes = Scenes(
        furniture_boxes=boxes.astype(jnp.float32),
        furniture_kind=params["kind_descriptor"][kind.T],
        object_kind=jnp.broadcast_to(params["category_descriptor"],
                                     (num_envs, shape.num_objects)).astype(jnp.int32),
        object_size=size,
        visit_order=order,
        num_slots=num_slots.T,
        slot=slot,
        object_boxes=jax.vmap(layout.object_boxes)(boxes, order, slot, size),
        layout_redraws=redraws,
    )
    return scenes, ok


def check_key(key) -> jax.Array:
    """A single PRNG key as a typed key; ``ValueError`` naming ``key`` otherwise."""
    if isinstance(key, jax.Array) and jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        if key.shape != ():
            raise ValueError(f"key must be a single PRNG key; got shape {key.shape}")
        return key
    shape, dtype = getattr(key, "shape", None), getattr(key, "dtype", None)
    if shape != (2,) or dtype != np.uint32:
        raise ValueError("key must be a JAX PRNG key (jax.random.key(seed) or "
                         f"jax.random.PRNGKey(seed)); got {type(key).__name__} "
                         f"with shape {shape} and dtype {dtype}")
    return jax.random.wrap_key_data(jnp.asarray(key))  # legacy raw key -> typed key


def generate(key, num_envs: int, config: FlowSimConfig = DEFAULT_CONFIG) -> Scenes:
    """Generate ``num_envs`` FlowSim environments (layouts, visiting orders, T-step rollouts).

    key: a JAX PRNG key; the same key, num_envs and config give the same Scenes.
    Raises ``ValueError`` on bad arguments and ``RuntimeError`` if some layout could not be
    placed within ``config.layout_budget`` redraws (the config is too crowded). Not for use
    inside ``jit`` (it checks the layouts on the host); there, call ``scenes_from_env_keys``.
    """
    if not isinstance(config, FlowSimConfig):
        raise ValueError(f"config must be a FlowSimConfig; got {type(config).__name__}")
    if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
        raise ValueError(f"num_envs must be a positive int; got {num_envs!r}")
    key = check_key(key)
    env_keys = jax.random.split(key, int(num_envs))
    scenes, ok = scenes_from_env_keys(env_keys, sim_params(config), sim_shape(config))
    failed = int(np.sum(~np.asarray(ok)))
    if failed:
        raise RuntimeError(
            f"generate: {failed} of {num_envs} layouts could not be placed within "
            f"layout_budget={config.layout_budget} redraws; the map is too crowded for "
            f"num_furniture={config.num_furniture} tables of up to {config.table_max_frac} of "
            f"map_size={config.map_size} (raise map_size/layout_budget/layout_candidates or "
            "lower num_furniture/table_max_frac)")
    return scenes
