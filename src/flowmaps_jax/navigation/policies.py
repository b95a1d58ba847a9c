"""Search policies: which table to look at next, given the belief and where the robot stands
(docs/search.md, "Policies"). Every function works on ONE episode (K padded candidate tables,
``valid`` (K,)), pure and jit-able. Ties (beliefs within ``BELIEF_ATOL``, plan costs within
``COST_RTOL``) go to the nearest table, then the lowest index.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

POLICIES = ("most-probable", "greedy", "optimal", "nearest")
MAX_OPTIMAL_TABLES = 7
"""The "optimal" policy's dynamic programme has 2^K · K states per look; K ≤ 7 keeps it exact and
fast (FlowSim has 3 or 4 tables of a kind)."""
MIN_DISTANCE = 1.0
"""Pixels: the greedy policy divides by max(distance, MIN_DISTANCE)."""
BELIEF_ATOL = 1e-6
"""Beliefs (and greedy ratios) closer than this are tied."""
COST_RTOL = 1e-5
"""Plan costs within this relative tolerance are tied (float32 sums of up to 7 terms)."""


def distances(position: jnp.ndarray, centres: jnp.ndarray) -> jnp.ndarray:
    """Euclidean distances (..., K) from ``position`` (..., 2) to ``centres`` (..., K, 2)."""
    return jnp.sqrt(jnp.sum((centres - position[..., None, :]) ** 2, axis=-1))


# --------------------------------------------------------------------------- exact plan


@functools.cache
def _layers(k: int) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], ...]:
    """Static tables of the subset DP over k places, one per subset size k − 1 down to 1: the
    size-s subsets' masks (n,), their "not yet looked at" 0/1 rows (n, k) float (for m(S)), the
    masks of S ∪ {j} (n, k) and whether j ∉ S (n, k) bool. Built once per k, at trace time."""
    masks = np.arange(2 ** k)
    bits = (masks[:, None] >> np.arange(k)) & 1
    layers = []
    for size in range(k - 1, 0, -1):
        rows = masks[bits.sum(-1) == size]
        out = 1 - bits[rows]
        layers.append((rows, out.astype(np.float32), rows[:, None] | (1 << np.arange(k)),
                       out.astype(bool)))
    return tuple(layers)


def subset_values(belief: jnp.ndarray, legs: jnp.ndarray) -> jnp.ndarray:
    """V (2^K, K): the least expected travel of the rest of a search that has looked at the
    subset S (a bit mask) and stands at place i: V(S, i) = min_{j ∉ S} d(i, j) · m(S) +
    V(S ∪ {j}, j), m(S) = Σ_{t ∉ S} b_t the belief not yet looked at, V(all, ·) = 0.

    belief: (K,) probabilities; legs: (K, K) distances between the places (K static)."""
    k = belief.shape[-1]
    table = jnp.zeros((2 ** k, k), belief.dtype)
    for rows, out, nxt, free in _layers(k):
        remaining = out @ belief  # (n,) m(S)
        after = table[nxt, np.arange(k)]  # (n, K_j): V(S ∪ {j}, j)
        cost = legs[None] * remaining[:, None, None] + after[:, None, :]  # (n, K_i, K_j)
        table = table.at[rows].set(jnp.min(jnp.where(free[:, None, :], cost, jnp.inf), -1))
    return table


def plan_costs(belief: jnp.ndarray, centres: jnp.ndarray, position: jnp.ndarray) -> jnp.ndarray:
    """Least expected travel (K,) of a plan that looks at table j first, for every j.

    belief: (K,) probabilities (zero on padding); centres: (K, 2) table centres; position: (2,).
    Expected travel: Σ_legs (leg length) · (mass not yet looked at), perfect detector.
    """
    k = belief.shape[-1]
    first = subset_values(belief, distances(centres, centres))[1 << np.arange(k), np.arange(k)]
    return distances(position, centres) * jnp.sum(belief) + first


def optimal_expected_travel(belief: jnp.ndarray, centres: jnp.ndarray, valid: jnp.ndarray,
                            start: jnp.ndarray) -> jnp.ndarray:
    """The least expected travel distance () of any visiting order, from ``start`` (2,)."""
    return jnp.min(jnp.where(valid, plan_costs(jnp.where(valid, belief, 0.0),
                                               jnp.where(valid[:, None], centres, 0.0), start),
                             jnp.inf))


# --------------------------------------------------------------------------- one decision


def pick(allowed: jnp.ndarray, *criteria: tuple[jnp.ndarray, jnp.ndarray | float]) -> jnp.ndarray:
    """Index of the allowed entry that maximises the criteria lexicographically; each criterion
    is (values (K,), tolerance): entries within tolerance of the best stay tied. Then lowest index.
    """
    keep = allowed
    for values, tol in criteria:
        v = jnp.where(keep, values, -jnp.inf)
        keep = keep & (v >= jnp.max(v) - tol)
    return jnp.argmax(keep).astype(jnp.int32)


def choose(policy: str, belief: jnp.ndarray, centres: jnp.ndarray, position: jnp.ndarray,
           allowed: jnp.ndarray, looks_at: jnp.ndarray) -> jnp.ndarray:
    """The table () int32 the policy looks at next.

    belief: (K,) current belief (zero on padding). centres: (K, 2). position: (2,) robot.
    allowed: (K,) bool tables it may look at now (real, and not the one it stands at).
    looks_at: (K,) int looks made at each table so far (the "nearest" policy's sweep).
    ``policy`` is static (a Python string).
    """
    dist = distances(position, centres)
    nearer = (-dist, 0.0)
    if policy == "most-probable":
        return pick(allowed, (belief, BELIEF_ATOL), nearer)
    if policy == "greedy":
        return pick(allowed, (belief / jnp.maximum(dist, MIN_DISTANCE), BELIEF_ATOL), nearer)
    if policy == "optimal":
        cost = plan_costs(belief, centres, position)
        tol = COST_RTOL * jnp.maximum(1.0, jnp.min(jnp.where(allowed, cost, jnp.inf)))
        return pick(allowed, (-cost, tol), (belief, BELIEF_ATOL), nearer)
    if policy == "nearest":
        fewest = jnp.min(jnp.where(allowed, looks_at, jnp.iinfo(jnp.int32).max))
        return pick(allowed & (looks_at == fewest), nearer)
    raise ValueError(f"policy must be one of {POLICIES}; got {policy!r}")


def choose_indexed(policy_index: jnp.ndarray, belief: jnp.ndarray, centres: jnp.ndarray,
                   position: jnp.ndarray, allowed: jnp.ndarray,
                   looks_at: jnp.ndarray) -> jnp.ndarray:
    """:func:`choose` with the policy as a traced index into ``POLICIES`` (``lax.switch``)."""
    branches = [functools.partial(choose, p) for p in POLICIES]
    return jax.lax.switch(policy_index, branches, belief, centres, position, allowed, looks_at)
