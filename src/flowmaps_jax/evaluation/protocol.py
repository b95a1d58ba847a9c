"""The evaluation protocol: which queries are asked, and one row of per-query numbers per
predictor (the protocol and its numbers: docs/protocol.md).

E validation environments, one τ ~ U{0..T−2} and τ_q ~ U{τ+1..T−1} each, every object queried;
ground truth the exact posterior q over slots (given the last min(H, τ + 1) observations in
worlds with habits or H > 1, which add the rows "exact, H = 1" and "empirical frequency") and
the slot boxes; KL(q‖p) from ``kl_draws`` draws of :mod:`.kl`'s mixture shared by every row;
slot metrics (:mod:`.slots`) from the first n of the largest n samples.

:func:`build_eval_queries` makes the :class:`EvalSet`; :func:`reference_rows` and
:func:`evaluate_predictor` score it into :class:`RowResult` rows, each checking its own
arguments once and then running the unchecked jitted kernels.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from tqdm import tqdm

from flowmaps_jax import flow
from flowmaps_jax.evaluation.kl import kl_estimate, mixture_log_prob, mixture_samples
from flowmaps_jax.evaluation.priors import (
    draw_slot_histogram,
    one_hot_slots,
    uniform_over_slots,
    with_off_bin,
)
from flowmaps_jax.evaluation.slots import score_slots
from flowmaps_jax.flowsim.config import FlowSimConfig
from flowmaps_jax.flowsim.dynamics import exact_posterior
from flowmaps_jax.flowsim.habits import (
    EXACT_H1_ROW,
    empirical_row,
    history_references,
    uses_history,
)
from flowmaps_jax.flowsim.scenes import draw_query_times, normalise_boxes, scene_tokens, slot_boxes
from flowmaps_jax.predictor import DEFAULT_NUM_STEPS, Predictor
from flowmaps_jax.tables import assign_slots, histogram
from flowmaps_jax.tokens import Queries, SceneTokens
from flowmaps_jax.validation import check_choice, check_instance, check_int

DEFAULT_NUM_ENVS = 200
DEFAULT_SAMPLES = (25, 100)
DEFAULT_KL_DRAWS = 100
DEFAULT_CHUNK_ENVS = 50
DEFAULT_LIKELIHOOD_STEPS = 48
"""Grid points of the accurate likelihood (RK4 on the stiff grid of ``flow.time_grid``); its
integration error is estimated against a grid of twice as many intervals, on the first
``ERROR_ENVS`` environments (the chunks that hold them)."""
ERROR_ENVS = 50
DEFAULT_LIKELIHOOD_DRAWS = 25
"""The accurate likelihood runs on the first this-many of each query's KL draws (it costs ~10
times the paper's 10-point grid per point); the paper-grid KL uses all of them."""
REFERENCE_ROWS = ("oracle", "oracle samples", "smoothed-q samples", "last-seen", "uniform")
"""The reference rows of every eval set; one with a history (``EvalSet.habit`` set, H > 1) adds
``history_row_names(H)`` before "last-seen"."""
# fold_in salts of the evaluation seed
_SALT_QUERIES, _SALT_KL, _SALT_SAMPLES, _SALT_ORACLE, _SALT_SMOOTHED = 0, 1, 2, 3, 4


# --------------------------------------------------------------------------- the query set


@struct.dataclass
class EvalSet:
    """The evaluation queries with their ground truth. E environments × M objects each.

    env, tau, tau_q: (E,) int32 environment index into the scenes, state and query time.
    tokens: SceneTokens (E, S), the map of each environment at its τ.
    queries: Queries (E, M), every object of the environment at τ_q.
    obj, horizon, slot_now, num_slots: (E, M) int32 object index (category), Δτ = τ_q − τ,
        slot observed at τ, number of real slots K.
    slot_probs: (E, M, F) exact posterior q over slots (zero beyond K).
    slot_boxes: (E, M, F, 4) normalised (y, x, h, w) box b_k at each slot (zeros beyond K).
    slot_mask: (E, M, F) bool, True on the K real slots.
    target: (E, M, 4) the object's actual normalised box at τ_q (one draw of the truth).
    kl_points: (E, M, D, 4) draws x ~ q shared by every row's KL estimate.
    kl_log_q: (E, M, D) log q at those draws.

    Set only for an eval set with a history (habits worlds or H > 1; None on the paper's):
    habit: (E, M) int32 index into ``flowsim.HABITS`` of the habit each queried object follows.
    history: H, the observations q conditions on (a query at τ has min(H, τ + 1) of them); static.
    exact_h1: (E, M, F) the exact posterior given the map at τ alone (None when H = 1: it is q).
    empirical: (E, M, F) the fraction of the observed history spent at each slot (None when H = 1:
        it is last-seen).
    """

    env: jnp.ndarray
    tau: jnp.ndarray
    tau_q: jnp.ndarray
    tokens: SceneTokens
    queries: Queries
    obj: jnp.ndarray
    horizon: jnp.ndarray
    slot_now: jnp.ndarray
    num_slots: jnp.ndarray
    slot_probs: jnp.ndarray
    slot_boxes: jnp.ndarray
    slot_mask: jnp.ndarray
    target: jnp.ndarray
    kl_points: jnp.ndarray
    kl_log_q: jnp.ndarray
    habit: jnp.ndarray | None = None
    history: int | None = struct.field(pytree_node=False, default=None)
    exact_h1: jnp.ndarray | None = None
    empirical: jnp.ndarray | None = None

    @property
    def num_envs(self) -> int:
        return int(self.env.shape[0])

    @property
    def num_queries(self) -> int:
        return int(np.prod(self.obj.shape))

    @property
    def num_slots_padded(self) -> int:
        """F, the padded slot axis."""
        return int(self.slot_probs.shape[-1])

    def take(self, index: np.ndarray) -> EvalSet:
        """The sub-set of environments ``index`` (a 1-D integer array)."""
        return _take(self, jnp.asarray(index))


@jax.jit
def _take(evalset: EvalSet, index: jnp.ndarray) -> EvalSet:
    """Every array of ``evalset`` at rows ``index``: one compiled gather per index length (one
    small program per array and length when run eagerly)."""
    return jax.tree_util.tree_map(lambda a: a[index], evalset)


def _check_sample_counts(sample_counts) -> tuple[int, ...]:
    """``sample_counts`` as distinct positive ints (from a non-empty tuple or list), sorted."""
    if not isinstance(sample_counts, (tuple, list)) or not sample_counts:
        raise ValueError(f"sample_counts must be a tuple of sample counts; got {sample_counts!r}")
    counts = tuple(check_int(f"sample_counts[{i}]", n) for i, n in enumerate(sample_counts))
    if len(set(counts)) != len(counts):
        raise ValueError(f"sample_counts must not repeat values; got {counts}")
    return tuple(sorted(counts))


def history_row_names(history: int) -> tuple[str, ...]:
    """The extra reference rows of an eval set with ``history`` = H > 1 observations."""
    return (EXACT_H1_ROW, empirical_row(history)) if history > 1 else ()


def build_eval_queries(scenes, config: FlowSimConfig, key: jax.Array,
                       kl_draws: int = DEFAULT_KL_DRAWS, horizon: int | None = None,
                       history: int = 1) -> EvalSet:
    """The protocol's queries for every environment of ``scenes`` (all E of them).

    τ ~ U{0..T−2} and τ_q ~ U{τ+1..T−1} per environment, all M objects queried; exact posterior,
    slot boxes, and ``kl_draws`` draws from the ground-truth mixture q per query (≥ 2).
    Environment e's times and draws depend only on ``key`` and e. ``horizon``: instead a fixed
    Δτ (τ ~ U{0..T−1−Δτ}, τ_q = τ + Δτ), e.g. 1 for the routine diagnostic.
    ``history``: H, the observations the exact posterior is given. With H > 1 or a world with
    habits other than the routine (``config.has_habits``), q is ``history_posterior`` given the
    last min(H, τ + 1) observations and the EvalSet's ``habit``, ``history`` (and for H > 1
    ``exact_h1``, ``empirical``) are set; the times and draws do not depend on H.
    """
    check_instance("config", config, FlowSimConfig)
    kl_draws = check_int("kl_draws", kl_draws, 2)
    history = check_int("history", history, 1, config.num_timesteps)
    if horizon is not None:
        horizon = check_int("horizon", horizon, 1, config.num_timesteps - 1)
    num_envs = scenes.num_envs
    m = config.num_objects
    env = jnp.arange(num_envs, dtype=jnp.int32)
    tau, tau_q, kl_keys = _query_times_and_keys(key, num_envs, config, horizon)
    tokens = scene_tokens(scenes, env, tau, config)
    obj = jnp.broadcast_to(jnp.arange(m, dtype=jnp.int32), (num_envs, m))
    descriptor = jnp.asarray(scenes.object_kind, jnp.int32)[env]
    queries = Queries(descriptor=descriptor, tau_q=jnp.broadcast_to(tau_q[:, None], (num_envs, m)))
    horizon = (tau_q - tau)[:, None] + jnp.zeros_like(obj)
    slot_now = jnp.asarray(scenes.slot)[env, tau]  # (E, M)
    num_slots = jnp.asarray(scenes.num_slots)[env]  # (E, M)
    extra = {}
    if uses_history(config, history):
        extra, probs = _history_truth(scenes, config, tau, horizon, history)
    else:  # the paper's protocol, as before habits existed
        probs = exact_posterior(np.asarray(num_slots), np.asarray(slot_now), np.asarray(horizon),
                                config, tau=np.asarray(tau)[:, None] + np.zeros((1, m), np.int32))
    flat_env = jnp.repeat(env, m)
    boxes = slot_boxes(scenes, flat_env, obj.reshape(-1), config)
    boxes = jnp.asarray(boxes, jnp.float32).reshape(num_envs, m, *boxes.shape[1:])
    f = probs.shape[-1]
    mask = jnp.arange(f) < num_slots[..., None]
    target = normalise_boxes(jnp.asarray(scenes.object_boxes)[env, tau_q], config)

    # the ground truth is made here from validated inputs: the mixture's jitted kernels directly
    points = jax.vmap(lambda k, p, b, bm: mixture_samples(k, p, b, bm, kl_draws))(
        kl_keys, probs, boxes, mask)  # (E, M, kl_draws, 4), environment e from kl_keys[e]
    log_q = mixture_log_prob(points, probs, boxes, mask)
    return EvalSet(env=env, tau=tau, tau_q=tau_q, tokens=tokens, queries=queries, obj=obj,
                   horizon=horizon.astype(jnp.int32), slot_now=slot_now.astype(jnp.int32),
                   num_slots=num_slots.astype(jnp.int32), slot_probs=probs, slot_boxes=boxes,
                   slot_mask=mask, target=jnp.asarray(target, jnp.float32), kl_points=points,
                   kl_log_q=log_q, **extra)


@functools.partial(jax.jit, static_argnames=("num_envs", "config", "horizon"))
def _query_times_and_keys(key, num_envs: int, config: FlowSimConfig, horizon: int | None):
    """(τ (E,), τ_q (E,), the KL draws' keys (E,)) of :func:`build_eval_queries`: environment
    e's from ``key`` and e alone; one compiled program (eagerly, a few dozen small ones)."""
    env = jnp.arange(num_envs, dtype=jnp.int32)
    env_keys = jax.vmap(lambda e: jax.random.fold_in(jax.random.fold_in(key, _SALT_QUERIES), e))(
        env)
    # the paper's law, as the training batches draw it (or the fixed Δτ)
    tau, tau_q = jax.vmap(lambda k: draw_query_times(k, (), (), config, horizon=horizon))(
        env_keys)
    kl_keys = jax.vmap(lambda e: jax.random.fold_in(jax.random.fold_in(key, _SALT_KL), e))(env)
    return tau.astype(jnp.int32), tau_q.astype(jnp.int32), kl_keys


def _history_truth(scenes, config: FlowSimConfig, tau, horizon, history: int):
    """(EvalSet's history fields, q (E, M, F)) of the queries at τ (E,) with Δτ (E, M)
    (``flowsim.habits.history_references``: q given the last min(H, τ + 1) observations, each
    query's habit family, and for H > 1 the exact posterior given one observation and the
    empirical frequency of the observed history)."""
    env = np.arange(np.shape(horizon)[0], dtype=np.int32)
    probs, habit, extra = history_references(scenes, config, env, tau, horizon, history)
    fields = {"habit": habit, "history": history}
    if extra is not None:
        fields.update(exact_h1=extra[EXACT_H1_ROW], empirical=extra[empirical_row(history)])
    return fields, probs


# --------------------------------------------------------------------------- rows


@dataclasses.dataclass
class RowResult:
    """Per-query numbers of one row of the results table (numpy arrays, (E, M) unless noted).

    name: row label. kl, kl_stderr: Monte-Carlo KL(q‖p) and its standard error per query (for a
        flow, with the accurate likelihood when one was asked for).
    kl_paper: a flow's per-query KL with the paper's likelihood grid (``logp_steps`` points of
        the sampling solver; None for closed-form densities or when not computed).
    kl_error: a flow's integration error of the accurate KL, |KL(n points) − KL(2n − 1 points)|
        over the queries of the first ``ERROR_ENVS`` environments' chunks (0.0 for closed-form
        densities; None when not computed).
    slots: {n: {"p_hat": (E, M, F + 1), "tv", "top1", "search_cost_ratio"}} for each sample count
        n (reference rows: the same exact slot distribution for every n).
    samples: (E, M, n_max, 4) model samples (None for reference rows).
    info: free-form facts for the report (checkpoint, step, seconds).
    """

    name: str
    kl: np.ndarray
    kl_stderr: np.ndarray
    slots: dict[int, dict[str, np.ndarray]]
    samples: np.ndarray | None = None
    info: dict = dataclasses.field(default_factory=dict)
    kl_paper: np.ndarray | None = None
    kl_error: float | None = 0.0


def _slot_entry(evalset: EvalSet, p_hat) -> dict[str, np.ndarray]:
    """One sample count's entry of RowResult.slots: p̂ and its slot scores against q."""
    return {"p_hat": np.asarray(p_hat), **scores_against_q(evalset, p_hat)}


def scores_against_q(evalset: EvalSet, p_hat) -> dict[str, np.ndarray]:
    """The slot scores (``slots.slot_scores``'s kernels) of p̂ (E, M, F + 1) against the set's
    exact posterior."""
    return score_slots(np.asarray(p_hat, np.float32),
                       np.asarray(evalset.slot_probs, np.float32),
                       np.asarray(evalset.slot_mask, bool))


def slot_shares(evalset: EvalSet, samples) -> jnp.ndarray:
    """p̂ (E, M, F + 1) of a model's ``samples`` (E, M, n, 4) on the set's slots: the protocol's
    assignment (``tables.empirical_slots``'s kernels; the set's arrays were checked when it was
    built)."""
    return histogram(assign_slots(jnp.asarray(samples, jnp.float32),
                                  jnp.asarray(evalset.slot_boxes, jnp.float32),
                                  jnp.asarray(evalset.slot_mask, bool)),
                     evalset.num_slots_padded)


def reference_rows(evalset: EvalSet, sample_counts: Sequence[int] = DEFAULT_SAMPLES,
                   key: jax.Array | None = None) -> list[RowResult]:
    """The reference rows (docs/protocol.md): oracle, oracle samples, smoothed-q samples,
    last-seen, uniform; with a history of H > 1 also "exact, H = 1" and "empirical frequency"
    before last-seen. Their KL uses the ground-truth mixture with the row's slot weights on the
    shared draws (a sampled row's is its source's). ``key``: the draws of "oracle samples" and
    "smoothed-q samples" (default ``key(0)``).
    """
    counts = _check_sample_counts(sample_counts)
    key = jax.random.key(0) if key is None else key
    exact = {"oracle": with_off_bin(evalset.slot_probs),
             "last-seen": one_hot_slots(evalset.slot_now, evalset.num_slots_padded),
             "uniform": uniform_over_slots(evalset.num_slots, evalset.num_slots_padded)}
    names = list(REFERENCE_ROWS)
    if evalset.exact_h1 is not None:  # a history: its extra rows, before last-seen
        extra = history_row_names(evalset.history)
        exact.update(zip(extra, (with_off_bin(jnp.asarray(evalset.exact_h1, jnp.float32)),
                                 with_off_bin(jnp.asarray(evalset.empirical, jnp.float32))),
                         strict=True))
        names[names.index("last-seen"):names.index("last-seen")] = extra
    kls = {name: kl_estimate(evalset.kl_log_q, mixture_log_prob(
               evalset.kl_points, p_exact[..., :-1], evalset.slot_boxes, evalset.slot_mask))
           for name, p_exact in exact.items()}
    rows = []
    for name in names:
        if name == "oracle samples":  # q's density, a fresh histogram of n draws per count
            kl = kls["oracle"]
            slots = {n: _slot_entry(evalset, draw_slot_histogram(
                         jax.random.fold_in(jax.random.fold_in(key, _SALT_ORACLE), n),
                         jnp.asarray(evalset.slot_probs, jnp.float32), n)) for n in counts}
        elif name == "smoothed-q samples":  # boxes drawn from the continuous q, then assigned
            kl = kls["oracle"]
            draws = mixture_samples(jax.random.fold_in(key, _SALT_SMOOTHED), evalset.slot_probs,
                                    evalset.slot_boxes, evalset.slot_mask, counts[-1])
            slots = {n: _slot_entry(evalset, slot_shares(evalset, draws[..., :n, :]))
                     for n in counts}
        else:  # exact slot distributions: the same scores for every n
            kl, entry = kls[name], _slot_entry(evalset, exact[name])
            slots = dict.fromkeys(counts, entry)
        rows.append(RowResult(name=name, kl=np.asarray(kl.mean), kl_stderr=np.asarray(kl.stderr),
                              slots=slots))
    return rows


def evaluate_predictor(predictor: Predictor, evalset: EvalSet, key: jax.Array,
                       sample_counts: Sequence[int] = DEFAULT_SAMPLES,
                       chunk_envs: int = DEFAULT_CHUNK_ENVS, num_steps: int = DEFAULT_NUM_STEPS,
                       method: str = "midpoint", logp_steps: int | None = None,
                       progress: bool = True, name: str | None = None,
                       likelihood_steps: int | None = DEFAULT_LIKELIHOOD_STEPS,
                       likelihood_draws: int = DEFAULT_LIKELIHOOD_DRAWS) -> RowResult:
    """Score one model on every query of ``evalset``.

    Works in chunks of ``chunk_envs`` environments (M queries each, one encoder pass per
    environment; the last chunk is padded so every chunk has one compiled shape). Per chunk:
    max(sample_counts) samples per query (the first n are used for n < max) and log p at the
    shared KL draws. Environment e's samples use ``fold_in(key, e)``, so results do not depend
    on the chunk size. ``logp_steps``: ODE grid points of the paper's likelihood (the sampling
    ``method``; default num_steps). ``likelihood_steps``: grid points of the accurate likelihood
    (``flow`` method ``"accurate"``) that ``kl`` uses, with its integration error against
    2·n − 1 points; None skips it (``kl`` is then the paper grid's). ``likelihood_draws``: the
    accurate likelihood uses the first this-many KL draws of each query (all when fewer).
    """
    counts = _check_sample_counts(sample_counts)
    chunk_envs = check_int("chunk_envs", chunk_envs)
    if likelihood_steps is not None:
        likelihood_steps = check_int("likelihood_steps", likelihood_steps, 3)
    likelihood_draws = check_int("likelihood_draws", likelihood_draws, 2)
    method = check_choice("method", method, flow.SOLVERS)
    fewest_points = 3 if method == "accurate" else 2  # the solver's grid points
    num_steps = check_int("num_steps", num_steps, fewest_points)
    if logp_steps is not None:
        logp_steps = check_int("logp_steps", logp_steps, fewest_points)
    logp_steps = num_steps if logp_steps is None else logp_steps
    n_max = counts[-1]
    num_envs = evalset.num_envs
    chunk = min(chunk_envs, num_envs)
    num_chunks = math.ceil(num_envs / chunk)
    sample_key = jax.random.fold_in(key, _SALT_SAMPLES)
    env_keys = jax.vmap(lambda e: jax.random.fold_in(sample_key, e))(jnp.asarray(evalset.env))
    samples = []
    family = getattr(predictor, "family", None)  # None: a stand-in sampler
    flow_density = family is not None and family.uses_solver  # its likelihood: an ODE solve
    accurate = likelihood_steps is not None and flow_density
    solves = {"paper": (logp_steps, method)}
    if accurate:
        solves.update(accurate=(likelihood_steps, "accurate"),
                      tight=(2 * likelihood_steps - 1, "accurate"))
    log_p = {k: [] for k in solves}
    draws = min(likelihood_draws, evalset.kl_points.shape[2])
    label = name or predictor.name
    start = time.perf_counter()
    for c in tqdm(range(num_chunks), desc=f"evaluating {label}", unit="chunk",
                  disable=not progress, leave=False):
        index = np.minimum(np.arange(c * chunk, (c + 1) * chunk), num_envs - 1)
        part = evalset.take(index)
        s = predictor.sample(part.tokens, part.queries, n_max, env_keys[index],
                             num_steps=num_steps, method=method)
        keep = min(chunk, num_envs - c * chunk)
        points = {"paper": part.kl_points, "accurate": part.kl_points[:, :, :draws],
                  "tight": part.kl_points[:, :, :draws]}
        lps = {k: np.asarray(predictor.log_prob(part.tokens, part.queries, points[k],
                                                num_steps=n, method=m))[:keep]
               for k, (n, m) in solves.items() if k != "tight" or c * chunk < ERROR_ENVS}
        s = np.asarray(s)[:keep]
        if not (np.all(np.isfinite(s)) and all(np.all(np.isfinite(v)) for v in lps.values())):
            raise ValueError(f"{label} ({predictor.source}) gave non-finite samples or "
                             "log-densities: its parameters are probably diverged (NaN/inf or "
                             "huge); no metric computed from them would mean anything")
        samples.append(s)
        for k, v in lps.items():
            log_p[k].append(v)
    seconds = time.perf_counter() - start
    samples_all = np.concatenate(samples)
    kls = {k: kl_estimate(evalset.kl_log_q[:, :, :draws] if k == "accurate"
                          else evalset.kl_log_q, jnp.asarray(np.concatenate(v)))
           for k, v in log_p.items() if k != "tight"}
    kl = kls["accurate"] if accurate else kls["paper"]
    kl_error = 0.0 if not flow_density else None
    if accurate:  # on the environments the tighter grid ran on: the same draws, so log p differs
        tight = np.concatenate(log_p["tight"])
        kl_error = abs(float(np.mean(np.concatenate(log_p["accurate"])[:len(tight)] - tight)))
    slots = {n: _slot_entry(evalset, slot_shares(evalset, samples_all[:, :, :n])) for n in counts}
    info = {"kind": predictor.family_name, "source": predictor.source, "step": predictor.step,
            "seconds": round(seconds, 2), "num_steps": num_steps, "logp_steps": logp_steps,
            "method": method, "likelihood_steps": likelihood_steps if accurate else None,
            "likelihood_draws": draws if accurate else None}
    return RowResult(name=label, kl=np.asarray(kl.mean), kl_stderr=np.asarray(kl.stderr),
                     slots=slots, samples=samples_all, info=info,
                     kl_paper=np.asarray(kls["paper"].mean) if accurate else None,
                     kl_error=kl_error)
