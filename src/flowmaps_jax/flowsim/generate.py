"""FlowSim scenes: the ``Scenes`` pytree and ``generate(key, num_envs, config)``. An
environment's content depends only on its own key (``jax.random.split(key, num_envs)``), never on
the batch it was generated in (docs/flowsim.md)."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.sharding import Mesh

from flowmaps_jax import distributed
from flowmaps_jax.flowsim import dynamics, habits, layout
from flowmaps_jax.flowsim.config import (
    DEFAULT_CONFIG,
    FlowSimConfig,
    SimShape,
    sim_params,
    sim_shape,
)
from flowmaps_jax.resources import array_bytes, check_request_size, computed_rows, first_rows
from flowmaps_jax.validation import (
    check_array,
    check_instance,
    check_int,
    check_int_array,
    check_key,
    check_real_array,
    is_concrete,
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
    habit: (E, M) int32 each object's index into ``habits.hypothesis_table(F)`` (0: routine).
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
    habit: jnp.ndarray

    @property
    def num_envs(self) -> int:
        return self.furniture_boxes.shape[0]


_FIELDS = tuple(field.name for field in dataclasses.fields(Scenes))
_FLOAT_FIELDS = ("furniture_boxes", "object_size", "object_boxes")


def _field_shapes(e: int, f: int, m: int, t: int) -> dict[str, tuple[int, ...]]:
    """Each field's shape for E environments, F furniture pieces, M objects, T timesteps."""
    return {"furniture_boxes": (e, f, 4), "furniture_kind": (e, f), "object_kind": (e, m),
            "object_size": (e, m), "visit_order": (e, m, f), "num_slots": (e, m),
            "slot": (e, t, m), "object_boxes": (e, t, m, 4), "layout_redraws": (e,),
            "habit": (e, m)}


def scenes_bytes_per_env(config: FlowSimConfig) -> int:
    """Bytes of one environment's ``Scenes`` arrays (a lower bound per environment)."""
    shapes = _field_shapes(1, config.num_furniture, config.num_objects, config.num_timesteps)
    return sum(array_bytes(shape) for shape in shapes.values())


def layout_bytes(config: FlowSimConfig, num_envs: int) -> int:
    """Working memory of laying out ``num_envs`` environments (a block of :data:`BLOCK`)."""
    words = layout.layout_num_words(config)
    return min(int(num_envs), BLOCK) * words * 4 * (4 + config.num_furniture)


def validate_scenes(scenes, config: FlowSimConfig | None = None, *, values: bool = True,
                    name: str = "scenes") -> None:
    """Raise ``ValueError`` naming the field if ``scenes`` is not a well-formed ``Scenes``:
    dtypes and shapes always (F, M, T of ``config`` when given), and with ``values`` (concrete
    arrays) the value ranges (boxes in the map, ids of the config, orders, slots).
    """
    if config is not None:
        check_instance("config", config, FlowSimConfig)
    check_instance(name, scenes, Scenes)
    f, m, t = ((None, None, None) if config is None
               else (config.num_furniture, config.num_objects, config.num_timesteps))

    def field(key: str, shape: tuple) -> tuple[int, ...]:
        value, where = getattr(scenes, key), f"{name}.{key}"
        if value is not None:
            check_array(where, value)
        if key in _FLOAT_FIELDS:
            return check_real_array(where, value, shape, finite=False).shape
        return check_int_array(where, value, shape=shape).shape

    e, f = field("furniture_boxes", (None, f, 4))[:2]
    field("furniture_kind", (e, f))
    m = field("object_kind", (e, m))[1]
    field("object_size", (e, m))
    field("visit_order", (e, m, f))
    field("num_slots", (e, m))
    t = field("slot", (e, t, m))[1]
    field("object_boxes", (e, t, m, 4))
    field("layout_redraws", (e,))
    field("habit", (e, m))
    arrays = [getattr(scenes, key) for key in _FIELDS]
    if values and is_concrete(*arrays):
        _check_values(name, {key: np.asarray(v) for key, v in zip(_FIELDS, arrays, strict=True)},
                      config)


def _check_values(name: str, a: dict[str, np.ndarray], config: FlowSimConfig | None) -> None:
    """The values part of :func:`validate_scenes`, on numpy arrays ``a`` of checked shapes."""
    f = a["furniture_boxes"].shape[1]
    for key in ("furniture_boxes", "object_boxes"):
        check_real_array(f"{name}.{key}", a[key], low=0,
                         high=None if config is None else config.map_size,
                         what="px, within the map")
    _check_positive(f"{name}.object_size", a["object_size"])
    check_int_array(f"{name}.num_slots", a["num_slots"], 1, f)
    check_int_array(f"{name}.visit_order", a["visit_order"], -1, f - 1)
    check_int_array(f"{name}.layout_redraws", a["layout_redraws"], 0)
    check_int_array(f"{name}.habit", a["habit"], 0, habits.num_hypotheses(f) - 1)
    for key in ("furniture_boxes", "object_boxes"):
        _check_positive(f"{name}.{key}", a[key][..., 2:] - a[key][..., :2],
                        " in y1 - y0 and x1 - x0 (y0, x0, y1, x1): y1 > y0, x1 > x0")
    for key, entries in (() if config is None else (
            ("furniture_kind", config.furniture_kinds), ("object_kind", config.categories))):
        known = [entry.descriptor for entry in entries]
        if not np.all(np.isin(a[key], known)):
            raise ValueError(f"{name}.{key} holds descriptor ids outside {known}")
    if np.any((a["visit_order"] >= 0) != (np.arange(f) < a["num_slots"][..., None])):
        raise ValueError(f"{name}.visit_order must hold furniture indices on exactly the first "
                         f"num_slots places and -1 after them")
    check_int_array(f"{name}.slot", a["slot"], 0, a["num_slots"][:, None, :] - 1,
                    high_name="num_slots - 1")


def _check_positive(name: str, values: np.ndarray, what: str = "") -> None:
    """Every value of the finite real array ``values`` > 0 (``what`` follows "positive")."""
    check_real_array(name, values)
    if values.size and np.min(values) <= 0:
        raise ValueError(f"{name} must be positive{what}; got a minimum of {np.min(values)}")


BLOCK = 512
"""Layout attempts run in blocks of this many environments inside one ``lax.while_loop``: first
attempts, then redraws of the failed ones."""


def _place_furniture(layout_keys, params, shape: SimShape):
    """Layouts for per-environment keys (E,), attempt a from ``fold_in(layout_keys[e], a)``.
    Returns (boxes (F, 4, E) int32, kind (F, E) int32, redraws (E,) int32, ok (E,) bool)."""
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
    """(Scenes, ok (E,) bool) for one PRNG key per environment (E,); ``params`` / ``shape``:
    ``sim_params`` / ``sim_shape``. Does not raise: check ``ok``."""
    num_envs = env_keys.shape[0]
    layout_keys = jax.vmap(jax.random.fold_in, in_axes=(0, None))(env_keys, 0)
    dynamics_keys = jax.vmap(jax.random.fold_in, in_axes=(0, None))(env_keys, 1)
    boxes, kind, redraws, ok = _place_furniture(layout_keys, params, shape)

    order, num_slots = layout.visit_orders(boxes, kind, params, shape)
    size = layout.object_sizes(boxes, order, params)
    if shape.habits:
        slot, habit = _habit_rollouts(env_keys, boxes, order, num_slots, params, shape)
    else:  # the paper's world, bit for bit as before habits existed
        words = layout.random_words(dynamics_keys, dynamics.rollout_num_words(shape))
        slot = dynamics.rollout(words, num_slots, params, shape)
        habit = jnp.zeros((shape.num_objects, num_envs), jnp.int32)
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
        habit=habit.T,
    )
    return scenes, ok


def _habit_rollouts(env_keys, boxes, order, num_slots, params, shape: SimShape):
    """(slot (T, M, E), habit (M, E)) of every object, from ``fold_in(env_key, 2)``."""
    num_words = habits.rollout_num_words(shape.num_timesteps)
    keys = jax.vmap(jax.random.fold_in, in_axes=(0, None))(env_keys, 2)
    words = jax.vmap(lambda k: jax.random.bits(k, (shape.num_objects, num_words),
                                               jnp.uint32))(keys)  # (E, M, W)
    centre = layout.box_centres(boxes, axis=1) / params["map_size"].astype(jnp.float32)
    table = jnp.maximum(order, 0)  # (M, F, E)
    slot_centres = jnp.take_along_axis(centre[None], table[:, :, None, :], axis=1)  # (M,F,2,E)
    slot_centres = jnp.transpose(slot_centres, (3, 0, 1, 2))  # (E, M, F, 2)
    one = functools.partial(habits.habit_rollout, params=params,
                            num_timesteps=shape.num_timesteps, families=shape.habit_families,
                            max_places=shape.max_places)
    slot, habit = jax.vmap(jax.vmap(one))(words, num_slots.T, slot_centres)  # (E, M, T), (E, M)
    return jnp.transpose(slot, (2, 1, 0)), habit.T


def generate(key, num_envs: int, config: FlowSimConfig = DEFAULT_CONFIG, *, mesh=None,
             part: slice | None = None) -> Scenes:
    """Generate ``num_envs`` FlowSim environments (layouts, visiting orders, T-step rollouts).

    mesh: a 1-D device mesh to split the environments over (same result). part: only these
    environments (a slice); they equal the same rows of the full set. ValueError on bad
    arguments or too much memory; :class:`LayoutError` if some layout could not be placed. Not
    inside ``jit`` (use ``scenes_from_env_keys``).
    """
    key = check_key(key)
    num_envs = check_int("num_envs", num_envs)
    check_instance("config", config, FlowSimConfig)
    if mesh is not None:
        check_instance("mesh", mesh, Mesh)
    if part is not None:
        check_instance("part", part, slice)
    count = num_envs
    if part is not None:
        count = len(range(num_envs)[part])
        if count == 0:
            raise ValueError(f"part={part} selects no environment of {num_envs}")
    check_request_size(f"generate({count} environments, layout_candidates="
                       f"{config.layout_candidates})",
                       count * scenes_bytes_per_env(config) + layout_bytes(config, count))
    if part is None:  # a small request as SMALL_REQUEST environments: one program for all
        rows = count if mesh is not None else computed_rows(
            count, scenes_bytes_per_env(config) + layout_bytes(config, 1))
        scenes, ok = first_rows(_generate_on(jax.random.split(key, rows), config, mesh), count)
    else:
        scenes, ok = _generate_on(jax.random.split(key, num_envs)[part], config, mesh)
    failed = int(np.sum(~np.asarray(ok)))
    if failed:
        raise LayoutError(
            f"generate: {failed} of {count} layouts could not be placed within "
            f"layout_budget={config.layout_budget} redraws; the map is too crowded for "
            f"num_furniture={config.num_furniture} tables of up to {config.table_max_frac} of "
            f"map_size={config.map_size} (raise map_size/layout_budget/layout_candidates or "
            "lower num_furniture/table_max_frac)")
    return scenes


class LayoutError(ValueError, RuntimeError):
    """Some layouts could not be placed within ``config.layout_budget`` redraws (a bad argument:
    ValueError; also a RuntimeError)."""


def _generate_on(env_keys, config: FlowSimConfig, mesh):
    """``scenes_from_env_keys`` on one device, or each device its block of keys over ``mesh``."""
    params, shape = sim_params(config), sim_shape(config)
    if mesh is None or mesh.size == 1:
        return scenes_from_env_keys(env_keys, params, shape)
    num_envs = env_keys.shape[0]
    scenes, ok = _sharded_generator(mesh, shape)(distributed.shard_rows(env_keys, mesh), params)
    return jax.tree.map(lambda x: x[:num_envs], (scenes, ok))


@functools.lru_cache(maxsize=8)
def _sharded_generator(mesh, shape: SimShape):
    from jax.sharding import PartitionSpec

    def local(keys, params):  # one device's block of environments, a plain local program
        return scenes_from_env_keys(keys, params, shape)

    rows = PartitionSpec(distributed.DATA_AXIS)
    return jax.jit(jax.shard_map(local, mesh=mesh, in_specs=(rows, PartitionSpec()),
                                 out_specs=rows, check_vma=False))
