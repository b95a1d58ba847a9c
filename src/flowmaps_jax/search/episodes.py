"""Search episodes in FlowSim scenes: the search set, each prior's table probabilities on it,
and the :class:`Episodes` they make for the simulator (:mod:`.simulator`).

:func:`build_search_set` draws the queries (as the evaluation protocol, or fixed horizons) with
their exact posterior (given the last H observations with habits or H > 1, plus the habit
family and :data:`EXACT_H1_ROW` and empirical-frequency rows) and true tables, and checks
everything it is built from; the priors (:func:`exact_tables`, :func:`uniform_tables`,
:func:`last_seen_tables`, :func:`extra_tables`, :func:`predictor_tables`),
:func:`history_tokens` and :func:`make_episodes` (over the K tables of the object's kind in
visiting order: ``target`` is the slot at τ_q) check only their other arguments. The
simulator's names are importable from here too.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from tqdm import tqdm

from flowmaps_jax.evaluation import priors as reference_priors
from flowmaps_jax.flowsim import (
    FlowSimConfig,
    Scenes,
    draw_query_times,
    exact_posterior,
    scene_tokens,
)
from flowmaps_jax.flowsim.habits import (  # noqa: F401  (names this module re-exports)
    EXACT_H1_ROW,
    empirical_row,
    history_references,
    uses_history,
)
from flowmaps_jax.model.flowmaps_family import DEFAULT_NUM_STEPS
from flowmaps_jax.resources import check_resources, network_flops, solver_evaluations
from flowmaps_jax.search.probabilities import spread_over_tables
from flowmaps_jax.search.simulator import (  # noqa: F401  (re-exported: the simulator's home was here)
    DEFAULT_BUDGET,
    Episodes,
    Outcome,
    at_targets,
    bayes_update,
    check_episodes,
    check_episodes_size,
    expected_outcomes,
    look_flops,
    outcome_bytes,
    run_episodes,
    simulate,
)
from flowmaps_jax.tables import table_probabilities
from flowmaps_jax.tokens import Queries, SceneTokens
from flowmaps_jax.validation import (
    PROB_ATOL,
    check_choice,
    check_instance,
    check_int,
    check_int_array,
    check_key,
    check_probabilities,
)

STARTS = ("centre", "last-seen")
_TINY = 1e-30
_SALT_TIMES, _SALT_SAMPLES = 11, 12


# --------------------------------------------------------------------------- sizes


def _set_bytes(config: FlowSimConfig, rows: int) -> int:
    """Bytes of a search set of ``rows`` scene rows (with a working copy)."""
    m, f, s = config.num_objects, config.num_furniture, config.max_tokens
    return 2 * 4 * rows * (7 * s + 4 * f + m * (6 * f + 16))


def check_search_size(config: FlowSimConfig, num_rows: int, *, budget: int,
                      policies: Sequence[str], num_samples: int = 0,
                      chunk_rows: int = 50, predictors: Sequence[Any] = (),
                      what: str = "", extra_rows: int = 0) -> None:
    """The whole search protocol's size, up front: the search set of ``num_rows`` scene rows
    (environments × times per environment), each prior's table probabilities, every row × policy
    run of ``budget`` looks, and each predictor's sampling. ``ValueError`` naming the arguments
    (``what`` says which set the rows) when over the memory or work budget. ``extra_rows``:
    reference rows beyond the exact posterior, uniform and last-seen (the habits path's two)."""
    m, f, s = config.num_objects, config.num_furniture, config.max_tokens
    rows = int(num_rows)
    k = min(f, 8)  # candidate tables of one kind: at most the furniture
    n = rows * m
    rows_text = f"{rows} scene rows ({what})" if what else f"{rows} scene rows"
    set_bytes = _set_bytes(config, rows)
    priors = 3 + int(extra_rows) + len(predictors)
    prior_bytes = 4 * n * (s + 1) * priors
    jobs = priors * len(policies) + 1
    kept = jobs * outcome_bytes(n, k, budget) // 2
    every = outcome_bytes(n * k, k, budget)  # expected_outcomes: every hiding place at once
    look = max(look_flops(k, p) for p in policies)
    check_resources(f"the search set of {rows_text} with budget={budget} looks x "
                    f"{len(policies)} policies x {priors} priors on its {n} episodes",
                    num_bytes=set_bytes + prior_bytes + kept + every,
                    flops=jobs * k * n * budget * look)
    for predictor in predictors:
        family = getattr(predictor, "family", None)  # None: a stand-in prior
        if family is None:
            continue
        model = predictor.model
        per_query, per_map = network_flops(model, s, family.gaussian is not None)
        evaluations = solver_evaluations(DEFAULT_NUM_STEPS) if family.uses_solver else 1
        check_resources(
            f"samples={num_samples} per query for {predictor.name} on "
            f"{n} queries of {rows_text}",
            num_bytes=4 * min(chunk_rows, rows) * m * num_samples * (4 * model.dim * (
                model.mlp_ratio + 4) + 4 * (s + 4)),
            flops=n * num_samples * evaluations * per_query + rows * per_map)


# --------------------------------------------------------------------------- FlowSim queries


@struct.dataclass
class SearchSet:
    """Search queries in FlowSim scenes with their ground truth: R scene rows × M objects.

    tokens: SceneTokens (R, S) the map at τ; queries: Queries (R, M) every object at τ_q.
    env, tau, tau_q: (R,) int32 environment, state time (the map the robot saw) and query time.
    obj, horizon, slot_now, true_slot, num_slots: (R, M) int32 category index, Δτ = τ_q − τ,
        slot at τ (last seen), slot at τ_q in the rollout (where the object is), K.
    visit_order: (R, M, F) int32 furniture (token) index of each slot, −1 padded.
    slot_probs: (R, M, F) exact posterior over the slots (zero beyond K): given the last
        ``history`` observations in a world with habits or with history > 1, otherwise the
        paper's one-observation posterior.
    furniture_px: (R, F, 4) pixel boxes (y0, x0, y1, x1) of the furniture; map_size: pixels.
    habit: (R, M) int32 index into ``flowsim.HABITS`` of the habit each object follows, or None
        (the paper's world with history 1: every object on the routine).
    extra_slots: {row name: (R, M, F)} the extra reference slot distributions (``EXACT_H1_ROW``,
        ``empirical_row(history)``; only with history > 1), or None.
    history: H, the observations ``slot_probs`` is given (``available_history``: fewer at τ < H−1).
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
    habit: jnp.ndarray | None = None
    extra_slots: dict[str, jnp.ndarray] | None = None
    history: int = struct.field(pytree_node=False, default=1)

    @property
    def num_rows(self) -> int:
        return int(self.env.shape[0])

    @property
    def num_tables(self) -> int:
        """The candidate axis of its episodes: the most tables of one kind."""
        return int(np.max(np.asarray(self.num_slots)))


def build_search_set(scenes: Scenes, config: FlowSimConfig, key: jax.Array,
                     times_per_env: int = 1,
                     horizons: Sequence[int] | None = None, history: int = 1) -> SearchSet:
    """Search queries for every environment of ``scenes``: every object is queried.

    Default: ``times_per_env`` rows per environment (the evaluation protocol's τ, τ_q draws);
    ``horizons``: one row per environment and fixed Δτ. Row r's times depend on ``key`` and r
    only. ``history`` H (1..T): with H > 1 or habits (:func:`uses_history`) the exact posterior
    is given the last min(H, τ + 1) observations and the set carries ``habit`` and
    ``extra_slots``.
    """
    check_instance("scenes", scenes, Scenes)
    check_instance("config", config, FlowSimConfig)
    key = check_key(key, "key")
    times_per_env = check_int("times_per_env", times_per_env)
    if horizons is not None:
        horizons = check_int_array("horizons", horizons, 1, shape=(None,))
    history = check_int("history", history, 1, config.num_timesteps)
    t_max = config.num_timesteps
    if horizons is None:
        per_env, fixed = times_per_env, None
    else:
        fixed = horizons.tolist()
        if not fixed or max(fixed) >= t_max:
            raise ValueError(f"horizons must be a non-empty list of Δτ in 1..{t_max - 1}; "
                             f"got {list(horizons)}")
        per_env = len(fixed)
    rows = scenes.num_envs * per_env
    what = (f"{scenes.num_envs} environments x " + (f"times_per_env={per_env}" if fixed is None
                                                      else f"{per_env} horizons"))
    check_resources(f"the search set of {rows} scene rows ({what})",
                    num_bytes=_set_bytes(config, rows))
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
    habit = extra = None
    if uses_history(config, history):
        probs, habit, extra = history_references(scenes, config, env, tau, horizon, history)
    else:  # the paper's world: the one-observation posterior, as always
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
        map_size=config.map_size, habit=habit, extra_slots=extra,
        history=history)


# --------------------------------------------------------------------------- priors


def exact_tables(search_set: SearchSet) -> jnp.ndarray:
    """The exact posterior at τ_q as table probabilities (R, M, S + 1) (the Bayes-optimal prior)."""
    s = search_set
    return spread_over_tables(s.slot_probs, s.visit_order, s.tokens.num_tokens)


def uniform_tables(search_set: SearchSet) -> jnp.ndarray:
    """Uniform over the K tables of the object's kind, as table probabilities (R, M, S + 1)."""
    s = search_set
    slots = reference_priors.uniform_over_slots(s.num_slots, s.visit_order.shape[-1])
    return spread_over_tables(slots, s.visit_order, s.tokens.num_tokens)


def extra_tables(search_set: SearchSet) -> dict[str, jnp.ndarray]:
    """The set's extra reference rows (``SearchSet.extra_slots``: the exact posterior given one
    observation, the empirical frequency of the last H) as table probabilities {name: (R, M,
    S + 1)}; empty for a set without them."""
    s = search_set
    return {name: spread_over_tables(slots, s.visit_order, s.tokens.num_tokens)
            for name, slots in (s.extra_slots or {}).items()}


def history_tokens(search_set: SearchSet, scenes: Scenes, config: FlowSimConfig,
                   history: int, max_tokens: int | None = None) -> SearchSet:
    """The set with the tokens a model sees: the map at τ and, for a model reading ``history``
    H > 1 maps, the objects of the H − 1 maps before it (``flowsim.scene_tokens(...,
    history=H)``), padded to ``config.max_tokens``, or to the model's own ``max_tokens`` when
    that is fewer (a one-map model in a search whose tokens have room for a history model's maps;
    :func:`pad_tables` brings its table probabilities back to the set's S). The same set for
    H = 1 and no fewer tokens. ``scenes`` and ``config`` are those the set was built from."""
    s = search_set
    if max_tokens is not None and max_tokens < s.tokens.num_tokens:
        config = dataclasses.replace(config, max_tokens=max_tokens)
    elif history == 1:
        return s
    return s.replace(tokens=scene_tokens(scenes, s.env, s.tau, config, history=history))


def pad_tables(table_probs, num_tokens: int) -> jnp.ndarray:
    """Table probabilities (..., S' + 1) over S' ≤ S tokens as (..., S + 1): the first S' tokens
    are the same tokens (tables first), the rest get no mass, the off bin stays last. Unchecked:
    :func:`history_tokens` never gives a model more tokens than the set has (S' ≤ S)."""
    probs = jnp.asarray(table_probs)
    extra = num_tokens + 1 - probs.shape[-1]
    if extra == 0:
        return probs
    zeros = jnp.zeros((*probs.shape[:-1], extra), probs.dtype)
    return jnp.concatenate([probs[..., :-1], zeros, probs[..., -1:]], axis=-1)


def last_seen_tables(search_set: SearchSet) -> jnp.ndarray:
    """All mass on the table the object was seen on at τ, as table probabilities (R, M, S + 1)."""
    s = search_set
    slots = reference_priors.one_hot_slots(s.slot_now, s.visit_order.shape[-1])
    return spread_over_tables(slots, s.visit_order, s.tokens.num_tokens)


def predictor_tables(predictor: Any, search_set: SearchSet, num_samples: int, key: jax.Array,
                     chunk_rows: int = 50, progress: bool = True, desc: str | None = None,
                     **sample_kwargs) -> jnp.ndarray:
    """A model's table probabilities (R, M, S + 1) for every query of the set.

    Runs :func:`.probabilities.table_probabilities` on chunks of ``chunk_rows`` scene rows (the
    last chunk is padded, so every chunk has one compiled shape); row r's samples come from
    ``fold_in(key, r)``, so the result does not depend on the chunk size. ``method`` (a keyword,
    default "samples") and the other keywords go to it. A model whose samples or table weights
    are not finite is an error naming it.
    """
    key = check_key(key, "key")
    chunk_rows = check_int("chunk_rows", chunk_rows)
    s = search_set
    chunk = min(chunk_rows, s.num_rows)
    method = sample_kwargs.pop("method", "samples")
    predictor = _Finite(predictor)
    row_keys = jax.vmap(lambda r: jax.random.fold_in(jax.random.fold_in(key, _SALT_SAMPLES), r))(
        jnp.arange(s.num_rows))
    parts, host = [], jax.tree_util.tree_map(np.asarray, (s.tokens, s.queries))
    starts = range(0, s.num_rows, chunk)
    label = desc or f"table probabilities ({getattr(predictor, 'name', '')})"
    for first in tqdm(starts, desc=label, unit="chunk", disable=not progress, leave=False):
        index = np.minimum(np.arange(first, first + chunk), s.num_rows - 1)
        part = jax.tree_util.tree_map(lambda a, i=index: a[i], host)  # no gather program
        probs = table_probabilities(predictor, *part, num_samples, row_keys[index], method,
                                    **sample_kwargs)
        parts.append(np.asarray(probs)[: min(chunk, s.num_rows - first)])
    return jnp.asarray(np.concatenate(parts))


class _Finite:
    """``predictor`` whose samples and table weights must be finite: NaN samples are off every
    table, so a diverged model's table probabilities would silently become "uniform over the
    kind"."""

    def __init__(self, predictor: Any):
        self._predictor = predictor

    def _finite(self, values, what: str):
        if not np.all(np.isfinite(np.asarray(values))):
            name = getattr(self._predictor, "name", type(self._predictor).__name__)
            source = getattr(self._predictor, "source", None)
            raise ValueError(f"predictor {name}{f' ({source})' if source else ''} gave non-finite "
                             f"{what}: its parameters are probably diverged (NaN/inf or huge); "
                             f"no search number computed from them would mean anything")
        return values

    def __getattr__(self, name: str):
        method = getattr(self._predictor, name)  # AttributeError when the predictor lacks it
        what = {"sample": "samples", "table_weights": "table weights"}.get(name)
        if what is None:
            return method
        return lambda *args, **kwargs: self._finite(method(*args, **kwargs), what)


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
    centres = jnp.where(valid[..., None], centres, 0.0)  # the simulator's canonical padding
    return belief, centres, valid, kind_mass, last_seen


def make_episodes(search_set: SearchSet, table_probs, start: str = "centre"
                  ) -> tuple[Episodes, jnp.ndarray]:
    """Episodes (N = R · M) over the K tables of each object's kind, from a prior's table
    probabilities (R, M, S + 1).

    ``table_probs`` must be a prior: finite, non-negative, each query's row summing to 1
    (``ValueError`` otherwise; float32 round-off allowed). The belief is the prior's mass on
    those tables, renormalised (uniform over them if it puts none there); mass on other tables
    and off every table is dropped and returned as the second value, ``kind_mass`` (N,) = the
    fraction of the prior's mass on the right kind's tables.
    Candidate k is the k-th table of the object's visiting order; ``target`` is its slot at τ_q.
    start: "centre" (the map centre) or "last-seen" (the table the object was on at τ).
    The episodes are canonical (as :func:`.simulator.check_episodes` returns them), ready for
    the simulator's cores.
    """
    s = search_set
    start = check_choice("start", start, STARTS)
    table_probs = check_probabilities(
        "table_probs", table_probs, (*s.queries.descriptor.shape, s.tokens.num_tokens + 1),
        atol=PROB_ATOL, min_value=-PROB_ATOL)
    probs = jnp.asarray(table_probs, jnp.float32)
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
    s = search_set
    q = s.slot_probs[..., : s.num_tables]
    return q.reshape(-1, q.shape[-1])
