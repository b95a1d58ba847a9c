"""Search episodes: a robot looks at tables one by one until it finds the object.

One episode, all arrays of :class:`Episodes` without the batch axis:

* the object hides on table ``target`` (in FlowSim: its table at τ_q in the rollout);
* the robot starts at ``start`` (pixels; the map centre or the object's last-seen table);
* each look drives in a straight line to a table's centre (Euclidean travel, pixels) and finds the
  object if it is there, except with probability ``p_miss`` (an imperfect detector);
* after a failed look at table j the belief is updated by Bayes' rule:
  b_j ← p_miss · b_j, then renormalised (p_miss = 0: zero it and renormalise). If nothing is left
  (a prior that ruled the true table out), the belief becomes uniform over the tables looked at
  least often (with a perfect detector: the tables not searched yet);
* the episode ends when the object is found or after ``budget`` looks.

:func:`run_episodes` runs a batch: ``jax.vmap`` over episodes of one ``lax.scan`` over the
``budget`` looks, jit-compiled once per (N, K, budget) for all policies (the policy is a traced
index). :func:`expected_outcomes` runs every possible hiding place at once (the K · N episodes
in one batch) for exact expectations under a truth distribution.

FlowSim episodes: :func:`build_search_set` draws the queries (as the evaluation protocol: every
object of an environment, τ ~ U{0..T−2}, τ_q ~ U{τ+1..T−1}; or fixed horizons) with their exact
posterior and true tables; :func:`exact_tables`, :func:`uniform_tables`, :func:`last_seen_tables`
and :func:`predictor_tables` give each prior's table probabilities; :func:`make_episodes` turns
one of them into :class:`Episodes` over the K tables of the object's kind (its visiting order:
candidate k is the k-th table of the route, so ``target`` is the slot at τ_q).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from tqdm import tqdm

from flowmaps_jax.evaluation import slots as slot_metrics
from flowmaps_jax.flowsim import (
    FlowSimConfig,
    Scenes,
    draw_query_times,
    exact_posterior,
    scene_tokens,
)
from flowmaps_jax.search.policies import (
    POLICIES,
    check_optimal_size,
    check_policy,
    choose_indexed,
    distances,
)
from flowmaps_jax.search.probabilities import slots_to_tables, table_probabilities
from flowmaps_jax.tokens import Queries, SceneTokens
from flowmaps_jax.validation import (
    check_instance,
    check_int,
    check_key,
    check_real,
    check_resources,
    network_flops,
    solver_evaluations,
)

DEFAULT_BUDGET = 10
"""Looks per episode (FlowSim has at most 4 tables of a kind: every policy finds the object
within K looks with a perfect detector)."""
STARTS = ("centre", "last-seen")
PROB_ATOL = 1e-4
"""A belief must sum to 1 within this tolerance."""
_TINY = 1e-30
_SALT_TIMES, _SALT_SAMPLES = 11, 12


# --------------------------------------------------------------------------- pytrees


@struct.dataclass
class Episodes:
    """N search episodes over (padded) K candidate tables.

    belief: (N, K) prior probabilities of the object's table (sum 1 over the real tables, 0 on
        padding). centres: (N, K, 2) table centres (y, x) in pixels. valid: (N, K) bool, real
        tables. start: (N, 2) the robot's start (y, x) in pixels. target: (N,) int32 the table
        the object is on.
    """

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
    """What happened in N episodes of ``budget`` = L looks.

    found: (N,) bool found within the budget. looks: (N,) int32 looks made (until found, or L).
    travel: (N,) float32 pixels driven (until found, or in all L looks). shortest: (N,) pixels
    from the start straight to the true table. path: (N, L) int32 table of each look, −1 after
    the episode ended. travel_at: (N, L) pixels driven after each look. belief: (N, L, K) the
    belief each look was decided on (the prior, then after each failure; repeated after the end).
    """

    found: jnp.ndarray
    looks: jnp.ndarray
    travel: jnp.ndarray
    shortest: jnp.ndarray
    path: jnp.ndarray
    travel_at: jnp.ndarray
    belief: jnp.ndarray


# --------------------------------------------------------------------------- validation


def check_p_miss(p_miss) -> float:
    """``p_miss`` (the chance a look at the right table misses the object) as a float in
    [0, 1), else ``ValueError`` naming it."""
    return check_real("p_miss (the chance a look at the right table misses the object)", p_miss,
                      0.0, 1.0, high_open=True)


def check_belief(name: str, belief, valid) -> None:
    """Concrete belief (..., K): finite, ≥ 0, summing to 1 over the ``valid`` tables, 0 elsewhere.
    """
    b = np.asarray(belief, np.float64)
    v = np.asarray(valid, bool)
    if b.shape != v.shape:
        raise ValueError(f"{name} must have shape {v.shape} (one probability per table); got "
                         f"{b.shape}")
    if not np.all(np.isfinite(b)):
        raise ValueError(f"{name} contains NaN or inf")
    if np.any(b < -PROB_ATOL):
        raise ValueError(f"{name} has negative probabilities (min {b.min():.3g})")
    if np.any(np.abs(np.where(v, 0.0, b)) > PROB_ATOL):
        raise ValueError(f"{name} puts probability on padded (invalid) tables")
    total = b.sum(-1)
    if np.any(np.abs(total - 1.0) > PROB_ATOL):
        worst = total.ravel()[np.argmax(np.abs(total - 1.0).ravel())]
        raise ValueError(f"{name} must sum to 1 over the tables; found a sum of {worst:.6g}")


def check_episodes(episodes: Episodes, policy: str | None = None) -> Episodes:
    """Validate shapes and values (``ValueError`` naming the field); canonical dtypes."""
    if not isinstance(episodes, Episodes):
        raise ValueError(f"episodes must be an Episodes; got {type(episodes).__name__}")
    shape = np.shape(episodes.valid)
    if len(shape) != 2 or shape[0] < 1 or shape[1] < 1:
        raise ValueError(f"episodes.valid must have shape (N, K) with N, K ≥ 1; got {shape}")
    n, k = shape
    for field, expected in (("belief", (n, k)), ("centres", (n, k, 2)), ("start", (n, 2)),
                            ("target", (n,))):
        got = np.shape(getattr(episodes, field))
        if got != expected:
            raise ValueError(f"episodes.{field} must have shape {expected}; got {got}")
    valid = np.asarray(episodes.valid)
    if valid.dtype != np.bool_:
        raise ValueError(f"episodes.valid must be boolean; got {valid.dtype}")
    if not np.all(valid.any(-1)):
        raise ValueError("episodes.valid: every episode needs at least one real table")
    check_belief("episodes.belief", episodes.belief, valid)
    centres, start = np.asarray(episodes.centres), np.asarray(episodes.start)
    if not np.all(np.isfinite(centres[valid])) or not np.all(np.isfinite(start)):
        raise ValueError("episodes.centres / episodes.start contain NaN or inf")
    target = np.asarray(episodes.target)
    if not np.issubdtype(target.dtype, np.integer) or np.any((target < 0) | (target >= k)) \
            or not np.all(valid[np.arange(n), np.clip(target, 0, k - 1)]):
        raise ValueError(f"episodes.target must index a real table (0..{k - 1}, valid)")
    if policy == "optimal":
        check_optimal_size(int(valid.sum(-1).max()))
    return Episodes(belief=jnp.asarray(episodes.belief, jnp.float32),
                    centres=jnp.asarray(np.where(valid[..., None], centres, 0.0), jnp.float32),
                    valid=jnp.asarray(valid), start=jnp.asarray(start, jnp.float32),
                    target=jnp.asarray(target, jnp.int32))


def check_table_probs(name: str, probs) -> np.ndarray:
    """Concrete table probabilities (..., S + 1): finite, ≥ 0 and summing to 1 over the tables
    and the off bin (a prior that is NaN, inf, negative or all zero is not a prior)."""
    p = np.asarray(probs, np.float64)
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name} contains NaN or inf: not a prior (a model with diverged "
                         f"parameters?)")
    if np.any(p < -PROB_ATOL):
        raise ValueError(f"{name} has negative probabilities (min {p.min():.3g})")
    total = p.sum(-1)
    if np.any(np.abs(total - 1.0) > PROB_ATOL):
        worst = total.ravel()[np.argmax(np.abs(total - 1.0).ravel())]
        raise ValueError(f"{name} must sum to 1 over the tables and the off bin of each query; "
                         f"found a sum of {worst:.6g}")
    return p


def _outcome_bytes(num_episodes: int, num_tables: int, budget: int) -> int:
    """Bytes of an Outcome of ``num_episodes`` × ``budget`` looks, with the scan's copy."""
    return 2 * 4 * num_episodes * budget * (num_tables + 3)


def _look_flops(num_tables: int, policy: str) -> int:
    """Rough work of one look of one episode: the optimal policy's DP, else a few passes."""
    return 4 * 2 ** num_tables * num_tables ** 2 if policy == "optimal" else 32 * num_tables


def check_episodes_size(num_episodes: int, num_tables: int, budget: int, policy: str,
                        copies: int = 1) -> None:
    """``ValueError`` naming ``budget`` when ``copies`` × ``num_episodes`` episodes of
    ``budget`` looks over ``num_tables`` tables would be over the memory or work budget
    (:func:`flowmaps_jax.validation.check_resources`)."""
    n = copies * num_episodes
    check_resources(f"budget={budget} looks for {n} episodes over {num_tables} tables",
                    num_bytes=_outcome_bytes(n, num_tables, budget),
                    flops=n * budget * _look_flops(num_tables, policy))


def check_search_size(config: FlowSimConfig, num_rows: int, *, budget: int,
                      policies: Sequence[str], num_samples: int = 0,
                      chunk_rows: int = 50, predictors: Sequence[Any] = (),
                      what: str = "") -> None:
    """The whole search protocol's size, up front: the search set of ``num_rows`` scene rows
    (environments × times per environment), each prior's table probabilities, every row × policy
    run of ``budget`` looks, and each predictor's sampling. ``ValueError`` naming the arguments
    (``what`` says which set the rows) when over the memory or work budget."""
    m, f, s = config.num_objects, config.num_furniture, config.max_tokens
    rows = int(num_rows)
    k = min(f, 8)  # candidate tables of one kind: at most the furniture
    n = rows * m
    rows_text = f"{rows} scene rows ({what})" if what else f"{rows} scene rows"
    set_bytes = 2 * 4 * rows * (7 * s + 4 * f + m * (6 * f + 16))
    priors = 3 + len(predictors)
    prior_bytes = 4 * n * (s + 1) * priors
    check_resources(f"the search set of {rows_text}", num_bytes=set_bytes + prior_bytes)
    jobs = priors * len(policies) + 1
    kept = jobs * _outcome_bytes(n, k, budget) // 2
    every = _outcome_bytes(n * k, k, budget)  # expected_outcomes: every hiding place at once
    look = max(_look_flops(k, p) for p in policies)
    check_resources(f"budget={budget} looks x {len(policies)} policies x {priors} priors on "
                    f"{n} episodes of {rows_text}",
                    num_bytes=set_bytes + prior_bytes + kept + every,
                    flops=jobs * k * n * budget * look)
    for predictor in predictors:
        model, kind = getattr(predictor, "model", None), getattr(predictor, "kind", None)
        if model is None or kind not in ("flowmaps", "mlp"):
            continue
        from flowmaps_jax.model.sampling import DEFAULT_NUM_STEPS

        per_query, per_map = network_flops(model, kind, s)
        evaluations = solver_evaluations(DEFAULT_NUM_STEPS) if kind == "flowmaps" else 1
        check_resources(
            f"samples={num_samples} per query for {getattr(predictor, 'name', kind)} on "
            f"{n} queries of {rows_text}",
            num_bytes=4 * min(chunk_rows, rows) * m * num_samples * (4 * model.dim * (
                model.mlp_ratio + 4) + 4 * (s + 4)),
            flops=n * num_samples * evaluations * per_query + rows * per_map)


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
    """The belief (..., K) after a failed look at table ``looked`` (...) int.

    P(table j | not found at ``looked``) ∝ b_j · (p_miss if j = looked else 1). With p_miss = 0
    the looked-at table gets 0. If no mass is left, the result is uniform over the ``valid``
    tables (default all) looked at least often, counting this look (``looks_at`` (..., K) int:
    looks so far *including* this one; default: only this one).
    """
    p_miss = check_p_miss(p_miss)
    b = np.asarray(belief)
    valid = np.ones(b.shape, bool) if valid is None else np.asarray(valid, bool)
    check_belief("belief", b, valid)
    looked = np.asarray(looked)
    if looked.shape != b.shape[:-1] or not np.issubdtype(looked.dtype, np.integer) \
            or np.any((looked < 0) | (looked >= b.shape[-1])):
        raise ValueError(f"looked must be integer table indices of shape {b.shape[:-1]} in "
                         f"0..{b.shape[-1] - 1}")
    if looks_at is None:
        looks_at = (np.arange(b.shape[-1]) == looked[..., None]).astype(np.int32)
    return _update(jnp.asarray(b, jnp.float32), jnp.asarray(looked), p_miss, jnp.asarray(valid),
                   jnp.asarray(looks_at, jnp.int32))


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
    """Every episode of the batch (vmap) → Outcome (N, ...); one compiled program per
    (N, K, budget) for all policies. policy_index: int32 index into ``POLICIES`` (traced).
    No validation (usable inside a planner's own ``jit``): :func:`run_episodes` checks first."""
    keys = jax.random.split(key, episodes.num_episodes)
    one = functools.partial(_episode, budget=budget)
    return jax.vmap(one, in_axes=(0, 0, 0, 0, 0, 0, None, None))(
        episodes.belief, episodes.centres, episodes.valid, episodes.start, episodes.target,
        keys, p_miss, policy_index)


def run_episodes(episodes: Episodes, policy: str, key: jax.Array | None = None,
                 budget: int = DEFAULT_BUDGET, p_miss: float = 0.0) -> Outcome:
    """Run N episodes with ``policy`` (see :mod:`flowmaps_jax.search.policies`) → Outcome (N, ...).

    key: typed PRNG key for the detector's misses (only matters when p_miss > 0; default
    key(0)). budget: looks per episode (≥ 1). p_miss: in [0, 1). Raises ``ValueError`` for bad
    episodes, an unknown policy, p_miss outside [0, 1), a budget < 1, or "optimal" with more than
    7 tables. Compiled once per (N, K, budget), shared by all policies.
    """
    policy = check_policy(policy)
    budget = check_int("budget", budget)
    p_miss = check_p_miss(p_miss)
    episodes = check_episodes(episodes, policy)
    check_episodes_size(episodes.num_episodes, episodes.num_tables, budget, policy)
    key = jax.random.key(0) if key is None else check_key(key)
    return simulate(episodes, key, jnp.float32(p_miss), jnp.int32(POLICIES.index(policy)),
                     budget)


def expected_outcomes(episodes: Episodes, truth, policy: str,
                      budget: int = DEFAULT_BUDGET) -> tuple[Outcome, jnp.ndarray]:
    """Exact expectations over where the object hides, with a perfect detector.

    Runs every episode once per possible hiding table t (the K · N episodes in one batch;
    ``episodes.target`` is ignored) → (Outcome with leading axes (K, N, ...), weights (K, N) =
    ``truth`` transposed). truth: (N, K) the distribution of the object's table (e.g. the exact
    posterior). ``search.scores.expected_scores`` averages any score with these weights;
    :func:`at_targets` picks each episode's own target (its ``run_episodes`` outcome).
    """
    policy = check_policy(policy)
    budget = check_int("budget", budget)
    episodes = check_episodes(episodes, policy)
    check_belief("truth", truth, episodes.valid)
    k, n = episodes.num_tables, episodes.num_episodes
    check_episodes_size(n, k, budget, policy, copies=k)
    tiled = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (k, *a.shape)).reshape(
        k * n, *a.shape[1:]), episodes)
    tiled = tiled.replace(target=jnp.repeat(jnp.arange(k, dtype=jnp.int32), n))
    every = simulate(tiled, jax.random.key(0), jnp.float32(0.0),
                      jnp.int32(POLICIES.index(policy)), budget)
    every = jax.tree_util.tree_map(lambda a: a.reshape(k, n, *a.shape[1:]), every)
    return every, jnp.asarray(truth, jnp.float32).T


def at_targets(every: Outcome, target) -> Outcome:
    """From an every-target Outcome (K, N, ...) (:func:`expected_outcomes`), episode n's outcome
    with the object on ``target[n]`` → Outcome (N, ...): with a perfect detector, exactly what
    :func:`run_episodes` returns for those targets."""
    index = jnp.asarray(target, jnp.int32)
    n = jnp.arange(index.shape[0])
    return jax.tree_util.tree_map(lambda a: a[index, n], every)


# --------------------------------------------------------------------------- FlowSim queries


@struct.dataclass
class SearchSet:
    """Search queries in FlowSim scenes with their ground truth: R scene rows × M objects.

    tokens: SceneTokens (R, S) the map at τ; queries: Queries (R, M) every object at τ_q.
    env, tau, tau_q: (R,) int32 environment, state time (the map the robot saw) and query time.
    obj, horizon, slot_now, true_slot, num_slots: (R, M) int32 category index, Δτ = τ_q − τ,
        slot at τ (last seen), slot at τ_q in the rollout (where the object is), K.
    visit_order: (R, M, F) int32 furniture (token) index of each slot, −1 padded.
    slot_probs: (R, M, F) exact posterior over the slots (zero beyond K).
    furniture_px: (R, F, 4) pixel boxes (y0, x0, y1, x1) of the furniture; map_size: pixels.
    """

    tokens: SceneTokens
    queries: Queries
    env: jnp.ndarray
    tau: jnp.ndarray
    tau_q: jnp.ndarray
    slot_probs: jnp.ndarray
    true_slot: jnp.ndarray
    slot_now: jnp.ndarray
    num_slots: jnp.ndarray
    visit_order: jnp.ndarray
    obj: jnp.ndarray
    horizon: jnp.ndarray
    furniture_px: jnp.ndarray
    map_size: int = struct.field(pytree_node=False, default=256)

    @property
    def num_rows(self) -> int:
        return int(self.env.shape[0])

    @property
    def num_tables(self) -> int:
        """The candidate axis of its episodes: the most tables of one kind."""
        return int(np.max(np.asarray(self.num_slots)))


def build_search_set(scenes: Scenes, config: FlowSimConfig, key: jax.Array,
                     times_per_env: int = 1,
                     horizons: Sequence[int] | None = None) -> SearchSet:
    """Search queries for every environment of ``scenes``: every object is queried.

    Default: ``times_per_env`` rows per environment, each with τ ~ U{0..T−2} and τ_q ~
    U{τ+1..T−1} (the evaluation protocol's draws). ``horizons``: instead one row per environment
    and fixed Δτ in ``horizons`` (τ ~ U{0..T−1−Δτ}). Row r's times depend on ``key`` and r only.
    """
    check_instance("scenes", scenes, Scenes)
    check_instance("config", config, FlowSimConfig)
    key = check_key(key)
    t_max = config.num_timesteps
    if horizons is None:
        per_env, fixed = check_int("times_per_env", times_per_env), None
    else:
        fixed = [check_int("horizons entries", h) for h in horizons]
        if not fixed or max(fixed) >= t_max:
            raise ValueError(f"horizons must be a non-empty list of Δτ in 1..{t_max - 1}; "
                             f"got {list(horizons)}")
        per_env = len(fixed)
    rows = scenes.num_envs * per_env
    m, f, s = config.num_objects, config.num_furniture, config.max_tokens
    what = (f"{scenes.num_envs} environments x " + (f"times_per_env={per_env}" if fixed is None
                                                      else f"{per_env} horizons"))
    check_resources(f"the search set of {rows} scene rows ({what})",
                    num_bytes=2 * 4 * rows * (7 * s + 4 * f + m * (6 * f + 16)))
    env = jnp.arange(rows, dtype=jnp.int32) // per_env
    keys = jax.vmap(lambda r: jax.random.fold_in(jax.random.fold_in(key, _SALT_TIMES), r))(
        jnp.arange(rows))
    if fixed is None:  # the protocol's law: τ ~ U{0..T−2}, τ_q ~ U{τ+1..T−1}
        tau, tau_q = jax.vmap(lambda k: draw_query_times(k, (), (), config))(keys)
    else:
        tau, tau_q = jax.vmap(lambda k, h: draw_query_times(k, (), (), config, horizon=h))(
            keys, jnp.asarray(np.tile(fixed, scenes.num_envs), jnp.int32))
    tau, tau_q = tau.astype(jnp.int32), tau_q.astype(jnp.int32)
    m = config.num_objects
    obj = jnp.broadcast_to(jnp.arange(m, dtype=jnp.int32), (rows, m))
    horizon = jnp.broadcast_to((tau_q - tau)[:, None], (rows, m))
    slot = jnp.asarray(scenes.slot)
    slot_now, true_slot = slot[env, tau], slot[env, tau_q]
    num_slots = jnp.asarray(scenes.num_slots)[env]
    probs = exact_posterior(np.asarray(num_slots), np.asarray(slot_now), np.asarray(horizon),
                            config, tau=np.asarray(jnp.broadcast_to(tau[:, None], (rows, m))))
    return SearchSet(
        env=env, tau=tau, tau_q=tau_q, tokens=scene_tokens(scenes, env, tau, config),
        queries=Queries(descriptor=jnp.asarray(scenes.object_kind, jnp.int32)[env],
                        tau_q=jnp.broadcast_to(tau_q[:, None], (rows, m))),
        obj=obj, horizon=horizon.astype(jnp.int32), slot_now=slot_now.astype(jnp.int32),
        true_slot=true_slot.astype(jnp.int32), num_slots=num_slots.astype(jnp.int32),
        visit_order=jnp.asarray(scenes.visit_order, jnp.int32)[env],
        slot_probs=jnp.asarray(probs, jnp.float32),
        furniture_px=jnp.asarray(scenes.furniture_boxes, jnp.float32)[env],
        map_size=config.map_size)


# --------------------------------------------------------------------------- priors


def _check_set(search_set) -> SearchSet:
    return check_instance("search_set", search_set, SearchSet)


def exact_tables(search_set: SearchSet) -> jnp.ndarray:
    """The exact posterior at τ_q as table probabilities (R, M, S + 1) (the Bayes-optimal prior)."""
    s = _check_set(search_set)
    return slots_to_tables(s.slot_probs, s.visit_order, s.tokens.num_tokens)


def uniform_tables(search_set: SearchSet) -> jnp.ndarray:
    """Uniform over the K tables of the object's kind, as table probabilities (R, M, S + 1)."""
    s = _check_set(search_set)
    slots = slot_metrics.uniform_slots(s.num_slots, s.visit_order.shape[-1])
    return slots_to_tables(slots, s.visit_order, s.tokens.num_tokens)


def last_seen_tables(search_set: SearchSet) -> jnp.ndarray:
    """All mass on the table the object was seen on at τ, as table probabilities (R, M, S + 1)."""
    s = _check_set(search_set)
    slots = slot_metrics.last_seen_slots(s.slot_now, s.visit_order.shape[-1])
    return slots_to_tables(slots, s.visit_order, s.tokens.num_tokens)


def predictor_tables(predictor: Any, search_set: SearchSet, num_samples: int, key: jax.Array,
                     chunk_rows: int = 50, progress: bool = True, desc: str | None = None,
                     **sample_kwargs) -> jnp.ndarray:
    """A model's table probabilities (R, M, S + 1) for every query of the set.

    Runs :func:`table_probabilities` on chunks of ``chunk_rows`` scene rows (the last chunk is
    padded, so every chunk has one compiled shape); row r's samples come from
    ``fold_in(key, r)``, so the result does not depend on the chunk size.
    """
    s = _check_set(search_set)
    key = check_key(key)
    chunk = min(check_int("chunk_rows", chunk_rows), s.num_rows)
    if callable(getattr(predictor, "sample", None)):
        predictor = _FiniteSamples(predictor)
    row_keys = jax.vmap(lambda r: jax.random.fold_in(jax.random.fold_in(key, _SALT_SAMPLES), r))(
        jnp.arange(s.num_rows))
    parts = []
    starts = range(0, s.num_rows, chunk)
    label = desc or f"table probabilities ({getattr(predictor, 'name', '')})"
    for first in tqdm(starts, desc=label, unit="chunk", disable=not progress, leave=False):
        index = np.minimum(np.arange(first, first + chunk), s.num_rows - 1)
        part = jax.tree_util.tree_map(lambda a, i=index: a[i], (s.tokens, s.queries))
        probs = table_probabilities(predictor, *part, num_samples, row_keys[index],
                                    **sample_kwargs)
        parts.append(np.asarray(probs)[: min(chunk, s.num_rows - first)])
    return jnp.asarray(np.concatenate(parts))


class _FiniteSamples:
    """``predictor`` whose samples must be finite: NaN samples are off every table, so a diverged
    model's table probabilities would silently become "uniform over the kind"."""

    def __init__(self, predictor: Any):
        self._predictor = predictor

    def sample(self, *args, **kwargs):
        samples = self._predictor.sample(*args, **kwargs)
        if not np.all(np.isfinite(np.asarray(samples))):
            name = getattr(self._predictor, "name", type(self._predictor).__name__)
            source = getattr(self._predictor, "source", None)
            raise ValueError(f"predictor {name}{f' ({source})' if source else ''} gave non-finite "
                             f"samples: its parameters are probably diverged (NaN/inf or huge); "
                             f"no search number computed from them would mean anything")
        return samples

    def __getattr__(self, name: str):
        return getattr(self._predictor, name)


# --------------------------------------------------------------------------- episodes


@functools.partial(jax.jit, static_argnames="num_tables")
def _candidates(table_probs, visit_order, num_slots, slot_now, furniture_px, num_tables):
    order = visit_order[..., :num_tables]  # (R, M, K)
    valid = jnp.arange(num_tables) < num_slots[..., None]
    mass = jnp.where(valid, jnp.take_along_axis(table_probs, jnp.maximum(order, 0), axis=-1), 0.0)
    kind_mass = mass.sum(-1)
    uniform = valid / valid.sum(-1, keepdims=True)
    belief = jnp.where(kind_mass[..., None] > 0,
                       mass / jnp.maximum(kind_mass, _TINY)[..., None], uniform)
    box = jnp.take_along_axis(furniture_px[:, None], jnp.maximum(order, 0)[..., None], axis=2)
    centres = 0.5 * (box[..., :2] + box[..., 2:])  # (R, M, K, 2)
    last_seen = jnp.take_along_axis(centres, slot_now[..., None, None], axis=2)[..., 0, :]
    return belief, centres, valid, kind_mass, last_seen


def make_episodes(search_set: SearchSet, table_probs, start: str = "centre"
                  ) -> tuple[Episodes, jnp.ndarray]:
    """Episodes (N = R · M) over the K tables of each object's kind, from a prior's table
    probabilities (R, M, S + 1).

    ``table_probs`` must be a prior: finite, non-negative, each query's row summing to 1
    (``ValueError`` otherwise; see :func:`check_table_probs`). The belief is the prior's mass on
    those tables, renormalised (uniform over them if it puts none there); mass on other tables
    and off every table is dropped and returned as the second value, ``kind_mass`` (N,) = the
    fraction of the prior's mass on the right kind's tables.
    Candidate k is the k-th table of the object's visiting order; ``target`` is its slot at τ_q.
    start: "centre" (the map centre) or "last-seen" (the table the object was on at τ).
    """
    s = _check_set(search_set)
    if start not in STARTS:
        raise ValueError(f"start must be one of {STARTS}; got {start!r}")
    probs = jnp.asarray(table_probs, jnp.float32)
    expected = (*s.queries.descriptor.shape, s.tokens.num_tokens + 1)
    if probs.shape != expected:
        raise ValueError(f"table_probs must have shape {expected} (R, M, S + 1); got "
                         f"{probs.shape}")
    check_table_probs("table_probs", table_probs)
    belief, centres, valid, kind_mass, last_seen = _candidates(
        probs, s.visit_order, s.num_slots, s.slot_now, s.furniture_px, s.num_tables)
    n, k = int(np.prod(belief.shape[:2])), belief.shape[-1]
    origin = jnp.full((n, 2), s.map_size / 2.0, jnp.float32) if start == "centre" \
        else last_seen.reshape(n, 2)
    episodes = Episodes(belief=belief.reshape(n, k), centres=centres.reshape(n, k, 2),
                        valid=valid.reshape(n, k), start=origin,
                        target=s.true_slot.reshape(n))
    return episodes, kind_mass.reshape(n)


def truth_probs(search_set: SearchSet) -> jnp.ndarray:
    """The exact posterior over the episodes' candidate tables, (N, K) (for expectations)."""
    s = _check_set(search_set)
    q = s.slot_probs[..., : s.num_tables]
    return q.reshape(-1, q.shape[-1])
