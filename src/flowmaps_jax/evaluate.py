"""Evaluation against the exact posterior: ``python -m flowmaps_jax.evaluate``.

Implements the evaluation protocol of DESIGN.md / issue 4::

    python -m flowmaps_jax.evaluate --checkpoint runs/flowmaps-cpu-X \\
        --baseline runs/mlp-cpu-Y [--baseline ...] [--out DIR] [--num-envs 200] \\
        [--samples 25,100] [--kl-draws 100] [--seed 0]

Protocol
--------
* E validation environments (``flowsim.scenes.validation_split``; 200 by default). For each
  environment one state time τ ~ U{0..T−2} and one query time τ_q ~ U{τ+1..T−1}; each of its M
  objects is queried (E·M = 600 queries). The map at τ is encoded once and shared by its M queries.
* Ground truth: the exact posterior q (M objects × F slots, zero beyond the K real slots) of
  ``flowsim.exact_posterior`` and the boxes b_k the object would have at slot k
  (``flowsim.scenes.slot_boxes``).
* Continuous KL(q‖p) = E_{x~q}[log q(x) − log p(x)] with q the Gaussian mixture of
  :mod:`flowmaps_jax.metrics`, estimated with ``kl_draws`` draws per query. The draws are made once
  and shared by every row (common random numbers, so row differences are less noisy).
  log p is exact: change of variables for FlowMaps, closed form for the MLP, and for the slot
  predictors (oracle / last-seen / uniform) the same mixture with their slot weights.
* Slot metrics from n samples (n in ``--samples``; the first n of the largest n drawn): p̂ by
  nearest-slot assignment (radius 0.05), total variation, top-1, search cost / oracle search cost.
  The reference rows use their slot distribution directly (no sampling), so the oracle has TV 0.
* Every number overall, by category and by horizon Δτ = τ_q − τ, as mean ± standard error over
  queries.

Outputs (``--out``): ``results.json``, ``results.md`` (with the route-offset mass one step
ahead: the routine diagnostic) and the figures ``kl.png`` (paper Fig. 2), ``by_horizon.png``,
``samples.png`` (paper Fig. 3) and ``slots.png`` (learned vs exact slot distributions).

The pieces are functions so notebooks can call them: :func:`build_eval_queries`,
:func:`reference_rows`, :func:`evaluate_predictor`, :func:`summarise_rows`,
:func:`write_report`, :func:`plot_kl`, :func:`plot_samples`, :func:`plot_slot_bars`,
:func:`run_evaluation`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import pathlib
import sys
import time
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from matplotlib.figure import Figure
from tqdm import tqdm

from flowmaps_jax import flow, metrics
from flowmaps_jax.flowsim.config import FlowSimConfig
from flowmaps_jax.flowsim.dynamics import exact_posterior
from flowmaps_jax.sample import DEFAULT_NUM_STEPS, SOLVERS, Predictor, load
from flowmaps_jax.tokens import Queries, SceneTokens
from flowmaps_jax.validation import check_int

DEFAULT_NUM_ENVS = 200
DEFAULT_SAMPLES = (25, 100)
DEFAULT_KL_DRAWS = 100
DEFAULT_CHUNK_ENVS = 50
REFERENCE_ROWS = ("oracle", "oracle samples", "last-seen", "uniform")
SLOT_METRICS = ("tv", "top1", "search_cost_ratio")
ROUTE_LABELS = ("0", "+1", "+2", "+3", "beyond", "off")
# fold_in salts of the evaluation seed
_SALT_QUERIES, _SALT_KL, _SALT_SAMPLES, _SALT_ORACLE = 0, 1, 2, 3


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
        index = np.asarray(index)
        return jax.tree_util.tree_map(lambda a: a[index], self)


def build_eval_queries(scenes, config: FlowSimConfig, key: jax.Array,
                       kl_draws: int = DEFAULT_KL_DRAWS, horizon: int | None = None) -> EvalSet:
    """The protocol's queries for every environment of ``scenes`` (all E of them).

    τ ~ U{0..T−2} and τ_q ~ U{τ+1..T−1} per environment, all M objects queried; exact posterior,
    slot boxes, and ``kl_draws`` draws from the ground-truth mixture q per query (≥ 2).
    Environment e's times and draws depend only on ``key`` and e. ``horizon``: instead a fixed
    Δτ (τ ~ U{0..T−1−Δτ}, τ_q = τ + Δτ), e.g. 1 for the routine diagnostic.
    """
    from flowmaps_jax.flowsim.scenes import normalise_boxes, scene_tokens, slot_boxes

    if not isinstance(config, FlowSimConfig):
        raise ValueError(f"config must be a FlowSimConfig; got {type(config).__name__}")
    kl_draws = check_int("kl_draws", kl_draws, 2)
    num_envs = scenes.num_envs
    t_max = config.num_timesteps
    if horizon is not None:
        horizon = check_int("horizon", horizon, 1)
        if horizon >= t_max:
            raise ValueError(f"horizon must be < num_timesteps={t_max}; got {horizon}")
    m = config.num_objects
    env = jnp.arange(num_envs, dtype=jnp.int32)
    env_keys = jax.vmap(lambda e: jax.random.fold_in(jax.random.fold_in(key, _SALT_QUERIES), e))(
        env)

    def times(k):
        k_tau, k_q = jax.random.split(k)
        if horizon is not None:
            tau = jax.random.randint(k_tau, (), 0, t_max - horizon)
            return tau, tau + horizon
        tau = jax.random.randint(k_tau, (), 0, t_max - 1)
        return tau, jax.random.randint(k_q, (), tau + 1, t_max)

    tau, tau_q = jax.vmap(times)(env_keys)
    tau, tau_q = tau.astype(jnp.int32), tau_q.astype(jnp.int32)
    tokens = scene_tokens(scenes, env, tau, config)
    obj = jnp.broadcast_to(jnp.arange(m, dtype=jnp.int32), (num_envs, m))
    descriptor = jnp.asarray(scenes.object_kind, jnp.int32)[env]
    queries = Queries(descriptor=descriptor, tau_q=jnp.broadcast_to(tau_q[:, None], (num_envs, m)))
    horizon = (tau_q - tau)[:, None] + jnp.zeros_like(obj)
    slot_now = jnp.asarray(scenes.slot)[env, tau]  # (E, M)
    num_slots = jnp.asarray(scenes.num_slots)[env]  # (E, M)
    probs = exact_posterior(np.asarray(num_slots), np.asarray(slot_now), np.asarray(horizon),
                            config, tau=np.asarray(tau)[:, None] + np.zeros((1, m), np.int32))
    flat_env = jnp.repeat(env, m)
    boxes = slot_boxes(scenes, flat_env, obj.reshape(-1), config)
    boxes = jnp.asarray(boxes, jnp.float32).reshape(num_envs, m, *boxes.shape[1:])
    f = probs.shape[-1]
    mask = jnp.arange(f) < num_slots[..., None]
    target = normalise_boxes(jnp.asarray(scenes.object_boxes)[env, tau_q], config)

    kl_keys = jax.vmap(lambda e: jax.random.fold_in(jax.random.fold_in(key, _SALT_KL), e))(env)
    points = _draw_kl_points(kl_keys, probs, boxes, mask, kl_draws)
    log_q = metrics.gt_mixture_log_prob(points, probs, boxes, mask)
    return EvalSet(env=env, tau=tau, tau_q=tau_q, tokens=tokens, queries=queries, obj=obj,
                   horizon=horizon.astype(jnp.int32), slot_now=slot_now.astype(jnp.int32),
                   num_slots=num_slots.astype(jnp.int32), slot_probs=probs, slot_boxes=boxes,
                   slot_mask=mask, target=jnp.asarray(target, jnp.float32), kl_points=points,
                   kl_log_q=log_q)


def _draw_kl_points(env_keys, probs, boxes, mask, n: int):
    """(E, M, n, 4) draws from q, environment e from env_keys[e]."""
    return jax.vmap(lambda k, p, b, m: metrics.sample_gt_mixture(k, p, b, n, m))(
        env_keys, probs, boxes, mask)


# --------------------------------------------------------------------------- scoring


def slot_scores(evalset: EvalSet, p_hat) -> dict[str, np.ndarray]:
    """Per-query slot metrics of a slot distribution p̂ (E, M, F + 1): tv, top1,
    search_cost_ratio, each (E, M) numpy."""
    q, mask = evalset.slot_probs, evalset.slot_mask
    return {
        "tv": np.asarray(metrics.slot_tv(p_hat, q)),
        "top1": np.asarray(metrics.top1(p_hat, q, mask)),
        "search_cost_ratio": np.asarray(metrics.search_cost_ratio(p_hat, q, mask)),
    }


@dataclasses.dataclass
class RowResult:
    """Per-query numbers of one row of the results table (numpy arrays, (E, M) unless noted).

    name: row label. kl, kl_stderr: Monte-Carlo KL(q‖p) and its standard error per query.
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


def reference_rows(evalset: EvalSet, sample_counts: Sequence[int] = DEFAULT_SAMPLES,
                   key: jax.Array | None = None) -> list[RowResult]:
    """The reference rows: oracle (q itself), oracle samples (n draws from q: the finite-sample
    ceiling of any sampler's slot metrics), last-seen (stays at its slot), uniform (K slots).

    Their KL uses the ground-truth mixture with the row's slot weights as the density
    (:func:`metrics.kl_slot_model` on the shared draws): exactly 0 for the oracle, and for oracle
    samples too (a perfect sampler's density is q; only its slot histogram is noisy).
    ``key``: the draws of "oracle samples" (default ``PRNGKey(0)``).
    """
    f = evalset.num_slots_padded
    key = jax.random.PRNGKey(0) if key is None else key
    exact = {
        "oracle": metrics.oracle_slots(evalset.slot_probs),
        "last-seen": metrics.last_seen_slots(evalset.slot_now, f),
        "uniform": metrics.uniform_slots(evalset.num_slots, f),
    }
    kls = {}
    for name, p_exact in exact.items():
        log_p = metrics.gt_mixture_log_prob(evalset.kl_points, p_exact[..., :-1],
                                            evalset.slot_boxes, evalset.slot_mask)
        kls[name] = metrics.continuous_kl(evalset.kl_log_q, log_p)
    rows = []
    for name in REFERENCE_ROWS:
        # a perfect sampler's density is q: "oracle samples" shares the oracle's q and KL
        p_exact, kl = exact.get(name, exact["oracle"]), kls.get(name, kls["oracle"])
        if name == "oracle samples":  # a fresh histogram of n draws per sample count
            slots = {}
            for n in sample_counts:
                oracle_key = jax.random.fold_in(jax.random.fold_in(key, _SALT_ORACLE), n)
                p_hat = metrics.sampled_oracle_slots(oracle_key, evalset.slot_probs, int(n))
                slots[int(n)] = {"p_hat": np.asarray(p_hat), **slot_scores(evalset, p_hat)}
        else:  # exact slot distributions: the same scores for every n
            scores = {"p_hat": np.asarray(p_exact), **slot_scores(evalset, p_exact)}
            slots = {int(n): scores for n in sample_counts}
        rows.append(RowResult(name=name, kl=np.asarray(kl.mean), kl_stderr=np.asarray(kl.stderr),
                              slots=slots))
    return rows


def _check_counts(sample_counts: Sequence[int]) -> tuple[int, ...]:
    counts = tuple(sample_counts)
    if not counts:
        raise ValueError("sample_counts must hold at least one sample count")
    for n in counts:
        check_int("sample_counts entries", n, 1)
    if len(set(counts)) != len(counts):
        raise ValueError(f"sample_counts must not repeat values; got {counts}")
    return tuple(sorted(int(n) for n in counts))


def _check_ode(num_steps, method, logp_steps) -> tuple[int, str, int]:
    """Validated (num_steps, method, logp_steps); logp_steps defaults to num_steps."""
    num_steps, method = flow.check_solver(num_steps, method)
    if logp_steps is None:
        return num_steps, method, num_steps
    return num_steps, method, flow.check_solver(logp_steps, method, name="logp_steps")[0]


def evaluate_predictor(predictor: Predictor, evalset: EvalSet, key: jax.Array,
                       sample_counts: Sequence[int] = DEFAULT_SAMPLES,
                       chunk_envs: int = DEFAULT_CHUNK_ENVS, num_steps: int = DEFAULT_NUM_STEPS,
                       method: str = "midpoint", logp_steps: int | None = None,
                       progress: bool = True, name: str | None = None) -> RowResult:
    """Score one model on every query of ``evalset``.

    Works in chunks of ``chunk_envs`` environments (M queries each, one encoder pass per
    environment; the last chunk is padded so every chunk has one compiled shape). Per chunk:
    max(sample_counts) samples per query (the first n are used for n < max) and log p at the
    shared KL draws. Environment e's samples use ``fold_in(key, e)``, so results do not depend
    on the chunk size. ``logp_steps``: ODE grid points of the likelihood (default num_steps).
    """
    counts = _check_counts(sample_counts)
    chunk_envs = check_int("chunk_envs", chunk_envs, 1)
    num_steps, method, logp_steps = _check_ode(num_steps, method, logp_steps)
    n_max = counts[-1]
    num_envs = evalset.num_envs
    chunk = min(chunk_envs, num_envs)
    num_chunks = math.ceil(num_envs / chunk)
    sample_key = jax.random.fold_in(key, _SALT_SAMPLES)
    env_keys = jax.vmap(lambda e: jax.random.fold_in(sample_key, e))(jnp.asarray(evalset.env))
    samples, log_p = [], []
    label = name or predictor.name
    start = time.perf_counter()
    for c in tqdm(range(num_chunks), desc=f"evaluating {label}", unit="chunk",
                  disable=not progress, leave=False):
        index = np.minimum(np.arange(c * chunk, (c + 1) * chunk), num_envs - 1)
        part = evalset.take(index)
        s = predictor.sample(part.tokens, part.queries, n_max, env_keys[index],
                             num_steps=num_steps, method=method)
        lp = predictor.log_prob(part.tokens, part.queries, part.kl_points, num_steps=logp_steps,
                                method=method)
        keep = min(chunk, num_envs - c * chunk)
        samples.append(np.asarray(s)[:keep])
        log_p.append(np.asarray(lp)[:keep])
    seconds = time.perf_counter() - start
    samples_all = np.concatenate(samples)
    log_p_all = np.concatenate(log_p)
    kl = metrics.continuous_kl(evalset.kl_log_q, jnp.asarray(log_p_all))
    slots = {}
    for n in counts:
        p_hat = metrics.empirical_slots(samples_all[:, :, :n], evalset.slot_boxes,
                                        evalset.slot_mask)
        slots[n] = {"p_hat": np.asarray(p_hat), **slot_scores(evalset, p_hat)}
    info = {"kind": predictor.kind, "source": predictor.source, "step": predictor.step,
            "seconds": round(seconds, 2), "num_steps": num_steps, "logp_steps": logp_steps,
            "method": method}
    return RowResult(name=label, kl=np.asarray(kl.mean), kl_stderr=np.asarray(kl.stderr),
                     slots=slots, samples=samples_all, info=info)


# --------------------------------------------------------------------------- aggregation


def _json_number(x: float) -> float | None:
    return None if not math.isfinite(x) else float(x)


def _clean(summary: dict) -> dict:
    """metrics.summarise output → JSON-safe {mean, stderr, count} (NaN → None)."""
    return {"mean": _json_number(summary["mean"]), "stderr": _json_number(summary["stderr"]),
            "count": int(summary["count"])}


def _breakdown(values: np.ndarray, evalset: EvalSet, config: FlowSimConfig) -> dict:
    """{"overall", "by_category", "by_horizon"} of per-query values (E, M)."""
    names = np.asarray([c.name for c in config.categories])[np.asarray(evalset.obj)]
    overall = metrics.summarise(values)["overall"]
    by_cat = metrics.summarise(values, names)["by_group"]
    by_h = metrics.summarise(values, np.asarray(evalset.horizon))["by_group"]
    cat_order = [c.name for c in config.categories if c.name in by_cat]
    return {"overall": _clean(overall),
            "by_category": {k: _clean(by_cat[k]) for k in cat_order},
            "by_horizon": {str(k): _clean(v) for k, v in sorted(by_h.items())}}


def summarise_rows(rows: Sequence[RowResult], evalset: EvalSet, config: FlowSimConfig) -> dict:
    """{row name: {"kl": breakdown, "slots": {n: {metric: breakdown}}, "info": {...}}}.

    A breakdown is {"overall": {mean, stderr, count}, "by_category": {name: ...},
    "by_horizon": {Δτ: ...}}. The KL stderr is over queries (it includes the Monte-Carlo error);
    "kl_mc_stderr" is the mean per-query Monte-Carlo standard error.
    """
    out = {}
    one_step = np.asarray(evalset.horizon) == 1
    for row in rows:
        p_hat = row.slots[max(row.slots)]["p_hat"]
        mass = np.asarray(metrics.route_offset_mass(p_hat, evalset.slot_now, evalset.num_slots))
        entry = {"route_offsets_one_step": {
                     "labels": list(ROUTE_LABELS), "count": int(one_step.sum()),
                     "mean": [_json_number(float(v)) for v in
                              (mass[one_step].mean(axis=0) if one_step.any()
                               else np.full(len(ROUTE_LABELS), np.nan))]},
                 "kl": _breakdown(row.kl, evalset, config),
                 "kl_mc_stderr": _json_number(float(np.mean(row.kl_stderr))),
                 "slots": {str(n): {m: _breakdown(s[m], evalset, config) for m in SLOT_METRICS}
                           for n, s in row.slots.items()},
                 "info": row.info}
        out[row.name] = entry
    return out


# --------------------------------------------------------------------------- report


def _fmt(stat: dict | None, digits: int = 3) -> str:
    if stat is None or stat["mean"] is None:
        return "–"
    if stat["stderr"] is None:
        return f"{stat['mean']:.{digits}f}"
    return f"{stat['mean']:.{digits}f} ± {stat['stderr']:.{digits}f}"


def markdown_table(results: dict) -> str:
    """The results as Markdown: the main table, then KL and TV by category and by horizon."""
    rows = results["rows"]
    counts = results["protocol"]["samples"]
    lines = ["# Evaluation against the exact posterior\n",
             _protocol_line(results["protocol"]) + "\n",
             "## Overall (mean ± standard error over queries)\n"]
    header = ["row", "KL(q‖p) [nats]"]
    for n in counts:
        header += [f"TV @{n}", f"top-1 @{n}", f"search cost ratio @{n}"]
    lines.append("| " + " | ".join(header) + " |")
    lines.append("|" + "---|" * len(header))
    for name, row in rows.items():
        cells = [name, _fmt(row["kl"]["overall"], 2)]
        for n in counts:
            slot = row["slots"][str(n)]
            cells += [_fmt(slot[m]["overall"]) for m in SLOT_METRICS]
        lines.append("| " + " | ".join(cells) + " |")
    n_big = str(counts[-1])
    first = next(iter(rows.values())).get("route_offsets_one_step")
    if first is not None:
        lines.append(f"\n## Routines: slot mass at route offsets one step ahead (Δτ = 1, "
                     f"{first['count']} queries, @{n_big})\n")
        lines.append("| row | " + " | ".join(f"offset {k}" if k[0] in "0+" else k
                                              for k in first["labels"]) + " |")
        lines.append("|---|" + "---|" * len(first["labels"]))
        for name, row in rows.items():
            cells = ["–" if v is None else f"{v:.3f}"
                     for v in row["route_offsets_one_step"]["mean"]]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    for group, title in (("by_category", "category"), ("by_horizon", "horizon Δτ")):
        keys = list(next(iter(rows.values()))["kl"][group])
        for metric, label in (("kl", "KL(q‖p)"), ("tv", f"slot TV @{n_big}"),
                              ("search_cost_ratio", f"search cost ratio @{n_big}")):
            lines.append(f"\n## {label} by {title}\n")
            lines.append("| row | " + " | ".join(keys) + " |")
            lines.append("|---|" + "---|" * len(keys))
            for name, row in rows.items():
                table = row["kl"] if metric == "kl" else row["slots"][n_big][metric]
                digits = 2 if metric == "kl" else 3
                lines.append(f"| {name} | "
                             + " | ".join(_fmt(table[group].get(k), digits) for k in keys) + " |")
    if results.get("figures"):
        lines.append("\n## Figures\n")
        lines += [f"![{f}]({f})" for f in results["figures"]]
    return "\n".join(lines) + "\n"


def _protocol_line(p: dict) -> str:
    return (f"{p['num_envs']} validation environments × {p['objects_per_env']} objects = "
            f"{p['num_queries']} queries; τ ~ U{{0..T−2}}, τ_q ~ U{{τ+1..T−1}}; KL from "
            f"{p['kl_draws']} draws of q per query; slot metrics from "
            f"{', '.join(str(n) for n in p['samples'])} samples; ODE: {p['method']} on "
            f"{p['num_steps']} grid points (likelihood: {p['logp_steps']}); seed {p['seed']}.")


def write_report(results: dict, out_dir: str | pathlib.Path) -> dict[str, pathlib.Path]:
    """Write ``results.json`` and ``results.md`` into out_dir (created); returns their paths."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / "results.json", "markdown": out / "results.md"}
    paths["json"].write_text(json.dumps(results, indent=2, allow_nan=False) + "\n")
    paths["markdown"].write_text(markdown_table(results))
    return paths


# --------------------------------------------------------------------------- figures


def plot_kl(results: dict, rows: Sequence[str] | None = None) -> Figure:
    """Paper Fig. 2: KL(q‖p) of the model rows (FlowMaps vs the MLP baselines), overall, by
    category and by horizon, with standard-error bars. rows: which rows (default: all models)."""
    table = results["rows"]
    if rows is None:
        rows = [n for n in table if n not in REFERENCE_ROWS] or list(table)
    fig = Figure(figsize=(13, 3.8), layout="constrained")
    ax_all, ax_cat, ax_h = fig.subplots(1, 3, gridspec_kw={"width_ratios": [1, 2, 3]})
    width = 0.8 / len(rows)
    colours = [f"C{i}" for i in range(len(rows))]
    for i, name in enumerate(rows):
        kl = table[name]["kl"]
        o = kl["overall"]
        ax_all.bar(i, o["mean"], yerr=o["stderr"] or 0.0, color=colours[i], capsize=3,
                   label=name)
        cats = list(kl["by_category"])
        means = [kl["by_category"][c]["mean"] for c in cats]
        errs = [kl["by_category"][c]["stderr"] or 0.0 for c in cats]
        xs = np.arange(len(cats)) + (i - (len(rows) - 1) / 2) * width
        ax_cat.bar(xs, means, width, yerr=errs, color=colours[i], capsize=2, label=name)
        ax_cat.set_xticks(np.arange(len(cats)), cats)
        hs = list(kl["by_horizon"])
        mean_h = np.array([kl["by_horizon"][h]["mean"] for h in hs], float)
        err_h = np.array([kl["by_horizon"][h]["stderr"] or 0.0 for h in hs], float)
        x_h = np.array([int(h) for h in hs])
        ax_h.plot(x_h, mean_h, "o-", color=colours[i], label=name, markersize=3)
        ax_h.fill_between(x_h, mean_h - err_h, mean_h + err_h, color=colours[i], alpha=0.2)
    ax_all.set_xticks(range(len(rows)), rows, rotation=15)
    ax_all.set_title("overall")
    ax_cat.set_title("by category")
    ax_h.set_title("by horizon Δτ")
    ax_h.set_xlabel("Δτ = τ_q − τ")
    for ax in (ax_all, ax_cat, ax_h):
        ax.set_ylabel("KL(q‖p) [nats]")
        ax.axhline(0.0, color="0.5", linewidth=0.8)
        ax.grid(axis="y", alpha=0.3)
    ax_h.legend(fontsize=8)
    fig.suptitle("KL(q‖p) against the exact posterior (lower is better; mean ± s.e.)")
    return fig


def plot_by_horizon(results: dict, rows: Sequence[str] | None = None) -> Figure:
    """KL(q‖p), slot TV and search-cost ratio (largest sample count) against the horizon Δτ, for
    the model rows and the "oracle samples" and "uniform" reference rows (mean ± s.e.)."""
    table = results["rows"]
    n_big = str(results["protocol"]["samples"][-1])
    if rows is None:
        rows = [n for n in ("oracle samples", "uniform") if n in table]
        rows += [n for n in table if n not in REFERENCE_ROWS]
    fig = Figure(figsize=(13, 3.8), layout="constrained")
    axes = fig.subplots(1, 3)
    panels = (("KL(q‖p) [nats]", lambda r: r["kl"]),
              (f"slot TV @{n_big}", lambda r: r["slots"][n_big]["tv"]),
              (f"search cost ratio @{n_big}", lambda r: r["slots"][n_big]["search_cost_ratio"]))
    for ax, (label, pick) in zip(axes, panels, strict=True):
        for i, name in enumerate(rows):
            by_h = pick(table[name])["by_horizon"]
            hs = list(by_h)
            mean = np.array([np.nan if by_h[h]["mean"] is None else by_h[h]["mean"] for h in hs])
            err = np.array([by_h[h]["stderr"] or 0.0 for h in hs], float)
            x = np.array([int(h) for h in hs])
            style = "--" if name in REFERENCE_ROWS else "-"
            ax.plot(x, mean, style, marker="o", markersize=3, color=f"C{i}", label=name)
            ax.fill_between(x, mean - err, mean + err, color=f"C{i}", alpha=0.15)
        ax.set(xlabel="Δτ = τ_q − τ", ylabel=label, title=label + " by horizon")
        ax.grid(alpha=0.3)
    axes[0].set_yscale("symlog", linthresh=1.0)
    axes[-1].legend(fontsize=8)
    fig.suptitle("By horizon: short horizons have sharp posteriors (dashed: reference rows)")
    return fig


def pick_queries(evalset: EvalSet, config: FlowSimConfig,
                 categories: Sequence[str] = ("fork", "remote", "bottle"),
                 horizons: tuple[int, int] = (2, 4)) -> list[tuple[int, int]]:
    """One (environment row, object) per category for the figures: among queries with
    Δτ in ``horizons`` (inclusive; a few steps ahead, so q is multimodal but not yet uniform),
    the one whose exact posterior has the most entropy; any horizon if none qualifies.
    Categories missing from the config are skipped."""
    names = [c.name for c in config.categories]
    q = np.asarray(evalset.slot_probs, np.float64)
    entropy = -np.sum(np.where(q > 0, q * np.log(np.where(q > 0, q, 1.0)), 0.0), axis=-1)
    horizon = np.asarray(evalset.horizon)
    in_range = (horizon >= horizons[0]) & (horizon <= horizons[1])
    picks = []
    for cat in categories:
        if cat not in names:
            continue
        m = names.index(cat)
        score = np.where(in_range[:, m], entropy[:, m], -np.inf)
        if not np.isfinite(score).any():
            score = entropy[:, m]
        picks.append((int(np.argmax(score)), m))
    return picks


def plot_samples(scenes, evalset: EvalSet, rows: Sequence[RowResult], config: FlowSimConfig,
                 picks: Sequence[tuple[int, int]] | None = None, num_shown: int = 25) -> Figure:
    """Paper Fig. 3: for each picked query (default: fork, remote, bottle), the map at τ with the
    exact posterior over the object's places shaded and labelled (its modes), and ``num_shown``
    samples of each model row overlaid (one row of panels per model)."""
    from flowmaps_jax.flowsim.render import draw_posterior, overlay_boxes

    rows = [r for r in rows if r.samples is not None]
    if not rows:
        raise ValueError("rows must include at least one model row with samples")
    picks = list(pick_queries(evalset, config) if picks is None else picks)
    if not picks:
        raise ValueError("picks is empty: no query to draw")
    fig = Figure(figsize=(4.3 * len(picks), 4.3 * len(rows)), layout="constrained")
    axes = fig.subplots(len(rows), len(picks), squeeze=False)
    for r, row in enumerate(rows):
        for c, (e, m) in enumerate(picks):
            ax = axes[r, c]
            env, tau = int(evalset.env[e]), int(evalset.tau[e])
            draw_posterior(scenes, env, m, tau, np.asarray(evalset.slot_probs[e, m]), config,
                           ax=ax)
            colour = config.categories[m].colour
            overlay_boxes(ax, row.samples[e, m, :num_shown], config, edgecolor=colour,
                          linewidth=1.2, alpha=0.9)
            ax.set_title(f"{row.name}: {config.categories[m].name}, τ = {tau} → "
                         f"τ_q = {int(evalset.tau_q[e])}", fontsize=9)
    fig.suptitle(f"{num_shown} samples per query (outlines) over the exact posterior "
                 "(shaded places, labelled with q)", fontsize=10)
    return fig


def plot_slot_bars(evalset: EvalSet, rows: Sequence[RowResult], config: FlowSimConfig,
                   picks: Sequence[tuple[int, int]] | None = None,
                   num_samples: int | None = None) -> Figure:
    """Learned slot distributions p̂ (from num_samples samples, default the largest count) next to
    the exact q, one panel per picked query; slots in visiting order, then "off"."""
    rows = [r for r in rows if r.samples is not None] or list(rows)
    picks = list(pick_queries(evalset, config) if picks is None else picks)
    if not picks:
        raise ValueError("picks is empty: no query to draw")
    fig = Figure(figsize=(4.2 * len(picks), 3.4), layout="constrained")
    axes = fig.subplots(1, len(picks), squeeze=False)[0]
    series = len(rows) + 1
    width = 0.8 / series
    for ax, (e, m) in zip(axes, picks, strict=True):
        k = int(evalset.num_slots[e, m])
        x = np.arange(k + 1)
        q = np.append(np.asarray(evalset.slot_probs[e, m, :k]), 0.0)
        ax.bar(x - 0.4 + width / 2, q, width, color="0.3", label="exact q")
        for i, row in enumerate(rows):
            n = max(row.slots) if num_samples is None else num_samples
            p = np.asarray(row.slots[n]["p_hat"][e, m])
            p = np.append(p[:k], p[-1])
            ax.bar(x - 0.4 + width * (i + 1.5), p, width, color=f"C{i}",
                   label=f"{row.name} (n={n})")
        ax.set_xticks(x, [str(i + 1) for i in range(k)] + ["off"])
        ax.set_xlabel("place along the visiting order")
        ax.set_title(f"{config.categories[m].name}, Δτ = {int(evalset.horizon[e, m])}",
                     fontsize=10)
        ax.set_ylim(0, 1)
    axes[0].set_ylabel("probability")
    axes[-1].legend(fontsize=7)
    fig.suptitle("learned slot distribution vs the exact posterior", fontsize=10)
    return fig


# --------------------------------------------------------------------------- the whole run


def run_evaluation(predictors: Sequence[Predictor], scenes, config: FlowSimConfig,
                   out_dir: str | pathlib.Path | None = None, *, seed: int = 0,
                   sample_counts: Sequence[int] = DEFAULT_SAMPLES,
                   kl_draws: int = DEFAULT_KL_DRAWS, chunk_envs: int = DEFAULT_CHUNK_ENVS,
                   num_steps: int = DEFAULT_NUM_STEPS, method: str = "midpoint",
                   logp_steps: int | None = None, figures: bool = True,
                   progress: bool = True) -> tuple[dict, list[RowResult], EvalSet]:
    """Evaluate ``predictors`` (baselines first, FlowMaps last, as they should appear) on every
    environment of ``scenes``; write the report and figures into out_dir if given.

    Returns (results dict as written to results.json, the RowResults, the EvalSet).
    """
    counts = _check_counts(sample_counts)
    if not predictors:
        raise ValueError("predictors must hold at least one Predictor")
    num_steps, method, logp_steps = _check_ode(num_steps, method, logp_steps)
    for p in predictors:
        if not isinstance(p, Predictor):
            raise ValueError(f"predictors must be Predictor objects; got {type(p).__name__}")
        if p.flowsim.map_size != config.map_size or p.flowsim.categories != config.categories:
            raise ValueError(f"predictor {p.name} ({p.source}) was trained on a different FlowSim "
                             "config (map size or categories) than the evaluation scenes")
    start = time.perf_counter()
    key = jax.random.PRNGKey(seed)
    evalset = build_eval_queries(scenes, config, key, kl_draws)
    rows = reference_rows(evalset, counts, key)
    names = _unique_names([p.name for p in predictors])
    for predictor, name in zip(predictors, names, strict=True):
        rows.append(evaluate_predictor(predictor, evalset, key, counts, chunk_envs, num_steps,
                                       method, logp_steps, progress, name=name))
    results = {
        "protocol": {"num_envs": evalset.num_envs, "objects_per_env": config.num_objects,
                     "num_queries": evalset.num_queries, "samples": list(counts),
                     "kl_draws": kl_draws, "num_steps": num_steps, "method": method,
                     "logp_steps": logp_steps,
                     "seed": seed, "assign_radius": metrics.ASSIGN_RADIUS,
                     "dynamics": config.dynamics},
        "rows": summarise_rows(rows, evalset, config),
        "figures": [],
    }
    if out_dir is not None:
        out = pathlib.Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        if figures:
            model_rows = [r for r in rows if r.samples is not None]
            plots = {"kl.png": lambda: plot_kl(results),
                     "by_horizon.png": lambda: plot_by_horizon(results),
                     "samples.png": lambda: plot_samples(scenes, evalset, model_rows, config),
                     "slots.png": lambda: plot_slot_bars(evalset, model_rows, config)}
            for filename, make in plots.items():
                make().savefig(out / filename, dpi=110)
                results["figures"].append(filename)
        results["seconds"] = round(time.perf_counter() - start, 1)
        write_report(results, out)
    else:
        results["seconds"] = round(time.perf_counter() - start, 1)
    return results, rows, evalset


def _unique_names(names: Sequence[str]) -> list[str]:
    seen: dict[str, int] = {}
    out = []
    for n in names:
        seen[n] = seen.get(n, 0) + 1
        out.append(n if seen[n] == 1 else f"{n} #{seen[n]}")
    return out


# --------------------------------------------------------------------------- CLI


def _parse_counts(text: str) -> tuple[int, ...]:
    try:
        counts = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--samples must be comma-separated integers like 25,100; got {text!r}") from None
    if not counts or any(n < 1 for n in counts):
        raise argparse.ArgumentTypeError(f"--samples must be positive integers; got {text!r}")
    return counts


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m flowmaps_jax.evaluate",
        description="Evaluate FlowMaps (and baselines) against FlowSim's exact posterior.")
    parser.add_argument("--checkpoint", required=True,
                        help="run or checkpoint directory of the model to evaluate (FlowMaps), "
                             "or pretrained:NAME for a shipped model (e.g. pretrained:flowmaps)")
    parser.add_argument("--baseline", action="extend", nargs="+", default=[], metavar="DIR",
                        help="run or checkpoint directories (or pretrained:NAME) of baselines "
                             "(several after one flag, or the flag repeated)")
    parser.add_argument("--out", default=None,
                        help="output directory (default: <checkpoint>/eval)")
    parser.add_argument("--num-envs", type=int, default=DEFAULT_NUM_ENVS,
                        help="validation environments (3 queries each)")
    parser.add_argument("--samples", type=_parse_counts, default=DEFAULT_SAMPLES,
                        help="sample counts for the slot metrics, e.g. 25,100")
    parser.add_argument("--kl-draws", type=int, default=DEFAULT_KL_DRAWS,
                        help="draws from q per query for the KL estimate")
    parser.add_argument("--seed", type=int, default=0, help="seed of times, draws and samples")
    parser.add_argument("--which", choices=("best", "latest"), default="best",
                        help="which checkpoint to load")
    parser.add_argument("--num-steps", type=int, default=DEFAULT_NUM_STEPS,
                        help="ODE grid points for sampling (10 = 18 midpoint evaluations)")
    parser.add_argument("--logp-steps", type=int, default=None,
                        help="ODE grid points for the likelihood (default: --num-steps)")
    parser.add_argument("--method", choices=SOLVERS, default="midpoint", help="ODE solver")
    parser.add_argument("--chunk-envs", type=int, default=DEFAULT_CHUNK_ENVS,
                        help="environments per compiled batch")
    parser.add_argument("--scenes", default=None,
                        help="evaluate on scenes from an .npz (flowsim.scenes.save_scenes) instead "
                             "of the validation split")
    parser.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


PRETRAINED_PREFIX = "pretrained:"


def _load_model(spec: str, which: str) -> Predictor:
    """A checkpoint directory, or ``pretrained:NAME`` for a model shipped with the package."""
    if spec.startswith(PRETRAINED_PREFIX):
        from flowmaps_jax.sample import load_pretrained

        return load_pretrained(spec[len(PRETRAINED_PREFIX):])
    return load(spec, which=which)


def main(argv: Sequence[str] | None = None) -> int:
    """CLI entry point; returns the exit code (0 on success, 2 on a bad argument)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        check_int("--num-envs", args.num_envs, 1)
        check_int("--kl-draws", args.kl_draws, 2)
        check_int("--num-steps", args.num_steps, 2)
        check_int("--chunk-envs", args.chunk_envs, 1)
        if args.logp_steps is not None:
            check_int("--logp-steps", args.logp_steps, 2)
        model = _load_model(args.checkpoint, args.which)
        baselines = [_load_model(path, args.which) for path in args.baseline]
        config = model.flowsim
        if args.scenes is not None:
            from flowmaps_jax.flowsim.scenes import load_scenes

            scenes, config = load_scenes(args.scenes)
            if args.num_envs < scenes.num_envs:
                scenes = jax.tree_util.tree_map(lambda a: a[: args.num_envs], scenes)
        else:
            from flowmaps_jax.flowsim.scenes import validation_split

            scenes = validation_split(config, num_envs=args.num_envs)
        if args.out:
            out = pathlib.Path(args.out)
        elif args.checkpoint.startswith(PRETRAINED_PREFIX):
            raise ValueError("--out is required when --checkpoint is a pretrained model")
        else:
            out = pathlib.Path(args.checkpoint) / "eval"
        print(f"Evaluating {model.name} ({model.source}, step {model.step})"
              + "".join(f" vs {b.name} ({b.source}, step {b.step})" for b in baselines)
              + f" on {scenes.num_envs} environments → {out}", flush=True)
        results, _, _ = run_evaluation(
            [*baselines, model], scenes, config, out, seed=args.seed, sample_counts=args.samples,
            kl_draws=args.kl_draws, chunk_envs=args.chunk_envs, num_steps=args.num_steps,
            method=args.method, logp_steps=args.logp_steps, figures=not args.no_figures,
            progress=not args.no_progress)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(markdown_table(results).split("\n## KL")[0])
    print(f"wrote {out / 'results.json'}, {out / 'results.md'}"
          + "".join(f", {out / f}" for f in results["figures"])
          + f" in {results['seconds']:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
