"""The report's figures: KL (paper Fig. 2), metrics by horizon, samples over the exact posterior
(paper Fig. 3) and learned vs exact slot distributions. Each returns a matplotlib ``Figure``
(no pyplot state); :func:`flowmaps_jax.evaluation.run_evaluation` saves them next to the report.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.figure import Figure

from flowmaps_jax.evaluation.protocol import REFERENCE_ROWS, EvalSet, RowResult
from flowmaps_jax.flowsim.config import FlowSimConfig
from flowmaps_jax.flowsim.render import draw_posterior, overlay_boxes


def _is_reference(name: str, row: dict) -> bool:
    """A reference row: one of ``REFERENCE_ROWS``, or a row without a model (no "kind" in its
    info, e.g. a history's "exact, H = 1")."""
    return name in REFERENCE_ROWS or "kind" not in row.get("info", {})


def plot_kl(results: dict, rows: Sequence[str] | None = None) -> Figure:
    """Paper Fig. 2: KL(q‖p) of the model rows (FlowMaps vs the MLP baselines), overall, by
    category and by horizon, with standard-error bars. rows: which rows (default: all models)."""
    table = results["rows"]
    if rows is None:
        rows = [n for n in table if not _is_reference(n, table[n])] or list(table)
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
        rows += [n for n in table if not _is_reference(n, table[n])]
    fig = Figure(figsize=(13, 3.8), layout="constrained")
    axes = fig.subplots(1, 3)
    panels = (("KL(q‖p) [nats]", lambda r: r["kl"]),
              (f"slot TV @{n_big}", lambda r: r["slots"][n_big]["tv"]),
              (f"rank cost @{n_big}", lambda r: r["slots"][n_big]["search_cost_ratio"]))
    for ax, (label, pick) in zip(axes, panels, strict=True):
        for i, name in enumerate(rows):
            by_h = pick(table[name])["by_horizon"]
            hs = list(by_h)
            mean = np.array([np.nan if by_h[h]["mean"] is None else by_h[h]["mean"] for h in hs])
            err = np.array([by_h[h]["stderr"] or 0.0 for h in hs], float)
            x = np.array([int(h) for h in hs])
            style = "--" if _is_reference(name, table[name]) else "-"
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
    """One (environment row, object) per category: the query with Δτ in ``horizons`` whose exact
    posterior has the most entropy (any horizon if none)."""
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


def _picks(evalset: EvalSet, config: FlowSimConfig,
           picks: Sequence[tuple[int, int]] | None) -> list[tuple[int, int]]:
    """The queries a figure draws: ``picks``, by default :func:`pick_queries`'s; none is a
    ``ValueError``."""
    picks = list(pick_queries(evalset, config) if picks is None else picks)
    if not picks:
        raise ValueError("picks is empty: no query to draw")
    return picks


def plot_samples(scenes, evalset: EvalSet, rows: Sequence[RowResult], config: FlowSimConfig,
                 picks: Sequence[tuple[int, int]] | None = None, num_shown: int = 25) -> Figure:
    """Paper Fig. 3: per picked query, the map at τ with the exact posterior shaded and
    ``num_shown`` samples of each model overlaid (a row of panels per model)."""
    rows = [r for r in rows if r.samples is not None]
    if not rows:
        raise ValueError("rows must include at least one model row with samples")
    picks = _picks(evalset, config, picks)
    fig = Figure(figsize=(4.3 * len(picks), 4.3 * len(rows)), layout="constrained")
    axes = fig.subplots(len(rows), len(picks), squeeze=False)
    for r, row in enumerate(rows):
        for c, (e, m) in enumerate(picks):
            ax = axes[r, c]
            env, tau = int(evalset.env[e]), int(evalset.tau[e])
            draw_posterior(scenes, env, m, tau, np.asarray(evalset.slot_probs[e, m]), config,
                           ax=ax)
            # black, so that the samples stand apart from the places shaded in the object's colour
            overlay_boxes(ax, row.samples[e, m, :num_shown], config, edgecolor="black",
                          linewidth=1.0, alpha=0.8)
            ax.set_title(f"{row.name}: {config.categories[m].name}, τ = {tau} → "
                         f"τ_q = {int(evalset.tau_q[e])}", fontsize=9)
    fig.suptitle(f"{num_shown} samples per query (black outlines) over the exact posterior (the "
                 "object's places, shaded by q and labelled with it); yellow ring: the object "
                 "at τ", fontsize=11)
    return fig


def plot_slot_bars(evalset: EvalSet, rows: Sequence[RowResult], config: FlowSimConfig,
                   picks: Sequence[tuple[int, int]] | None = None,
                   num_samples: int | None = None) -> Figure:
    """Learned slot distributions p̂ (from num_samples samples, default the largest count) next to
    the exact q, one panel per picked query; slots in visiting order, then "off"."""
    rows = [r for r in rows if r.samples is not None] or list(rows)
    picks = _picks(evalset, config, picks)
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
    axes[-1].legend(fontsize=8)
    fig.suptitle("learned slot distribution vs the exact posterior", fontsize=11)
    return fig

