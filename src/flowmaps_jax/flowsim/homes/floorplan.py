"""Floor plans: rooms on a grid of cells joined by doors, and geodesic distances through doors
(docs/flowsim.md, "Homes"). Metres (x along the width, y along the depth, z up); one home (vmap
over homes); room k = column · rows + row, a room box (x0, y0, x1, y1); door slots are static.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.flowsim.homes.config import HomesConfig


def door_pairs(config: HomesConfig) -> np.ndarray:
    """(D, 2) int32 the two rooms of every door slot: first the stacked pairs of each column,
    then for each column boundary every (row, row') pair (static: the same for every home)."""
    rows, cols = config.grid_rows, config.grid_cols
    pairs = [(c * rows + r, c * rows + r + 1) for c in range(cols) for r in range(rows - 1)]
    pairs += [(c * rows + r, (c + 1) * rows + s) for c in range(cols - 1)
              for r in range(rows) for s in range(rows)]
    return np.asarray(pairs, np.int32).reshape(-1, 2)


def _splits(u: jnp.ndarray, total, jitter: float) -> jnp.ndarray:
    """Boundaries (n + 1,) of ``total`` split into n parts ∝ 1 + jitter·(2u − 1)."""
    weight = 1.0 + jitter * (2.0 * u - 1.0)
    edges = jnp.cumsum(weight) / jnp.sum(weight) * total
    return jnp.concatenate([jnp.zeros((1,), edges.dtype), edges.at[-1].set(total)])


def split_uniforms(u: jnp.ndarray, shapes: dict[str, tuple[int, ...]]) -> dict:
    """Cut a flat vector of uniforms into named arrays of the given shapes (in order)."""
    out, start = {}, 0
    for name, shape in shapes.items():
        size = int(np.prod(shape))
        out[name] = u[start:start + size].reshape(shape)
        start += size
    return out


def plan_uniforms(config: HomesConfig) -> dict[str, tuple[int, ...]]:
    """The uniforms ``floor_plan`` reads, by name and shape."""
    d = config.max_doors
    return {"size": (2,), "cols": (config.grid_cols,), "rows": (config.grid_cols, config.grid_rows),
            "type": (config.num_rooms,), "main": (d,), "extra": (d,), "position": (d,)}


def floor_plan(u, config: HomesConfig) -> dict:
    """One home's floor plan from uniforms u (sum of ``plan_uniforms`` sizes,) in [0, 1).

    Returns a dict of arrays: home_size (2,) float32 (W, D) m; room_type (NR,) int32 index into
    ``config.room_types``; room_box (NR, 4) float32 (x0, y0, x1, y1); door_position (D, 2)
    float32 (0 where absent); door_rooms (D, 2) int32; door_valid (D,) bool.
    """
    rows, cols = config.grid_rows, config.grid_cols
    u = split_uniforms(u, plan_uniforms(config))
    lo = jnp.asarray([config.home_width[0], config.home_depth[0]], jnp.float32)
    hi = jnp.asarray([config.home_width[1], config.home_depth[1]], jnp.float32)
    size = lo + u["size"] * (hi - lo)
    xs = _splits(u["cols"], size[0], config.split_jitter)  # (C+1,)
    ys = jax.vmap(lambda v: _splits(v, size[1], config.split_jitter))(u["rows"])  # (C, rows+1)
    col = np.repeat(np.arange(cols), rows)
    row = np.tile(np.arange(rows), cols)
    room_box = jnp.stack([xs[col], ys[col, row], xs[col + 1], ys[col, row + 1]], axis=-1)
    types = jnp.asarray(config.room_type_index, jnp.int32)
    room_type = types[jnp.argsort(u["type"])]  # the rooms shuffled over the cells

    pairs = door_pairs(config)
    a, b = room_box[pairs[:, 0]], room_box[pairs[:, 1]]
    stacked = np.arange(len(pairs)) < cols * (rows - 1)  # static
    # the shared wall: stacked pairs share y = a.y1 over x0..x1; neighbours x = a.x1 over y-overlap
    lo_along = jnp.where(stacked, jnp.maximum(a[:, 0], b[:, 0]), jnp.maximum(a[:, 1], b[:, 1]))
    hi_along = jnp.where(stacked, jnp.minimum(a[:, 2], b[:, 2]), jnp.minimum(a[:, 3], b[:, 3]))
    clear = config.wall_margin + config.door_width / 2
    fits = hi_along - lo_along >= 2 * clear
    score = jnp.where(fits & ~stacked, u["main"], -1.0)
    boundary = np.where(stacked, -1, (np.arange(len(pairs)) - cols * (rows - 1)) // (rows * rows))
    main = jnp.zeros(len(pairs), bool)
    for c in range(cols - 1):  # static, a handful of boundaries
        here = boundary == c
        best = jnp.argmax(jnp.where(here, score, -2.0))
        main = main.at[best].set(True)
    extra = u["extra"] < config.extra_door_prob
    valid = jnp.asarray(stacked) | (fits & (main | extra))
    along = lo_along + clear + u["position"] * jnp.maximum(
        hi_along - lo_along - 2 * clear, 0.0)
    across = jnp.where(stacked, a[:, 3], a[:, 2])
    position = jnp.where(jnp.asarray(stacked)[:, None], jnp.stack([along, across], -1),
                         jnp.stack([across, along], -1))
    return {"home_size": size, "room_type": room_type, "room_box": room_box,
            "door_position": jnp.where(valid[:, None], position, 0.0),
            "door_rooms": jnp.asarray(pairs), "door_valid": valid}


def room_adjacency(door_rooms, door_valid, num_rooms: int) -> jnp.ndarray:
    """(NR, NR) bool: rooms joined by a door (symmetric, no self loops)."""
    onehot_a = jax.nn.one_hot(door_rooms[..., 0], num_rooms, dtype=jnp.float32)
    onehot_b = jax.nn.one_hot(door_rooms[..., 1], num_rooms, dtype=jnp.float32)
    weight = door_valid.astype(jnp.float32)[..., None]
    joined = jnp.einsum("...da,...db->...ab", onehot_a * weight, onehot_b)
    return (joined + jnp.swapaxes(joined, -1, -2)) > 0


def floyd_warshall(weights: jnp.ndarray) -> jnp.ndarray:
    """All-pairs shortest path lengths (N, N) of edge lengths (N, N) (inf: no edge)."""
    n = weights.shape[-1]
    dist = jnp.where(jnp.eye(n, dtype=bool), jnp.minimum(weights, 0.0), weights)

    def relax(k, d):
        return jnp.minimum(d, d[:, k, None] + d[None, k, :])

    return jax.lax.fori_loop(0, n, relax, dist)


def geodesic_distances(points, point_room, point_valid, door_position, door_rooms,
                       door_valid, num_rooms: int) -> jnp.ndarray:
    """Walking distances (P, P) float32 between points (P, 2) through doors, metres.

    point_room: (P,) int32; point_valid: (P,) bool (inf for an invalid point, 0 on the
    diagonal). Doors: (D, 2) positions, (D, 2) rooms, (D,) valid.
    """
    nodes = jnp.concatenate([points, door_position], axis=0)  # (P + D, 2)
    member_points = jax.nn.one_hot(point_room, num_rooms, dtype=bool) & point_valid[:, None]
    member_doors = ((jax.nn.one_hot(door_rooms[:, 0], num_rooms, dtype=bool)
                     | jax.nn.one_hot(door_rooms[:, 1], num_rooms, dtype=bool))
                    & door_valid[:, None])
    member = jnp.concatenate([member_points, member_doors], axis=0).astype(jnp.float32)
    share = (member @ member.T) > 0
    length = jnp.linalg.norm(nodes[:, None, :] - nodes[None, :, :], axis=-1)
    dist = floyd_warshall(jnp.where(share, length, jnp.inf))
    p = points.shape[0]
    return dist[:p, :p]

