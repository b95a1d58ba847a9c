"""Furniture placement (vectorised rejection sampling), visiting orders and object boxes
(docs/flowsim.md). Batch functions over E environments with the environment axis LAST (boxes
(F, 4, E)); the config is split into a static ``shape`` and traceable ``params``. Each 32-bit
random word gives two 16-bit draws mapped by ``(bits * n) >> 16``.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from flowmaps_jax.boxes import centred_squares, corner_centres
from flowmaps_jax.flowsim.config import SimShape

Params = dict  # numeric config part: see config.sim_params


def candidate_counts(shape: SimShape) -> tuple[int, ...]:
    """Candidates proposed for each piece: a linear ramp from 1 (the first piece always fits)
    to ``layout_candidates`` (the last piece, placed on the most crowded map)."""
    f, c = shape.num_furniture, shape.layout_candidates
    if f == 1:
        return (1,)
    return tuple(max(1, math.ceil(c * i / (f - 1))) for i in range(f))


def layout_num_words(shape: SimShape) -> int:
    """Random 32-bit words one layout attempt consumes."""
    return 2 * shape.num_furniture + sum(candidate_counts(shape))


def random_words(keys: jax.Array, num_words: int) -> jnp.ndarray:
    """(num_words, E) uint32 random words, column e drawn from ``keys[e]`` alone."""
    return jax.vmap(lambda k: jax.random.bits(k, (num_words,), jnp.uint32), out_axes=1)(keys)


def scaled16(bits: jnp.ndarray, size) -> jnp.ndarray:
    """Integers in [0, size) from the low 16 bits of ``bits`` (size <= 2**16, broadcasting)."""
    return ((bits & 0xFFFF) * jnp.asarray(size).astype(jnp.uint32) >> 16).astype(jnp.int32)


def uniform16(bits: jnp.ndarray) -> jnp.ndarray:
    """Floats in [0, 1) on a 2**-16 grid from the low 16 bits of ``bits``."""
    return (bits & 0xFFFF).astype(jnp.float32) * (1.0 / 65536.0)


def stable_ranks(values: jnp.ndarray) -> jnp.ndarray:
    """Ranks (F, E) int32 of ``values`` (F, E) along axis 0, ties broken by index."""
    f = values.shape[0]
    index = jnp.arange(f)[:, None, None]
    other = jnp.arange(f)[None, :, None]
    before = (values[None, :] < values[:, None]) | ((values[None, :] == values[:, None])
                                                    & (other < index))
    return jnp.sum(before, axis=1, dtype=jnp.int32)


def boxes_overlap(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """Whether boxes ``a`` and ``b`` overlap with positive area; touching edges do not count.

    Boxes are (y0, x0, y1, x1) with y1/x1 exclusive, coordinates on axis ``-2`` (env-last
    layout: (..., 4, E)); the rest broadcasts.
    """
    return ((a[..., 0, :] < b[..., 2, :]) & (b[..., 0, :] < a[..., 2, :])
            & (a[..., 1, :] < b[..., 3, :]) & (b[..., 1, :] < a[..., 3, :]))


def attempt_layouts(words: jnp.ndarray, params: Params, shape: SimShape):
    """One layout attempt per environment from its random words (W, E), W = layout_num_words.

    Returns (boxes (F, 4, E) int32 pixels (y0, x0, y1, x1), kind (F, E) int32 index into
    ``config.furniture_kinds``, ok (E,) bool — False if some piece found no free spot).
    """
    f, k = shape.num_furniture, shape.num_kinds
    kind_bits, size_bits = words[:f], words[f:2 * f]

    # Kinds: min_per_kind of each kind, extras uniform, then shuffled (random ranks).
    index = jnp.arange(f)[:, None]
    per_kind = params["min_per_kind"]
    base = jnp.where(index < per_kind * k, index // per_kind, scaled16(kind_bits, k))  # (F, E)
    ranks = stable_ranks(kind_bits >> 16)
    kind = jnp.take_along_axis(base, ranks, axis=0).astype(jnp.int32)

    # Sizes: uniform integers in [side_lo, side_hi] as (h, w): (F, 2, E).
    side_choices = params["side_hi"] - params["side_lo"] + 1
    size = params["side_lo"] + jnp.stack(
        [scaled16(size_bits >> 16, side_choices), scaled16(size_bits, side_choices)], axis=1)
    corner_choices = params["map_size"] - size + 1  # (F, 2, E)

    # Sequential first-fit; piece i only checks the i pieces placed before it. The loop over
    # the (few, static) pieces is unrolled so each piece uses exactly its candidate count.
    placed, fitted, offset = [], [], 2 * f
    for i, count in enumerate(candidate_counts(shape)):
        bits = words[offset:offset + count]  # (C_i, E)
        offset += count
        corner = jnp.stack([scaled16(bits >> 16, corner_choices[i, 0]),
                            scaled16(bits, corner_choices[i, 1])], axis=1)  # (C_i, 2, E)
        cands = jnp.concatenate([corner, corner + size[i]], axis=1)  # (C_i, 4, E)
        if i == 0:
            placed.append(cands[0])
            continue
        hits = boxes_overlap(cands[:, None], jnp.stack(placed)[None])  # (C_i, i, E)
        fits = ~jnp.any(hits, axis=1)  # (C_i, E)
        first = jnp.argmax(fits, axis=0)  # (E,) first fitting candidate
        chosen = jnp.arange(count)[:, None] == first[None, :]
        placed.append(jnp.sum(jnp.where(chosen[:, None, :], cands, 0), axis=0))
        fitted.append(jnp.any(fits, axis=0))
    ok = jnp.all(jnp.stack(fitted), axis=0) if fitted else jnp.ones(words.shape[1:], bool)
    return jnp.stack(placed), kind, ok


def box_centres(boxes: jnp.ndarray, axis: int = -1) -> jnp.ndarray:
    """Centres (cy, cx) of pixel boxes (y0, x0, y1, x1) whose coordinates lie on ``axis``."""
    boxes = jnp.moveaxis(boxes.astype(jnp.float32), axis, -1)
    return jnp.moveaxis(corner_centres(boxes), -1, axis)


def table_angle(cy: jnp.ndarray, cx: jnp.ndarray, map_size) -> jnp.ndarray:
    """Angle in [0, 2π) of centres around the map centre: 0 points up, increases clockwise on
    screen (y grows downwards): atan2(cx − W/2, −(cy − H/2)) mod 2π."""
    half = 0.5 * jnp.asarray(map_size, jnp.float32)
    return jnp.mod(jnp.arctan2(cx - half, -(cy - half)), 2.0 * jnp.pi)


_ORDERING_KEYS = {
    "clockwise": lambda cy, cx, map_size: table_angle(cy, cx, map_size),
    "counter_clockwise": lambda cy, cx, map_size: -table_angle(cy, cx, map_size),
    "top_to_bottom": lambda cy, cx, map_size: cy,
    "bottom_to_top": lambda cy, cx, map_size: -cy,
    "left_to_right": lambda cy, cx, map_size: cx,
}
"""The sort key of each rule of ``config.ORDERINGS`` (a config names only these)."""


def ordering_key(cy: jnp.ndarray, cx: jnp.ndarray, ordering: str, map_size) -> jnp.ndarray:
    """Sort key whose ascending order is the visiting order of rule ``ordering``."""
    return _ORDERING_KEYS[ordering](cy, cx, map_size)


def visit_orders(boxes: jnp.ndarray, kind: jnp.ndarray, params: Params, shape: SimShape):
    """Visiting order of every category over the furniture of its kind.

    boxes (F, 4, E), kind (F, E) kind index.
    Returns (visit_order (M, F, E) int32 furniture indices padded with -1,
    num_slots (M, E) int32).
    """
    f = shape.num_furniture
    centre = box_centres(boxes, axis=1)  # (F, 2, E)
    cy, cx = centre[:, 0], centre[:, 1]
    position = jnp.arange(f)[:, None, None]  # axis 0: position r along the order
    piece = jnp.arange(f)[None, :, None]  # axis 1: furniture index i
    orders, counts = [], []
    for ordering, cat_kind in zip(shape.orderings, shape.category_kind, strict=True):
        valid = kind == cat_kind
        key = jnp.where(valid, ordering_key(cy, cx, ordering, params["map_size"]), jnp.inf)
        rank = stable_ranks(key)  # (F, E): valid pieces take ranks 0..K-1
        count = jnp.sum(valid, axis=0, dtype=jnp.int32)
        order = jnp.sum(jnp.where(rank[None] == position, piece, 0), axis=1)  # (F, E)
        orders.append(jnp.where(position[:, 0] < count[None, :], order, -1))
        counts.append(count)
    return jnp.stack(orders).astype(jnp.int32), jnp.stack(counts)


def object_sizes(boxes: jnp.ndarray, visit_order: jnp.ndarray, params: Params) -> jnp.ndarray:
    """(M, E) float32 object side: max(min_object_px, floor(object_frac * min side of the start
    table)). boxes (F, 4, E), visit_order (M, F, E)."""
    f = boxes.shape[0]
    side = jnp.minimum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1])  # (F, E)
    start = visit_order[:, 0, None, :] == jnp.arange(f)[None, :, None]  # (M, F, E)
    start_side = jnp.sum(jnp.where(start, side[None], 0), axis=1).astype(jnp.float32)
    size = jnp.floor(params["object_frac"] * start_side)
    return jnp.maximum(params["min_object_px"].astype(jnp.float32), size)


def object_boxes(boxes: jnp.ndarray, visit_order: jnp.ndarray, slot: jnp.ndarray,
                 size: jnp.ndarray) -> jnp.ndarray:
    """(T, M, 4) float32 object boxes (y0, x0, y1, x1) centred on the current table.

    One environment, environment-first layout (vmap it): boxes (F, 4), visit_order (M, F),
    slot (T, M), size (M,).
    """
    table = jnp.take_along_axis(visit_order[None], slot[:, :, None], axis=2)[..., 0]  # (T, M)
    centre = box_centres(boxes)[table]  # (T, M, 2)
    return centred_squares(centre, 0.5 * size[None, :, None])
