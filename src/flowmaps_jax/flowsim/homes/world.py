"""The ``Homes`` pytree, its field table (shapes, dtypes, units) and ``validate_homes``.

Sizes: E homes, NR = len(rooms), D door slots, R = NR · receptacles_per_room[1] receptacle
slots, M = objects_per_home[1] object slots, T = num_hours, C = NUM_CONTEXTS. Lengths in
metres; class ids index the config's vocabulary tuples (−1: an unused slot).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from flowmaps_jax.flowsim.homes.config import MAX_METRES, NUM_CONTEXTS, REGIMES, HomesConfig
from flowmaps_jax.flowsim.homes.floorplan import door_pairs
from flowmaps_jax.validation import (
    check_instance,
    check_int_array,
    check_real_array,
    is_concrete,
)

FIELDS: dict[str, tuple[tuple[str, ...], str, str, str]] = {
    "home_size": (("E", "2"), "float32", "m", "footprint (width along x, depth along y)"),
    "room_type": (("E", "NR"), "int32", "", "index into config.room_types"),
    "room_box": (("E", "NR", "4"), "float32", "m", "(x0, y0, x1, y1)"),
    "door_position": (("E", "D", "2"), "float32", "m", "(x, y) on its wall; 0 if no door"),
    "door_rooms": (("E", "D", "2"), "int32", "", "the two rooms a door slot joins"),
    "door_valid": (("E", "D"), "bool", "", "whether the door slot holds a door"),
    "receptacle_class": (("E", "R"), "int32", "", "index into config.receptacle_classes; -1"),
    "receptacle_room": (("E", "R"), "int32", "", "room of the receptacle slot"),
    "receptacle_box": (("E", "R", "6"), "float32", "m", "(cx, cy, cz, w, d, h); 0 if unused"),
    "receptacle_valid": (("E", "R"), "bool", "", "whether the slot holds a receptacle"),
    "receptacle_distance": (("E", "R", "R"), "float32", "m",
                            "geodesic walking distance through doors; 0 if either is unused"),
    "object_class": (("E", "M"), "int32", "", "index into config.object_classes; -1 unused"),
    "object_valid": (("E", "M"), "bool", "", "used and standing on an allowed receptacle"),
    "object_allowed": (("E", "M", "R"), "bool", "", "receptacles the object may stand on"),
    "regime": (("E", "M"), "int32", "", "index into REGIMES"),
    "cycle": (("E", "M", "R"), "int32", "",
              "allowed receptacles clockwise around the home's centre; -1 after them"),
    "num_allowed": (("E", "M"), "int32", "", "number of allowed receptacles"),
    "favourite": (("E", "M", "C"), "int32", "",
                  "preferred receptacle per context (preferences regime); -1 if masked"),
    "receptacle": (("E", "T", "M"), "int32", "",
                   "the object's receptacle at every hour; -1 for masked objects"),
}
"""Field -> (shape symbols, dtype, unit, meaning): the schema of ``Homes`` and of its files."""


@struct.dataclass
class Homes:
    """E generated homes; every field is described in ``FIELDS`` (shapes, dtypes, units)."""

    home_size: jax.Array
    room_type: jax.Array
    room_box: jax.Array
    door_position: jax.Array
    door_rooms: jax.Array
    door_valid: jax.Array
    receptacle_class: jax.Array
    receptacle_room: jax.Array
    receptacle_box: jax.Array
    receptacle_valid: jax.Array
    receptacle_distance: jax.Array
    object_class: jax.Array
    object_valid: jax.Array
    object_allowed: jax.Array
    regime: jax.Array
    cycle: jax.Array
    num_allowed: jax.Array
    favourite: jax.Array
    receptacle: jax.Array

    @property
    def num_homes(self) -> int:
        return self.home_size.shape[0]

    def home(self, index: int) -> Homes:
        """Home ``index`` alone (every field without its leading E axis)."""
        return jax.tree.map(lambda x: x[index], self)

    def as_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


assert tuple(FIELDS) == tuple(f.name for f in dataclasses.fields(Homes))


def sizes(config: HomesConfig, num_homes: int | None = None) -> dict[str, int]:
    """The shape symbols of ``FIELDS`` for ``config`` (E only if ``num_homes`` is given)."""
    out = {"NR": config.num_rooms, "D": config.max_doors, "R": config.max_receptacles,
           "M": config.max_objects, "T": config.num_hours, "C": NUM_CONTEXTS, "2": 2, "4": 4,
           "6": 6}
    if num_homes is not None:
        out["E"] = num_homes
    return out


def field_shape(field: str, dims: dict[str, int], batched: bool = True) -> tuple[int, ...]:
    symbols = FIELDS[field][0]
    return tuple(dims[s] for s in (symbols if batched else symbols[1:]))


def object_boxes(homes: Homes, hour, config: HomesConfig) -> jax.Array:
    """(E, M, 6) float32 object boxes (cx, cy, cz, w, d, h) at ``hour`` (an int, or (E,) ints):
    the class's size, centred on its receptacle's top (objects on one receptacle share its
    centre); 0 for masked objects. Jittable."""
    hour = jnp.broadcast_to(jnp.asarray(hour), homes.home_size.shape[:1])
    where = jnp.take_along_axis(homes.receptacle, hour[:, None, None], axis=1)[:, 0]  # (E, M)
    under = jnp.take_along_axis(homes.receptacle_box, jnp.maximum(where, 0)[..., None], axis=1)
    size = jnp.asarray([o.size for o in config.object_classes], jnp.float32)[
        jnp.maximum(homes.object_class, 0)]  # (E, M, 3)
    centre = jnp.stack([under[..., 0], under[..., 1], under[..., 5] + size[..., 2] / 2], -1)
    box = jnp.concatenate([centre, size], axis=-1)
    return jnp.where(homes.object_valid[..., None], box, 0.0)


def validate_homes(homes, config: HomesConfig, *, batched: bool = True, values: bool = True,
                   name: str = "homes") -> None:
    """``ValueError`` naming the field unless ``homes`` is a well-formed ``Homes`` of ``config``:
    shapes and dtypes always, with ``values`` (concrete) the values too. ``batched``: with the
    leading E axis; ``name``: what the messages call ``homes``.
    """
    check_instance(name, homes, Homes)
    check_instance("config", config, HomesConfig)
    arrays = homes.as_dict()
    first = arrays["home_size"]
    dims = sizes(config, np.shape(first)[0] if batched and np.ndim(first) else 0)
    for field, value in arrays.items():
        expected, dtype = field_shape(field, dims, batched), np.dtype(FIELDS[field][1])
        array = isinstance(value, (np.ndarray, jax.Array))
        if not array or tuple(value.shape) != expected or np.dtype(value.dtype) != dtype:
            got = (f"has shape {tuple(value.shape)} and dtype {value.dtype}" if array
                   else f"is a {type(value).__name__}, not an array")
            raise ValueError(f"{name}.{field} {got}, expected {expected} "
                             f"({', '.join(FIELDS[field][0])} of the config) and {dtype}")
    if not (values and is_concrete(*arrays.values())):
        return
    longest = 2 * MAX_METRES * (config.num_rooms + 1)  # a walk through every room, and more
    for field, high in (("home_size", MAX_METRES), ("room_box", MAX_METRES),
                        ("door_position", MAX_METRES), ("receptacle_box", MAX_METRES),
                        ("receptacle_distance", longest)):
        check_real_array(f"{name}.{field}", arrays[field], low=0.0, high=high, what="metres")
    r = config.max_receptacles
    for field, low, high in (("room_type", 0, len(config.room_types) - 1),
                             ("receptacle_class", -1, len(config.receptacle_classes) - 1),
                             ("object_class", -1, len(config.object_classes) - 1),
                             ("regime", 0, len(REGIMES) - 1),
                             ("receptacle_room", 0, config.num_rooms - 1),
                             ("favourite", None, r - 1),  # indices: below R
                             ("receptacle", None, r - 1), ("cycle", None, r - 1)):
        check_int_array(f"{name}.{field}", arrays[field], low, high)
    a = {k: np.asarray(v) if batched else np.asarray(v)[None] for k, v in arrays.items()}
    box = a["receptacle_box"]
    if np.any(box[..., 3:][a["receptacle_valid"]] <= 0):
        raise ValueError(f"{name}.receptacle_box: receptacle sizes (w, d, h) must be positive")
    room = a["room_box"]
    if np.any(room[..., 2:] <= room[..., :2]):
        raise ValueError(f"{name}.room_box must have x1 > x0 and y1 > y0")
    if np.any(a["door_rooms"] != door_pairs(config)):
        raise ValueError(f"{name}.door_rooms must be the config's door slots (door_pairs)")
    if np.any((a["receptacle_class"] >= 0) != a["receptacle_valid"]):
        raise ValueError(f"{name}.receptacle_valid must mark exactly the slots with a class")
    allowed = a["object_allowed"]
    if np.any(allowed & ~a["receptacle_valid"][:, None, :]) or np.any(
            allowed & ~a["object_valid"][..., None]):
        raise ValueError(f"{name}.object_allowed may only mark receptacles of valid objects")
    if np.any(a["object_valid"] & (a["object_class"] < 0)):
        raise ValueError(f"{name}.object_valid marks an unused object slot")
    num = allowed.sum(-1)
    if np.any(a["num_allowed"] != num) or np.any(a["object_valid"] & (num == 0)):
        raise ValueError(f"{name}.num_allowed must count object_allowed (>= 1 if valid)")
    for field in ("favourite", "receptacle"):
        v = a[field]
        if field == "receptacle":
            v = np.swapaxes(v, 1, 2)  # (E, M, T)
        on = np.take_along_axis(allowed, np.maximum(v, 0), axis=-1)
        valid = a["object_valid"][..., None]
        if np.any(valid & ((v < 0) | ~on)) or np.any(~valid & (v != -1)):
            raise ValueError(f"{name}.{field} must be an allowed receptacle of each valid "
                             f"object (and -1 for masked ones)")
    cyc = a["cycle"]
    used = np.arange(cyc.shape[-1]) < num[..., None]
    if np.any((cyc >= 0) != used) or np.any(
            used & ~np.take_along_axis(allowed, np.maximum(cyc, 0), axis=-1)):
        raise ValueError(f"{name}.cycle must list the allowed receptacles, then -1")
