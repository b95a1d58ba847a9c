"""Receptacles placed in rooms by type, dynamic objects on the receptacles they may stand on,
and each object's cycle (docs/flowsim.md, "Homes"). One home; receptacle index k · S + s for
slot s of room k, a box (cx, cy, cz, w, d, h) m; unused slots: class −1; an object whose class
can stand on nothing here is masked out (``object_valid`` False).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from flowmaps_jax.flowsim.homes.config import HomesConfig
from flowmaps_jax.flowsim.homes.floorplan import split_uniforms


def receptacle_uniforms(config: HomesConfig) -> dict[str, tuple[int, ...]]:
    """The uniforms ``place_receptacles`` reads, by name and shape."""
    nr, s = config.num_rooms, config.receptacles_per_room[1]
    return {"count": (nr,), "class": (nr, len(config.receptacle_classes)), "cell": (nr, 4),
            "size": (nr, s, 3), "position": (2, nr, s)}


def object_uniforms(config: HomesConfig) -> dict[str, tuple[int, ...]]:
    """The uniforms ``place_objects`` reads, by name and shape."""
    return {"count": (), "class": (len(config.object_classes),)}


def place_receptacles(u, room_type, room_box, config: HomesConfig) -> dict:
    """Receptacles of one home from uniforms u (``receptacle_uniforms``, flat). room_type (NR,)
    int32, room_box (NR, 4) float32.

    Returns receptacle_class (R,) int32 (−1 unused), receptacle_room (R,) int32,
    receptacle_box (R, 6) float32 (cx, cy, cz, w, d, h) m, receptacle_valid (R,) bool.
    """
    nr, s = config.num_rooms, config.receptacles_per_room[1]
    lo, hi = config.receptacles_per_room
    u = split_uniforms(u, receptacle_uniforms(config))
    allows = jnp.asarray(np.asarray(config.room_allows(), bool))[room_type]  # (NR, NC)
    count = lo + jnp.floor(u["count"] * (hi - lo + 1)).astype(jnp.int32)
    count = jnp.minimum(count, jnp.sum(allows, axis=-1))
    score = jnp.where(allows, u["class"], -1.0)
    cls = jnp.argsort(-score, axis=-1)[:, :s].astype(jnp.int32)  # (NR, S)
    valid = jnp.arange(s)[None, :] < count[:, None]
    cell = jnp.argsort(u["cell"], axis=-1)[:, :s]  # distinct cells
    room_w = (room_box[:, 2] - room_box[:, 0])[:, None] / 2  # cell sides (NR, 1)
    room_d = (room_box[:, 3] - room_box[:, 1])[:, None] / 2
    x0 = room_box[:, 0, None] + (cell % 2) * room_w
    y0 = room_box[:, 1, None] + (cell // 2) * room_d
    sizes = jnp.asarray([r.size for r in config.receptacle_classes], jnp.float32)[cls]
    sizes = sizes * (1.0 + config.size_jitter * (2 * u["size"] - 1))
    w, d, h = sizes[..., 0], sizes[..., 1], sizes[..., 2]
    turn = (room_d > room_w) != (d > w)  # longer footprint side along the cell's longer side
    w, d = jnp.where(turn, d, w), jnp.where(turn, w, d)
    m = config.wall_margin
    w, d = jnp.minimum(w, room_w - 2 * m), jnp.minimum(d, room_d - 2 * m)
    cx = x0 + m + w / 2 + u["position"][0] * (room_w - 2 * m - w)
    cy = y0 + m + d / 2 + u["position"][1] * (room_d - 2 * m - d)
    box = jnp.stack([cx, cy, h / 2, w, d, h], axis=-1)
    valid = valid.reshape(-1)
    return {"receptacle_class": jnp.where(valid, cls.reshape(-1), -1),
            "receptacle_room": jnp.repeat(jnp.arange(nr, dtype=jnp.int32), s),
            "receptacle_box": jnp.where(valid[:, None], box.reshape(-1, 6), 0.0),
            "receptacle_valid": valid}


def place_objects(u, receptacle_class, receptacle_valid, config: HomesConfig) -> dict:
    """Objects of one home from uniforms u (``object_uniforms``, flat): object_class (M,) int32
    (−1 unused), object_valid (M,) bool, object_allowed (M, R) bool (receptacles it may stand
    on; all False if masked)."""
    u = split_uniforms(u, object_uniforms(config))
    allows = jnp.asarray(np.asarray(config.object_allows(), bool))  # (K, NC)
    on = allows[:, jnp.maximum(receptacle_class, 0)] & receptacle_valid[None, :]  # (K, R)
    placeable = jnp.any(on, axis=-1)
    lo, hi = config.objects_per_home
    count = lo + jnp.floor(u["count"] * (hi - lo + 1)).astype(jnp.int32)
    score = u["class"] + placeable.astype(jnp.float32)
    cls = jnp.argsort(-score)[:config.max_objects].astype(jnp.int32)
    used = jnp.arange(config.max_objects) < count
    valid = used & placeable[cls]
    return {"object_class": jnp.where(used, cls, -1), "object_valid": valid,
            "object_allowed": on[cls] & valid[:, None]}


def cycles(object_allowed, receptacle_box, home_size) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(cycle (M, R) int32 allowed receptacles clockwise around the home's centre, −1 after
    them; num_allowed (M,) int32)."""
    offset = receptacle_box[:, :2] - home_size / 2
    angle = jnp.mod(jnp.arctan2(offset[:, 0], offset[:, 1]), 2 * jnp.pi)  # 0 along +y
    key = jnp.where(object_allowed, angle[None, :], jnp.inf)
    order = jnp.argsort(key, axis=-1, stable=True).astype(jnp.int32)
    num = jnp.sum(object_allowed, axis=-1).astype(jnp.int32)
    return jnp.where(jnp.arange(order.shape[-1]) < num[:, None], order, -1), num
