"""The homes evaluation's ``results.md``, ``results.json`` and figures (from
:func:`flowmaps_jax.evaluation.receptacle_protocol.run_evaluation`'s results)."""

from __future__ import annotations

import json
import pathlib

from flowmaps_jax.atomic_files import save_figure, write_file
from flowmaps_jax.evaluation.receptacle_scores import best_lines
from flowmaps_jax.flowsim.homes import REGIMES

METRIC_NAMES = {"kl": "KL (nats)", "tv": "TV", "top1": "top-1", "rank_cost": "rank cost"}
NAV_COLUMNS = ("sr@1", "sr@5", "sr@10", "msr", "spl@1", "mspl", "steps")
NAV_NAMES = {"sr@1": "SR@1", "sr@5": "SR@5", "sr@10": "SR@10", "msr": "mSR",
             "spl@1": "SPL@1", "mspl": "mSPL", "steps": "steps"}


def _pm(stat: dict | None, digits: int = 3, scale: float = 1.0) -> str:
    if not stat or stat.get("mean") is None:
        return "—"
    mean = stat["mean"] * scale
    mean = 0.0 if abs(mean) < 0.5 * 10 ** -digits else mean  # no "-0.000"
    if stat.get("stderr") is None:
        return f"{mean:.{digits}f}"
    return f"{mean:.{digits}f} ± {stat['stderr'] * scale:.{digits}f}"


def _part(summary: dict, part: str, key: str | None):
    return summary["overall"] if part == "overall" else summary[part].get(key)


def posterior_table(results: dict, part: str = "overall", key: str | None = None) -> str:
    """row | KL | TV | top-1 | rank cost (mean ± standard error) on one part of the queries."""
    lines = ["| row | " + " | ".join(METRIC_NAMES.values()) + " |",
             "|---|" + "---|" * len(METRIC_NAMES)]
    for name, row in results["posterior"].items():
        cells = [_pm(_part(row["metrics"][m], part, key)) if m in row["metrics"] else "—"
                 for m in METRIC_NAMES]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def horizon_table(results: dict, metric: str) -> str:
    """row | one column per horizon: ``metric``'s mean over that horizon's queries."""
    horizons = [str(h) for h in results["protocol"]["horizons"]]
    lines = ["| row | " + " | ".join(f"Δτ = {h} h" for h in horizons) + " |",
             "|---|" + "---|" * len(horizons)]
    for name, row in results["posterior"].items():
        if metric not in row["metrics"]:
            continue
        by = row["metrics"][metric]["by_horizon"]
        lines.append(f"| {name} | " + " | ".join(_pm(by.get(h), 3) for h in horizons) + " |")
    return "\n".join(lines)


def navigation_table(results: dict, part: str = "overall", key: str | None = None) -> str:
    """The 2026 paper's layout: row | SR@1 | SR@5 | SR@10 | mSR | SPL@1 | mSPL | steps |
    E[travel] ÷ exact (SR and SPL in %)."""
    lines = ["| row | " + " | ".join(NAV_NAMES[c] for c in NAV_COLUMNS) + " | E[travel] ÷ exact |",
             "|---|" + "---|" * (len(NAV_COLUMNS) + 1)]
    for name, row in results["navigation"].items():
        cells = []
        for c in NAV_COLUMNS:
            stat = _part(row["metrics"][c], part, key)
            cells.append(_pm(stat, 1) if c == "steps" else _pm(stat, 2, 100.0))
        ratio = _part(row["travel_ratio"], part, key)
        cells.append("—" if ratio is None else f"{ratio:.3f}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def markdown(results: dict) -> str:
    """The whole report of the parts ``results`` holds (``posterior``, ``navigation``)."""
    p = results["protocol"]
    parts = [part for part in ("posterior", "navigation") if part in results]
    regimes = [r for r in REGIMES if p["queries_by_regime"].get(r)]
    counts = ", ".join(f"{r} {p['queries_by_regime'][r]}" for r in regimes)
    out = [
        f"# FlowSim homes: {' and '.join(parts)}", "",
        f"`{results.get('command', 'python -m flowmaps_jax.evaluate')}`", "",
        f"{p['homes']} evaluation homes (seed {p['eval_seed']}) × {p['queries_per_home']} "
        f"queries, regime {p['regime']} (queries: {counts}); horizons "
        f"{', '.join(map(str, p['horizons']))} h; the exact posterior reads the last "
        f"{p['history']} hours; {p['samples']} samples per sample row; seed {p['seed']}"
        + (f"; FlowMaps: {p['model']}" if p.get("model") else "") + ". Mean ± standard "
        f"error over queries. {results['seconds']:.0f} s.", ""]
    fit = p.get("count_table")
    if fit:
        out += [f"Count rows chosen on {fit['fitted_on']}: bandwidth b = {fit['bandwidth']:g} h, "
                f"back-off α = {fit['alpha']:g}, other-day-type factor {fit['day_factor']:.2g}, "
                f"hourly stay s₁ = {fit['stay']:g}.", ""]
    best = results.get("best_reference", {})
    if "posterior" in results:
        out += ["## Posterior", "",
                "KL(q ‖ p) in nats, TV, top-1 and rank cost against the exact posterior q "
                "(docs/protocol.md's definitions on the object's allowed receptacles; sample "
                "rows have no KL).", "", "### All regimes", "", posterior_table(results), ""]
        if best.get("posterior"):
            out += best_lines(best["posterior"], "### Best reference row per regime (by KL; "
                              "the exact rows and the model excluded)", "kl")
        for r in regimes:
            out += [f"### {r}", "", posterior_table(results, "by_regime", r), ""]
        out += ["## By horizon", "", "### Rank cost", "",
                horizon_table(results, "rank_cost"), "", "### KL (nats)", "",
                horizon_table(results, "kl"), ""]
    if "navigation" not in results:
        return "\n".join(out)
    out += ["## Navigation", "",
            f"Start: the centre of room 0; geodesic travel through doors; a perfect detector; "
            f"SR@k: found within k looks; mSR: mean SR@k over k = 1 … {p['budget']}; SPL@1 and "
            f"mSPL (within {p['budget']} looks) in %; steps: metres walked / "
            f"{p['step_length_m']} m; E[travel] ÷ exact: expected walk under the exact "
            "posterior over the Bayes-optimal searcher's (ratio of means). Rows: prior, policy "
            "(optimal: least expected travel under that prior, by exact dynamic programming; "
            "most-probable: decreasing prior, ties to the nearest).", "",
            "### All regimes", "", navigation_table(results), ""]
    if best.get("navigation"):
        out += best_lines(best["navigation"], "### Best reference row per regime (by SR@1; the "
                          "exact rows and the model excluded)", "sr@1")
    for r in regimes:
        out += [f"### {r}", "", navigation_table(results, "by_regime", r), ""]
    return "\n".join(out)


def write_report(results: dict, out: pathlib.Path, stem: str = "results"
                 ) -> list[pathlib.Path]:
    """``<stem>.json`` and ``<stem>.md`` into ``out``."""
    out = pathlib.Path(out)
    return [write_file(out / f"{stem}.json", json.dumps(results, indent=1, ensure_ascii=False),
                       name="--out file"),
            write_file(out / f"{stem}.md", markdown(results), name="--out file")]


def write_figures(results: dict, out: pathlib.Path) -> list[str]:
    """``success_vs_looks.png`` (SR@k per navigation row) and ``rank_cost_by_horizon.png``
    (rank cost per posterior row), of the parts ``results`` holds; returns their names."""
    from matplotlib.figure import Figure

    out, written = pathlib.Path(out), []
    if "navigation" in results:
        _success_figure(results, out, Figure)
        written.append("success_vs_looks.png")
    if "posterior" in results:
        _rank_cost_figure(results, out, Figure)
        written.append("rank_cost_by_horizon.png")
    return written


def _success_figure(results: dict, out: pathlib.Path, Figure) -> None:
    fig = Figure(figsize=(7, 4.5))
    ax = fig.subplots()
    for name, row in results["navigation"].items():
        k = range(1, len(row["success_at"]) + 1)
        ax.plot(k, [100 * s for s in row["success_at"]], marker="o", ms=3, label=name)
    ax.set(xlabel="looks k", ylabel="SR@k (%)", title="Success within k looks")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6)
    save_figure(fig, out / "success_vs_looks.png", name="--out file", dpi=100)


def _rank_cost_figure(results: dict, out: pathlib.Path, Figure) -> None:
    fig = Figure(figsize=(7, 4.5))
    ax = fig.subplots()
    horizons = [str(h) for h in results["protocol"]["horizons"]]
    for name, row in results["posterior"].items():
        by = row["metrics"]["rank_cost"]["by_horizon"]
        xs = [int(h) for h in horizons if by.get(h)]
        ax.plot(xs, [by[str(h)]["mean"] for h in xs], marker="o", ms=3, label=name)
    ax.set(xscale="log", xlabel="horizon Δτ (hours)", ylabel="rank cost",
           title="Rank cost by horizon")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6)
    save_figure(fig, out / "rank_cost_by_horizon.png", name="--out file", dpi=100)
