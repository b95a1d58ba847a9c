"""The search protocol: every prior (row) driven by every policy on the same FlowSim episodes
(docs/search.md).

Rows, in report order: the exact posterior, the models, uniform over the kind, last-seen, and
nearest first (no prior); with habits or H > 1 also "exact, H = 1" and "empirical frequency",
and every summary split by habit (:func:`habit_sections`). Each row × policy is scored per
episode, summarised overall, by category and by Δτ, divided by the exact row under the same
policy, and with a perfect detector also in exact expectation over the true table. Priors,
policies, budget and sizes are checked once (:func:`score_priors`) before any episode runs.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from flowmaps_jax.evaluation.run import unique_names
from flowmaps_jax.flowsim import HABITS, FlowSimConfig, Scenes, world_of
from flowmaps_jax.search import episodes as ep
from flowmaps_jax.search import scores as sc
from flowmaps_jax.search import simulator as sim
from flowmaps_jax.tables import ASSIGN_TOLERANCE, TABLE_METHODS
from flowmaps_jax.validation import check_choice, check_int, check_real, prefix_errors

MAIN_POLICIES = ("most-probable", "greedy", "optimal")
"""The policies every prior is driven by (``"nearest"`` is the prior-free row)."""
EXACT_ROW = "exact posterior"
UNIFORM_ROW = "uniform over the kind"
LAST_SEEN_ROW = "last-seen first"
NEAREST_ROW = "nearest table first"
DEFAULT_NUM_ENVS = 200
DEFAULT_TIMES_PER_ENV = 2
DEFAULT_SAMPLES = 100
DISTANCE_POINTS = 61
_SALT_DETECTOR, _SALT_MODELS = 21, 22


@dataclasses.dataclass
class RowRun:
    """One row driven by one policy: its episodes (N,), Outcome (with beliefs), per-episode scores,
    exact-expectation scores (None with p_miss > 0) and kind_mass (N,) (the prior's mass on the
    tables of the object's kind before renormalising)."""

    name: str
    policy: str
    episodes: sim.Episodes
    outcome: sim.Outcome
    scores: dict[str, np.ndarray]
    expected: dict[str, np.ndarray] | None
    kind_mass: np.ndarray


def reference_priors(search_set: ep.SearchSet) -> dict[str, Any]:
    """Table probabilities (R, M, S + 1) of the reference rows that need no model, in report
    order: the exact posterior, the set's extra rows (``episodes.extra_tables``: none on the
    paper's protocol), uniform over the kind, last-seen first."""
    return {EXACT_ROW: ep.exact_tables(search_set), **ep.extra_tables(search_set),
            UNIFORM_ROW: ep.uniform_tables(search_set),
            LAST_SEEN_ROW: ep.last_seen_tables(search_set)}


def episode_groups(search_set: ep.SearchSet, config: FlowSimConfig) -> dict[str, np.ndarray]:
    """Per-episode labels (N,): "category" (name), "horizon" (Δτ) and, when the set has habits
    (``SearchSet.habit``), "habit" (a ``flowsim.HABITS`` name)."""
    names = np.asarray([c.name for c in config.categories])
    groups = {"category": names[np.asarray(search_set.obj).reshape(-1)],
              "horizon": np.asarray(search_set.horizon).reshape(-1)}
    if search_set.habit is not None:
        groups["habit"] = np.asarray(HABITS)[np.asarray(search_set.habit).reshape(-1)]
    return groups


def habit_sections(rows: dict) -> dict:
    """The per-habit sections of ``rows`` (from :func:`score_priors` on a set with habits):
    {habit: {"episodes": n, "rows": {row: {policy: {"summary", "ratio"[, "expected",
    "expected_ratio"]}}}}}, each part that habit's episodes only (the ratios to the exact
    posterior on the same episodes), habits in ``HABITS`` order; {} without habits."""
    first = next(iter(rows[EXACT_ROW]["policies"].values()))
    present = first["summary"].get("by_habit")
    if present is None:
        return {}
    parts = ("summary", "ratio", "expected", "expected_ratio")
    return {habit: {"episodes": int(present[habit]["count"]),
                    "rows": {name: {policy: {part: value[part]["by_habit"][habit]
                                             for part in parts if part in value}
                                    for policy, value in entry["policies"].items()}
                             for name, entry in rows.items()}}
            for habit in HABITS if habit in present}


def score_priors(search_set: ep.SearchSet, priors: dict[str, Any], config: FlowSimConfig, *,
                 policies: Sequence[str] = MAIN_POLICIES, budget: int = sim.DEFAULT_BUDGET,
                 p_miss: float = 0.0, start: str = "centre", key: jax.Array | None = None,
                 progress: bool = True) -> tuple[dict, dict[tuple[str, str], RowRun]]:
    """Drive every prior in ``priors`` ({row name: table probabilities (R, M, S + 1)}; must
    include ``EXACT_ROW``) by every policy, plus the nearest-table-first row.

    ``policies``: distinct names from ``MAIN_POLICIES`` ("nearest" is its own row, not a policy
    to drive the priors with).

    Returns (rows: {row: {"kind_mass": stat, "policies": {policy: {"summary", "ratio",
    "expected", "expected_ratio", "curves"}}}}, runs: {(row, policy): RowRun}).
    """
    budget = check_int("budget", budget)
    p_miss = check_real("p_miss", p_miss, 0.0, 1.0, high_open=True)
    if not isinstance(policies, (tuple, list)) or not policies:
        raise ValueError(f"policies must be a tuple of policy names; got {policies!r}")
    policies = tuple(check_choice("policies", p, MAIN_POLICIES) for p in policies)
    if len(set(policies)) != len(policies):
        raise ValueError(f"policies must be distinct names from {MAIN_POLICIES}; got {policies}")
    if EXACT_ROW not in priors:
        raise ValueError(f"priors must include the {EXACT_ROW!r} row (the reference)")
    key = jax.random.key(0) if key is None else key
    groups = episode_groups(search_set, config)
    weights = jnp.asarray(ep.truth_probs(search_set), jnp.float32).T  # (K, N), for expectations
    uniform_episodes, _ = ep.make_episodes(search_set, ep.uniform_tables(search_set), start)
    # each prior checked once, as it becomes episodes (the same for every policy)
    made = {name: ep.make_episodes(search_set, table_probs, start)
            for name, table_probs in priors.items()}
    made[NEAREST_ROW] = uniform_episodes, np.ones(uniform_episodes.num_episodes)
    n, k = uniform_episodes.num_episodes, uniform_episodes.num_tables
    for policy in (*policies, "nearest"):  # the sizes, before any episode runs (K: real tables)
        sim.check_episodes_size(n, k, budget, policy, copies=k if p_miss == 0.0 else 1)
    jobs = [(name, policy) for name in priors for policy in policies] + [(NEAREST_ROW, "nearest")]
    runs: dict[tuple[str, str], RowRun] = {}
    for name, policy in tqdm(jobs, desc="search episodes", unit="run", disable=not progress,
                             leave=False):
        episodes, mass = made[name]
        if p_miss == 0.0:  # one run per hiding place: exact expectations, and the rollout's
            every = sim.simulate_every_target(episodes, sim.policy_index(policy), budget)
            outcome = sim.at_targets(every, episodes.target)
            expected = sc.expected_scores(every, weights)
        else:  # the same misses for every row
            detector = jax.random.fold_in(key, _SALT_DETECTOR)
            outcome = sim.simulate(episodes, detector, jnp.float32(p_miss),
                                   sim.policy_index(policy), budget)
            expected = None
        runs[name, policy] = RowRun(name, policy, episodes, outcome, sc.episode_scores(outcome),
                                    expected, np.asarray(mass))
    return _summarise(runs, list(priors), policies, groups), runs


def _summarise(runs, names, policies, groups) -> dict:
    longest = max(float(r.scores["travel"].max()) for r in runs.values())
    grid = np.linspace(0.0, max(longest, 1.0), DISTANCE_POINTS)
    table: dict = {}
    for name in [*names, NEAREST_ROW]:
        entry: dict = {"policies": {}}
        for policy in policies:
            run = runs[name, "nearest" if name == NEAREST_ROW else policy]
            exact = runs[EXACT_ROW, policy]
            summary = sc.summarise_scores(run.scores, groups)
            part = {"summary": summary,
                    "ratio": sc.ratios(summary, sc.summarise_scores(exact.scores, groups)),
                    "curves": sc.success_curves(run.scores, grid)}
            if run.expected is not None:
                expected = sc.summarise_scores(run.expected, groups)
                part["expected"] = expected
                part["expected_ratio"] = sc.ratios(
                    expected, sc.summarise_scores(exact.expected, groups))
            entry["policies"][policy] = part
        entry["kind_mass"] = sc.mean_stat(runs[name, policies[0] if name != NEAREST_ROW
                                               else "nearest"].kind_mass)
        table[name] = entry
    return table


# --------------------------------------------------------------------------- the whole run


def _has_weights(predictor) -> bool:
    """Whether a predictor gives explicit table weights (``Predictor.has_table_weights``)."""
    return bool(getattr(predictor, "has_table_weights", False))


def model_history(predictor) -> int:
    """The maps a predictor reads (``model.history``; 1 for anything without it)."""
    return int(getattr(getattr(predictor, "model", None), "history", 1) or 1)


def run_search(predictors: Sequence[Any], scenes: Scenes, config: FlowSimConfig, *,
               seed: int = 0, num_samples: int = DEFAULT_SAMPLES,
               times_per_env: int = DEFAULT_TIMES_PER_ENV, horizons: Sequence[int] | None = None,
               policies: Sequence[str] = MAIN_POLICIES, budget: int = sim.DEFAULT_BUDGET,
               p_miss: float = 0.0, start: str = "centre", chunk_rows: int = 50,
               progress: bool = True, table_method: str = "weights", history: int = 1,
               **sample_kwargs) -> tuple[dict, dict[tuple[str, str], RowRun], ep.SearchSet]:
    """The protocol on every environment of ``scenes``: queries, priors (the reference rows and
    one row per predictor, in the order given), every row × policy → (results, runs, search set).
    A predictor (a Predictor or a stand-in) names the ``flowsim`` config it was trained on.

    ``config`` is the world ``scenes`` come from (``flowsim.world_config``); ``history``: the
    observations the exact posterior is given (``episodes.build_search_set``). On the habits
    path (``episodes.uses_history``) each model reads its own ``model.history`` maps, its row
    is named "NAME (H = h)", and ``results`` gains "habits" (:func:`habit_sections`) and the
    protocol's "world" and "history".

    ``results`` is search.json's content. ``table_method``: "weights" (default: a read-out
    head's mixture weights; models without them are sampled) or "samples" (``num_samples``).
    """
    seed = check_int("seed", seed, None)
    num_samples = check_int("num_samples", num_samples)
    table_method = check_choice("table_method", table_method, TABLE_METHODS)
    policies = tuple(policies)
    for p in predictors:
        if p.flowsim.map_size != config.map_size or p.flowsim.categories != config.categories:
            raise ValueError(f"predictors: {getattr(p, 'name', p)} was trained on another FlowSim "
                             "config (map size or categories) than the search scenes")
    started = time.perf_counter()
    key = jax.random.key(int(seed))
    habits = ep.uses_history(config, history)
    search_set = ep.build_search_set(scenes, config, key, times_per_env, horizons, history)
    reference = reference_priors(search_set)
    priors = {EXACT_ROW: reference.pop(EXACT_ROW)}
    seconds = {}
    labels = [getattr(p, "name", type(p).__name__) for p in predictors]
    if habits:
        labels = [f"{label} (H = {model_history(p)})"
                  for label, p in zip(labels, predictors, strict=True)]
    names = unique_names(labels)
    for predictor, name in zip(predictors, names, strict=True):
        t0 = time.perf_counter()
        method = table_method if _has_weights(predictor) else "samples"
        # a model reading H maps gets them all, each model no more tokens than it takes
        with prefix_errors(f"predictors: {name} reads {model_history(predictor)} maps, which do "
                           "not fit its tokens: "):
            its_set = ep.history_tokens(search_set, scenes, config, model_history(predictor),
                                        predictor.flowsim.max_tokens)
        priors[name] = ep.predictor_tables(predictor, its_set, num_samples,
                                           jax.random.fold_in(key, _SALT_MODELS), chunk_rows,
                                           progress, desc=f"{method} of {name}", method=method,
                                           **sample_kwargs)
        priors[name] = ep.pad_tables(priors[name], search_set.tokens.num_tokens)
        seconds[name] = round(time.perf_counter() - t0, 1)
    priors.update(reference)
    rows, runs = score_priors(search_set, priors, config, policies=policies, budget=budget,
                              p_miss=p_miss, start=start, key=key, progress=progress)
    for predictor, name in zip(predictors, names, strict=True):
        rows[name]["info"] = {"kind": getattr(predictor, "family_name", None),
                              "source": getattr(predictor, "source", None),
                              "step": getattr(predictor, "step", None),
                              "table_method": (table_method if _has_weights(predictor)
                                               else "samples"),
                              "sampling_seconds": seconds[name]}
    results = {
        "protocol": {
            "num_envs": int(scenes.num_envs), "scene_rows": search_set.num_rows,
            "episodes": int(np.prod(search_set.obj.shape)),
            "times_per_env": None if horizons is not None else int(times_per_env),
            "horizons": None if horizons is None else [int(h) for h in horizons],
            "num_samples": num_samples, "table_method": table_method,
            "policies": list(policies),  # as score_priors checked them
            "budget": int(budget), "p_miss": float(p_miss), "start": start, "seed": int(seed),
            "assign_tolerance": ASSIGN_TOLERANCE, "dynamics": config.dynamics,
            "map_size": config.map_size, "max_tables": search_set.num_tables},
        "rows": rows,
        "figures": [],
        "seconds": round(time.perf_counter() - started, 1),
    }
    if habits:  # the paper's protocol keeps its report as it was
        results["protocol"].update(world=world_of(config), habits=[list(h) for h in config.habits],
                                   history=int(search_set.history))
        results["habits"] = habit_sections(rows)
    return results, runs, search_set
