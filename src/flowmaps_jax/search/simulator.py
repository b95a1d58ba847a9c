"""The episode simulator: a robot looks at tables one by one until it finds the object
(docs/search.md). :func:`run_episodes` and :func:`expected_outcomes` check their arguments;
:func:`simulate` and :func:`simulate_every_target` check nothing."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from flowmaps_jax.navigation.policies import (
    MAX_OPTIMAL_TABLES,
    POLICIES,
    choose_indexed,
    distances,
)
from flowmaps_jax.resources import check_resources
from flowmaps_jax.validation import (
    PROB_ATOL,
    check_choice,
    check_instance,
    check_int,
    check_int_array,
    check_key,
    check_mask,
    check_probabilities,
    check_real,
    check_real_array,
)

DEFAULT_BUDGET = 10
"""Looks per episode (FlowSim has at most 4 tables of a kind)."""
_TINY = 1e-30


# --------------------------------------------------------------------------- pytrees


@struct.dataclass
class Episodes:
    """N search episodes over (padded) K candidate tables: belief (N, K) prior of the object's
    table (0 on padding), centres (N, K, 2) (y, x) pixels, valid (N, K) bool real tables, start
    (N, 2) pixels, target (N,) int32 the object's table."""

    belief: jnp.ndarray
    centres: jnp.ndarray
    valid: jnp.ndarray
    start: jnp.ndarray
    target: jnp.ndarray

    @property
    def num_episodes(self) -> int:
        return int(self.belief.shape[0])

    @property
    def num_tables(self) -> int:
        """K, the padded candidate axis."""
        return int(self.belief.shape[-1])


@struct.dataclass
class Outcome:
    """N episodes of L = ``budget`` looks: found (N,) bool, looks (N,) int32, travel (N,) pixels
    driven, shortest (N,) pixels straight to the true table, path (N, L) int32 table of each look
    (−1 after the end), travel_at (N, L), belief (N, L, K) the belief each look was decided on.
    """

    found: jnp.ndarray
    looks: jnp.ndarray
    travel: jnp.ndarray
    shortest: jnp.ndarray
    path: jnp.ndarray
    travel_at: jnp.ndarray
    belief: jnp.ndarray


# --------------------------------------------------------------------------- validation


def check_episodes(episodes: Episodes, policy: str, budget: int,
                   every_target: bool = False) -> Episodes:
    """The episodes checked (ValueError naming the field; their size by
    :func:`check_episodes_size`, K · N with ``every_target``) and canonical for :func:`simulate`."""
    valid = check_mask("episodes.valid", episodes.valid, (None, None))
    n, k = valid.shape
    check_probabilities("episodes.belief", episodes.belief, (n, k), atol=PROB_ATOL,
                        min_value=-PROB_ATOL, support=valid, support_name="episodes.valid")
    centres = check_real_array("episodes.centres", episodes.centres, (n, k, 2), finite=False)
    start = check_real_array("episodes.start", episodes.start, (n, 2))
    target = check_int_array("episodes.target", episodes.target, shape=(n,))
    if n < 1 or not np.all(valid.any(-1)):
        raise ValueError(f"episodes.valid must hold N ≥ 1 episodes, each with at least one real "
                         f"table; got shape {valid.shape}")
    centres = np.where(valid[..., None], np.asarray(centres), 0.0)
    check_real_array("episodes.centres", centres)  # NaN or inf on a real table
    target = np.asarray(target)
    if np.any((target < 0) | (target >= k)) or not np.all(
            valid[np.arange(n), np.clip(target, 0, k - 1)]):
        raise ValueError(f"episodes.target must index a real table (0..{k - 1}, valid)")
    check_episodes_size(n, k, budget, policy, copies=k if every_target else 1,
                        real_tables=int(valid.sum(-1).max()))
    return Episodes(belief=jnp.asarray(episodes.belief, jnp.float32),
                    centres=jnp.asarray(centres, jnp.float32), valid=jnp.asarray(valid),
                    start=jnp.asarray(start, jnp.float32),
                    target=jnp.asarray(target, jnp.int32))


def outcome_bytes(num_episodes: int, num_tables: int, budget: int) -> int:
    """Bytes of an Outcome of ``num_episodes`` × ``budget`` looks, with the scan's copy."""
    return 2 * 4 * num_episodes * budget * (num_tables + 3)


def look_flops(num_tables: int, policy: str) -> int:
    """Rough work of one look of one episode: the optimal policy's DP, else a few passes."""
    return 4 * 2 ** num_tables * num_tables ** 2 if policy == "optimal" else 32 * num_tables


def check_episodes_size(num_episodes: int, num_tables: int, budget: int, policy: str,
                        copies: int = 1, real_tables: int | None = None) -> None:
    """ValueError for "optimal" over more than ``MAX_OPTIMAL_TABLES`` real tables, or naming
    ``budget`` when ``copies`` × ``num_episodes`` episodes would exceed the resource bounds."""
    k = num_tables if real_tables is None else real_tables
    if policy == "optimal" and k > MAX_OPTIMAL_TABLES:
        raise ValueError(
            f"policy='optimal' takes at most {MAX_OPTIMAL_TABLES} candidate tables per episode; "
            f"got {k}. Its exact dynamic programme over subsets holds 2^K · K values and does "
            f"2^K · K² work per look and episode (K = {k}: {2 ** k * k ** 2:,}), which no longer "
            "fits a vectorised batch; use 'greedy' or 'most-probable' for more tables")
    n = copies * num_episodes
    check_resources(f"budget={budget} looks for {n} episodes over {num_tables} tables",
                    num_bytes=outcome_bytes(n, num_tables, budget),
                    flops=n * budget * look_flops(num_tables, policy))


# --------------------------------------------------------------------------- Bayes


def _update(belief, looked, p_miss, valid, looks_at):
    """Bayes after a failed look at ``looked``; uniform over the least-looked tables if empty."""
    hit = jnp.arange(belief.shape[-1]) == jnp.asarray(looked)[..., None]
    b = jnp.where(hit, belief * p_miss, belief)
    total = jnp.sum(b, axis=-1, keepdims=True)
    fewest = jnp.min(jnp.where(valid, looks_at, jnp.iinfo(jnp.int32).max), -1, keepdims=True)
    least = valid & (looks_at == fewest)
    fallback = least / jnp.sum(least, axis=-1, keepdims=True)
    return jnp.where(total > _TINY, b / jnp.where(total > _TINY, total, 1.0), fallback)


def bayes_update(belief, looked, p_miss: float = 0.0, valid=None, looks_at=None) -> jnp.ndarray:
    """The belief (..., K) after a failed look at table ``looked`` (...) int: ∝ b_j · (p_miss
    if j = looked else 1); with no mass left, uniform over the ``valid`` tables looked at least
    often (``looks_at`` (..., K) int, counting this look; default only this one)."""
    p_miss = check_real("p_miss", p_miss, 0.0, 1.0, high_open=True)
    belief = check_probabilities("belief", belief, (..., None), atol=PROB_ATOL,
                                 min_value=-PROB_ATOL)
    *batch, k = belief.shape
    if valid is not None:
        valid = check_mask("valid", valid, (*batch, k))
        check_probabilities("belief", belief, atol=PROB_ATOL, min_value=-PROB_ATOL,
                            support=valid, support_name="valid")  # none on invalid tables
    looked = check_int_array("looked", looked, 0, k - 1, shape=tuple(batch))
    valid = np.ones(belief.shape, bool) if valid is None else valid
    if looks_at is None:
        looks_at = (np.arange(belief.shape[-1]) == looked[..., None]).astype(np.int32)
    return _update(jnp.asarray(belief, jnp.float32), jnp.asarray(looked), p_miss,
                   jnp.asarray(valid), jnp.asarray(looks_at, jnp.int32))


# --------------------------------------------------------------------------- running


def _episode(belief, centres, valid, start, target, key, p_miss, policy_index, *, budget: int):
    """One episode (no batch axis): a ``lax.scan`` over the budget's looks."""
    k = belief.shape[-1]
    index = jnp.arange(k)

    def look(state, u):
        b, position, here, looks_at, found, travel, looks = state
        allowed = valid & (index != here)
        allowed = jnp.where(jnp.any(allowed), allowed, valid)
        j = choose_indexed(policy_index, b, centres, position, allowed, looks_at)
        go = ~found
        leg = distances(position, centres[j][None])[0]
        seen = looks_at + (go & (index == j)).astype(jnp.int32)
        after = _update(b, j, p_miss, valid, seen)
        state = (jnp.where(go, after, b), jnp.where(go, centres[j], position),
                 jnp.where(go, j, here), seen, found | (go & (j == target) & (u >= p_miss)),
                 travel + jnp.where(go, leg, 0.0), looks + go.astype(jnp.int32))
        return state, (jnp.where(go, j, -1), state[5], b)

    init = (belief, start, jnp.int32(-1), jnp.zeros(k, jnp.int32), jnp.bool_(False),
            jnp.float32(0.0), jnp.int32(0))
    final, (path, travel_at, beliefs) = jax.lax.scan(
        look, init, jax.random.uniform(key, (budget,)))
    shortest = distances(start, centres[target][None])[0]
    return Outcome(found=final[4], looks=final[6], travel=final[5], shortest=shortest, path=path,
                   travel_at=travel_at, belief=beliefs)


@functools.partial(jax.jit, static_argnames="budget")
def simulate(episodes: Episodes, key, p_miss, policy_index, budget: int) -> Outcome:
    """Every episode → Outcome (N, ...); policy_index int32 into ``POLICIES`` (traced). No
    validation."""
    keys = jax.random.split(key, episodes.num_episodes)
    one = functools.partial(_episode, budget=budget)
    return jax.vmap(one, in_axes=(0, 0, 0, 0, 0, 0, None, None))(
        episodes.belief, episodes.centres, episodes.valid, episodes.start, episodes.target,
        keys, p_miss, policy_index)


def run_episodes(episodes: Episodes, policy: str, key: jax.Array | None = None,
                 budget: int = DEFAULT_BUDGET, p_miss: float = 0.0) -> Outcome:
    """Run N episodes with ``policy`` → Outcome (N, ...). key: typed PRNG key for the
    detector's misses (default key(0)); budget ≥ 1 looks; p_miss in [0, 1). ValueError on bad
    input."""
    check_instance("episodes", episodes, Episodes)
    policy = check_choice("policy", policy, POLICIES)
    if key is not None:
        key = check_key(key, "key")
    budget = check_int("budget", budget)
    p_miss = check_real("p_miss", p_miss, 0.0, 1.0, high_open=True)
    episodes = check_episodes(episodes, policy, budget)
    key = jax.random.key(0) if key is None else key
    return simulate(episodes, key, jnp.float32(p_miss), policy_index(policy), budget)


def policy_index(policy: str) -> jnp.ndarray:
    """A policy's name as the traced index :func:`simulate` takes (its place in ``POLICIES``)."""
    return jnp.int32(POLICIES.index(policy))


def simulate_every_target(episodes: Episodes, policy_index, budget: int) -> Outcome:
    """Every episode once per hiding table, perfect detector → Outcome (K, N, ...). No
    validation."""
    k, n = episodes.num_tables, episodes.num_episodes
    tiled = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (k, *a.shape)).reshape(
        k * n, *a.shape[1:]), episodes)
    tiled = tiled.replace(target=jnp.repeat(jnp.arange(k, dtype=jnp.int32), n))
    every = simulate(tiled, jax.random.key(0), jnp.float32(0.0), policy_index, budget)
    return jax.tree_util.tree_map(lambda a: a.reshape(k, n, *a.shape[1:]), every)


def expected_outcomes(episodes: Episodes, truth, policy: str,
                      budget: int = DEFAULT_BUDGET) -> tuple[Outcome, jnp.ndarray]:
    """Exact expectations over where the object hides (perfect detector): (Outcome (K, N, ...)
    of every hiding table, weights (K, N) = ``truth`` (N, K) transposed)."""
    check_instance("episodes", episodes, Episodes)
    policy = check_choice("policy", policy, POLICIES)
    budget = check_int("budget", budget)
    episodes = check_episodes(episodes, policy, budget, every_target=True)
    valid = np.asarray(episodes.valid)
    check_probabilities("truth", truth, valid.shape, atol=PROB_ATOL, min_value=-PROB_ATOL,
                        support=valid, support_name="episodes.valid")
    every = simulate_every_target(episodes, policy_index(policy), budget)
    return every, jnp.asarray(truth, jnp.float32).T


def at_targets(every: Outcome, target) -> Outcome:
    """Episode n's outcome with the object on ``target[n]`` from an every-target Outcome
    (K, N, ...) → Outcome (N, ...)."""
    index = jnp.asarray(target, jnp.int32)
    n = jnp.arange(index.shape[0])
    return jax.tree_util.tree_map(lambda a: a[index, n], every)
