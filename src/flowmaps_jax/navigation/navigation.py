"""Object navigation in homes, scored as the field scores it (FlowMaps 2026, SGM, HOMER); the
protocol is docs/flowsim.md, "Navigation". One episode per query; each policy (``POLICIES``)
fixes a visiting order of the allowed receptacles before the first look (perfect detector);
:func:`episode_metrics` scores them. Jitted and vmapped over homes and queries; the optimal
policy's DP is grouped by size on the host (``DP_SIZES``).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.flowsim.homes import HomesConfig, geodesic_distances
from flowmaps_jax.flowsim.homes.queries import HomesQueries, allowed_slots, receptacle_at
from flowmaps_jax.flowsim.homes.world import Homes
from flowmaps_jax.navigation.policies import BELIEF_ATOL, COST_RTOL, pick, subset_values
from flowmaps_jax.validation import check_choice, check_int

POLICIES = ("most-probable", "optimal", "nearest")
SR_LOOKS = (1, 5, 10)
LOOK_BUDGET = 10
STEP_LENGTH = 0.25
"""Metres per step (the "steps" column: metres walked / STEP_LENGTH)."""
MAX_OPTIMAL_RECEPTACLES = 12
DP_SIZES = (4, 8, MAX_OPTIMAL_RECEPTACLES)
"""The dynamic programme pads each episode's A allowed receptacles to the first size ≥ A."""
FAR = 1e4
"""Metres to and from a padded receptacle of the dynamic programme (visited only once no
belief mass is left, when every leg is free)."""
NAVIGATION_METRICS = ("sr@1", "sr@5", "sr@10", "msr", "spl@1", "mspl", "steps")


# --------------------------------------------------------------------------- geometry


@functools.partial(jax.jit, static_argnames="config")
def _start(homes: Homes, config: HomesConfig):
    start = (homes.room_box[:, 0, :2] + homes.room_box[:, 0, 2:]) / 2  # (E, 2)

    def one(point, home):
        points = jnp.concatenate([point[None], home.receptacle_box[:, :2]])
        rooms = jnp.concatenate([jnp.zeros((1,), jnp.int32), home.receptacle_room])
        valid = jnp.concatenate([jnp.ones((1,), bool), home.receptacle_valid])
        d = geodesic_distances(points, rooms, valid, home.door_position, home.door_rooms,
                               home.door_valid, config.num_rooms)
        return jnp.where(home.receptacle_valid, d[0, 1:], 0.0)

    return start, jax.vmap(one)(start, homes)


def start_points(homes: Homes, config: HomesConfig) -> tuple[jax.Array, jax.Array]:
    """The searcher's start (E, 2) (centre of room 0) and its geodesic distance (E, R) in
    metres to every receptacle (0 for unused slots)."""
    return _start(homes, config)


# --------------------------------------------------------------------------- greedy orders


def _greedy_order(belief, allowed, distance, start_distance):
    """(R,) order of one episode (−1 after the allowed ones): the highest belief first, ties to
    the nearest from where the searcher stands (a constant belief: nearest first)."""
    def step(carry, _):
        visited, here = carry
        candidates = allowed & ~visited
        chosen = pick(candidates, (belief, BELIEF_ATOL), (-here, 0.0))
        left = jnp.any(candidates)
        visited = visited | (left & (jnp.arange(allowed.shape[0]) == chosen))
        return (visited, jnp.where(left, distance[chosen], here)), jnp.where(left, chosen, -1)

    init = (jnp.zeros_like(allowed), start_distance)
    return jax.lax.scan(step, init, None, length=allowed.shape[0])[1]


@jax.jit
def greedy_orders(belief, homes: Homes, queries: HomesQueries, start_distance):
    """(E, Q, R) int32 most-probable-first orders of ``belief`` (E, Q, R) (−1 padded)."""
    allowed = allowed_slots(homes, queries)
    per_query = jax.vmap(_greedy_order, in_axes=(0, 0, None, None))
    return jax.vmap(per_query)(belief, allowed, homes.receptacle_distance, start_distance)


# --------------------------------------------------------------------------- exact DP


def _optimal_one(belief, allowed, distance, start_distance, a: int):
    """(order (R,), least expected travel ()) of one episode, its allowed receptacles padded
    to ``a``."""
    r = allowed.shape[0]
    index = jnp.argsort(~allowed, stable=True)[:a]
    valid = jnp.arange(a) < jnp.sum(allowed)
    b = jnp.where(valid, belief[index], 0.0)
    b = b / jnp.maximum(jnp.sum(b), 1e-30)
    pair = valid[:, None] & valid[None, :]
    d = jnp.where(pair, distance[index][:, index], FAR)
    here = jnp.where(valid, start_distance[index], FAR)
    table = subset_values(b, d)
    bit = 1 << jnp.arange(a)
    mask, order, value = jnp.int32(0), [], None
    for _ in range(a):  # follow the plan, re-reading the table
        free = (mask & bit) == 0
        remaining = jnp.sum(jnp.where(free, b, 0.0))
        cost = here * remaining + table[mask | bit, jnp.arange(a)]
        if value is None:
            value = jnp.min(jnp.where(free, cost, jnp.inf))
        tol = COST_RTOL * jnp.maximum(1.0, jnp.min(jnp.where(free, cost, jnp.inf)))
        chosen = pick(free, (-cost, tol), (valid.astype(jnp.float32), 0.5), (-here, 0.0))
        order.append(chosen)
        mask = mask | (1 << chosen)
        here = d[chosen]
    order = jnp.stack(order)
    real = valid[order]
    order = jnp.where(real, index[order], -1)
    order = order[jnp.argsort(~real, stable=True)]  # padding last
    return jnp.concatenate([order, jnp.full((r - a,), -1, jnp.int32)]), value


@functools.partial(jax.jit, static_argnames="a")
def _optimal_batch(belief, allowed, distance, start_distance, a: int):
    return jax.vmap(functools.partial(_optimal_one, a=a))(belief, allowed, distance,
                                                          start_distance)


def optimal_orders(belief, homes: Homes, queries: HomesQueries, start_distance,
                   chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """Orders (E, Q, R) int32 of least expected travel under ``belief`` (E, Q, R), and that
    expected travel (E, Q) in metres (the Bayes-optimal searcher's when ``belief`` is the exact
    posterior). Episodes are grouped on the host by ``DP_SIZES`` and run in chunks."""
    allowed = np.asarray(allowed_slots(homes, queries))
    e, q, r = allowed.shape
    count = allowed.sum(-1).reshape(-1)
    a = int(count.max())  # the most allowed receptacles of one object
    if a > MAX_OPTIMAL_RECEPTACLES:
        raise ValueError(
            f"policy 'optimal' takes at most {MAX_OPTIMAL_RECEPTACLES} allowed receptacles per "
            f"object; an object here has {a}. Its exact dynamic programme holds 2^A · A values "
            f"and does 2^A · A² work per episode (A = {a}: {2 ** a * a ** 2:,}); use "
            "'most-probable' or 'nearest', or a vocabulary with fewer receptacles per object")
    home = np.repeat(np.arange(e), q)
    flat_belief = np.asarray(belief, np.float32).reshape(e * q, r)
    flat_allowed = allowed.reshape(e * q, r)
    distance, start = np.asarray(homes.receptacle_distance), np.asarray(start_distance)
    orders = np.full((e * q, r), -1, np.int32)
    values = np.zeros(e * q, np.float32)
    low = 0
    for size in DP_SIZES:
        members = np.nonzero((count > low) & (count <= size))[0]
        low = size
        step = max(1, min(chunk, 2 ** 25 // (2 ** size * size * size)))
        for begin in range(0, members.size, step):
            part = members[begin:begin + step]
            shape = min(step, 1 << (part.size - 1).bit_length())  # few compiled shapes
            pad = np.resize(part, shape)
            o, v = _optimal_batch(flat_belief[pad], flat_allowed[pad], distance[home[pad]],
                                  start[home[pad]], size)
            orders[part], values[part] = np.asarray(o)[:part.size], np.asarray(v)[:part.size]
    return orders.reshape(e, q, r), values.reshape(e, q)


# --------------------------------------------------------------------------- episodes


def _walk(order, target, exact, distance, start_distance, budget: int):
    """Scores of one episode's visiting order (R,) (−1 padded)."""
    real = order >= 0
    o = jnp.maximum(order, 0)
    legs = jnp.concatenate([start_distance[o[:1]], distance[o[:-1], o[1:]]])
    cum = jnp.cumsum(jnp.where(real, legs, 0.0))
    hit = real & (order == target)
    found = jnp.any(hit)
    looks = jnp.where(found, jnp.argmax(hit) + 1, jnp.sum(real) + 1)
    made = jnp.minimum(jnp.sum(real), budget)
    within = found & (looks <= budget)
    travel = jnp.where(within, cum[jnp.maximum(looks - 1, 0)], cum[jnp.maximum(made - 1, 0)])
    expected = jnp.sum(jnp.where(real, exact[o] * cum, 0.0))
    return {"looks": looks.astype(jnp.int32), "travel": travel, "expected_travel": expected,
            "shortest": start_distance[jnp.maximum(target, 0)]}


@functools.partial(jax.jit, static_argnames="budget")
def walk_orders(orders, homes: Homes, queries: HomesQueries, exact, start_distance,
                budget: int = LOOK_BUDGET) -> dict[str, jax.Array]:
    """Episodes of visiting orders (E, Q, R): {looks, travel (m, within the budget),
    expected_travel (m, under ``exact`` (E, Q, R), no budget), shortest (m)}, each (E, Q)."""
    target = receptacle_at(homes, queries.tau_q, queries.object_index)
    walk = functools.partial(_walk, budget=budget)
    per_query = jax.vmap(walk, in_axes=(0, 0, 0, None, None))
    return jax.vmap(per_query)(orders, target, exact, homes.receptacle_distance, start_distance)


def visit_orders(policy: str, belief, homes: Homes, queries: HomesQueries, start_distance
                 ) -> np.ndarray | jax.Array:
    """(E, Q, R) visiting orders of ``policy`` (``POLICIES``) under ``belief`` (E, Q, R)."""
    check_choice("policy", policy, POLICIES)
    if policy == "optimal":
        return optimal_orders(belief, homes, queries, start_distance)[0]
    if policy == "nearest":
        belief = jnp.zeros(allowed_slots(homes, queries).shape, jnp.float32)
    return greedy_orders(belief, homes, queries, start_distance)


def episode_metrics(outcome: dict, budget: int = LOOK_BUDGET) -> dict[str, np.ndarray]:
    """Per-episode ``NAVIGATION_METRICS`` (E, Q) float64 (and ``success_at`` (E, Q, budget)) of
    :func:`walk_orders` outcomes; SR and SPL as fractions (0..1)."""
    budget = check_int("budget", budget, max(SR_LOOKS))
    looks = np.asarray(outcome["looks"])
    travel = np.asarray(outcome["travel"], np.float64)
    shortest = np.asarray(outcome["shortest"], np.float64)
    within = looks[..., None] <= np.arange(1, budget + 1)
    longest = np.maximum(travel, shortest)
    efficiency = np.where(longest > 0, shortest / np.where(longest > 0, longest, 1.0), 1.0)
    out = {f"sr@{k}": within[..., k - 1].astype(np.float64) for k in SR_LOOKS}
    out["msr"] = within.mean(-1)
    out["spl@1"] = np.where(looks == 1, efficiency, 0.0)
    out["mspl"] = np.where(looks <= budget, efficiency, 0.0)
    out["steps"] = travel / STEP_LENGTH
    out["success_at"] = within.astype(np.float64)
    return out
