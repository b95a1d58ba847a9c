"""The results: per-query rows summarised into ``results.json`` and ``results.md``, overall, by
category and by horizon Δτ (mean ± standard error; ``null``, never NaN, for a group of one), and
by habit when the eval set has one.
"""

from __future__ import annotations

import json
import math
import pathlib
from collections.abc import Hashable, Sequence

import jax.numpy as jnp
import numpy as np

from flowmaps_jax.atomic_files import make_output_dir, write_file
from flowmaps_jax.evaluation.protocol import EvalSet, RowResult
from flowmaps_jax.evaluation.slots import (
    ROUTE_OFFSET_LABELS,
    SLOT_METRICS,
    offset_mass,
)
from flowmaps_jax.flowsim.config import HABITS, FlowSimConfig

# --------------------------------------------------------------------------- aggregation


def _stats(values: np.ndarray) -> dict:
    n = values.size
    stderr = float(values.std(ddof=1) / math.sqrt(n)) if n > 1 else float("nan")
    return {"mean": float(values.mean()), "stderr": stderr, "count": int(n)}


def summarise(values, groups=None) -> dict:
    """``{"overall": {"mean", "stderr", "count"}, "by_group": {id: {...}}}`` of per-query
    ``values`` (``by_group`` only with ``groups``, ids of the same shape, sorted); stderr is NaN
    for a group of one."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        raise ValueError("values is empty")
    out: dict = {"overall": _stats(v.ravel())}
    if groups is None:
        return out
    g = np.asarray(groups)
    if g.shape != v.shape:
        raise ValueError(f"groups must have the shape of values {v.shape}; got {g.shape}")
    by_group: dict[Hashable, dict] = {}
    for gid in np.unique(g):
        by_group[gid.item()] = _stats(v[g == gid])
    out["by_group"] = by_group
    return out


def _json_number(x: float) -> float | None:
    return None if not math.isfinite(x) else float(x)


def _clean(summary: dict) -> dict:
    """A :func:`summarise` entry → JSON-safe {mean, stderr, count} (NaN → None)."""
    return {"mean": _json_number(summary["mean"]), "stderr": _json_number(summary["stderr"]),
            "count": int(summary["count"])}


def _breakdown(values: np.ndarray, evalset: EvalSet, config: FlowSimConfig) -> dict:
    """{"overall", "by_category", "by_horizon"} of per-query values (E, M)."""
    names = np.asarray([c.name for c in config.categories])[np.asarray(evalset.obj)]
    overall = summarise(values)["overall"]
    by_cat = summarise(values, names)["by_group"]
    by_h = summarise(values, np.asarray(evalset.horizon))["by_group"]
    cat_order = [c.name for c in config.categories if c.name in by_cat]
    return {"overall": _clean(overall),
            "by_category": {k: _clean(by_cat[k]) for k in cat_order},
            "by_horizon": {str(k): _clean(v) for k, v in sorted(by_h.items())}}


def summarise_rows(rows: Sequence[RowResult], evalset: EvalSet, config: FlowSimConfig) -> dict:
    """{row name: {"kl": breakdown, "slots": {n: {metric: breakdown}}, "info": {...}}}.

    A breakdown is {"overall": {mean, stderr, count}, "by_category": {name: ...},
    "by_horizon": {Δτ: ...}}; "info" holds "kl_mc_stderr", "kl_integration_error",
    "kl_paper_grid" and "route_offsets_one_step".
    """
    out = {}
    one_step = np.asarray(evalset.horizon) == 1
    for row in rows:
        p_hat = row.slots[max(row.slots)]["p_hat"]
        mass = np.asarray(offset_mass(jnp.asarray(p_hat, jnp.float32),
                                      jnp.asarray(evalset.slot_now, jnp.int32),
                                      jnp.asarray(evalset.num_slots, jnp.int32)))
        entry = {"route_offsets_one_step": {
                     "labels": list(ROUTE_OFFSET_LABELS), "count": int(one_step.sum()),
                     "mean": [_json_number(float(v)) for v in
                              (mass[one_step].mean(axis=0) if one_step.any()
                               else np.full(len(ROUTE_OFFSET_LABELS), np.nan))]},
                 "kl": _breakdown(row.kl, evalset, config),
                 "kl_mc_stderr": _json_number(float(np.mean(row.kl_stderr))),
                 "kl_integration_error": (None if row.kl_error is None
                                          else _json_number(float(row.kl_error))),
                 "kl_paper_grid": (None if row.kl_paper is None
                                   else _breakdown(row.kl_paper, evalset, config)),
                 "slots": {str(n): {m: _breakdown(s[m], evalset, config) for m in SLOT_METRICS}
                           for n, s in row.slots.items()},
                 "info": row.info}
        out[row.name] = entry
    return out


def summarise_habits(rows: Sequence[RowResult], evalset: EvalSet) -> dict:
    """``{habit: {"count": queries, "rows": {row name: {"kl": stat, "slots": {n: {"tv", "top1",
    "search_cost_ratio", "off": stat}}}}}}`` over the habits present in ``evalset``, in
    ``flowsim.HABITS`` order; stat {mean, stderr, count}.
    """
    if evalset.habit is None:
        raise ValueError("evalset has no habits (it was built without a history)")
    habit = np.asarray(evalset.habit)
    out = {}
    for fam in np.unique(habit):
        sel = habit == fam

        def stat(values, sel=sel):
            return _clean(summarise(np.asarray(values)[sel])["overall"])

        out[HABITS[int(fam)]] = {"count": int(sel.sum()), "rows": {
            row.name: {"kl": stat(row.kl),
                       "slots": {str(n): {**{m: stat(s[m]) for m in SLOT_METRICS},
                                          "off": stat(s["p_hat"][..., -1])}
                                 for n, s in row.slots.items()}}
            for row in rows}}
    return out


# --------------------------------------------------------------------------- Markdown and files


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
    header = ["row", "KL(q‖p) [nats]", "integration error", "KL, paper grid"]
    for n in counts:
        header += [f"TV @{n}", f"top-1 @{n}", f"rank cost @{n}"]
    lines.append("| " + " | ".join(header) + " |")
    lines.append("|" + "---|" * len(header))
    for name, row in rows.items():
        err = row.get("kl_integration_error")
        paper = row.get("kl_paper_grid")
        cells = [name, _fmt(row["kl"]["overall"], 2), "–" if err is None else f"{err:.3f}",
                 "–" if paper is None else _fmt(paper["overall"], 2)]
        for n in counts:
            slot = row["slots"][str(n)]
            cells += [_fmt(slot[m]["overall"]) for m in SLOT_METRICS]
        lines.append("| " + " | ".join(cells) + " |")
    n_big = str(counts[-1])
    first = next(iter(rows.values())).get("route_offsets_one_step")
    if first is not None and "routine" in results.get("by_habit", {"routine": None}):
        lines.append(f"\n## Routines: slot mass at route offsets one step ahead (Δτ = 1, "
                     f"{first['count']} queries, @{n_big})\n")
        lines.append("| row | " + " | ".join(f"offset {k}" if k[0] in "0+" else k
                                              for k in first["labels"]) + " |")
        lines.append("|---|" + "---|" * len(first["labels"]))
        for name, row in rows.items():
            cells = ["–" if v is None else f"{v:.3f}"
                     for v in row["route_offsets_one_step"]["mean"]]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    for habit, part in results.get("by_habit", {}).items():
        lines.append(f"\n## Habit: {habit} ({part['count']} queries, @{n_big})\n")
        lines.append("| row | KL(q‖p) [nats] | TV | top-1 | rank cost | off-table mass |")
        lines.append("|---|---|---|---|---|---|")
        for name, row in part["rows"].items():
            slot = row["slots"][n_big]
            lines.append(f"| {name} | {_fmt(row['kl'], 2)} | "
                         + " | ".join(_fmt(slot[m]) for m in (*SLOT_METRICS, "off")) + " |")
    for group, title in (("by_category", "category"), ("by_horizon", "horizon Δτ")):
        keys = list(next(iter(rows.values()))["kl"][group])
        for metric, label in (("kl", "KL(q‖p)"), ("tv", f"slot TV @{n_big}"),
                              ("search_cost_ratio", f"rank cost @{n_big}")):
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
            f"{p['num_steps']} grid points (paper likelihood grid: {p['logp_steps']}; accurate "
            f"likelihood: {p.get('likelihood_steps') or 'off'} points, RK4 on the stiff grid, on "
            f"the first {p.get('likelihood_draws')} draws per query; its integration error "
            f"against twice the intervals on the first {p.get('integration_error_envs')} "
            "environments); "
            f"slot assignment {p.get('assignment', 'v1')}; seed {p['seed']}. Rank cost: Σ_k "
            "rank_k q_k visiting slots by decreasing p̂, over the same by decreasing q "
            "(docs/protocol.md)." + _history_sentence(p))


def _history_sentence(p: dict) -> str:
    """The world and history of an eval set with a history ("" for the paper's protocol)."""
    if "history" not in p:
        return ""
    habits = ", ".join(f"{name} {weight:.2f}" for name, weight in p["habits"])
    return (f" World: {p['world']} (habits {habits}); q is the exact posterior given the last "
            f"min(H, τ + 1) observations of the object, H = {p['history']}, its habit "
            "marginalised; each model reads the maps it was trained on (its H).")


def write_report(results: dict, out_dir: str | pathlib.Path) -> dict[str, pathlib.Path]:
    """Write ``results.json`` and ``results.md`` into out_dir (created); returns their paths."""
    out = make_output_dir("out_dir", out_dir, files=("results.json", "results.md"))
    paths = {"json": out / "results.json", "markdown": out / "results.md"}
    text = json.dumps(results, indent=2, allow_nan=False) + "\n"  # refused before any write
    write_file(paths["json"], text, name="out_dir file")
    write_file(paths["markdown"], markdown_table(results), name="out_dir file")
    return paths
