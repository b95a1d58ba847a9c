"""Figures of the search report: episodes on the map, success against looks and distance. Each
returns a Figure (no pyplot state); maps in pixels, y down."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from flowmaps_jax.flowsim import FlowSimConfig
from flowmaps_jax.search.episodes import SearchSet
from flowmaps_jax.search.report import POLICY_LABELS
from flowmaps_jax.search.simulator import Episodes, Outcome

_MAP = 2.6  # inches per map panel of plot_episodes
_BELIEF = 2.1  # inches per belief panel beside it
_TEXT = 8.5  # points: table names, look numbers, belief values, ticks


def pick_episodes(search_set: SearchSet, count: int = 2, horizons: tuple[int, int] = (2, 4),
                  score=None) -> list[int]:
    """Up to ``count`` episode indices, one per category: the highest ``score`` (N,) (default the
    exact posterior's entropy) with Δτ in ``horizons`` (any Δτ if none)."""
    m = search_set.queries.descriptor.shape[1]
    if score is None:
        q = np.asarray(search_set.slot_probs, np.float64)
        score = -np.sum(np.where(q > 0, q * np.log(np.where(q > 0, q, 1.0)), 0.0), axis=-1)
    score = np.asarray(score, np.float64).reshape(-1, m)
    horizon = np.asarray(search_set.horizon)
    inside = (horizon >= horizons[0]) & (horizon <= horizons[1])
    picks = []
    for obj in range(min(count, m)):
        best = np.where(inside[:, obj], score[:, obj], -np.inf)
        if not np.isfinite(best).any():
            best = score[:, obj]
        picks.append(int(np.argmax(best)) * m + obj)
    return picks


def _colour(entries, descriptor: int, default: str = "0.6") -> str:
    return next((e.colour for e in entries if e.descriptor == descriptor), default)


def draw_episode_map(ax: Axes, search_set: SearchSet, episodes: Episodes, outcome: Outcome,
                     n: int, config: FlowSimConfig, title: str | None = None) -> None:
    """Episode ``n`` on its map: furniture (candidate tables numbered along the route), the object
    where it was last seen (hollow) and where it is (star), the start (×), the path with each
    look numbered (green: found, red: not found within the budget)."""
    m = search_set.queries.descriptor.shape[1]
    r, obj = divmod(int(n), m)
    size = float(search_set.map_size)
    furniture = np.asarray(search_set.furniture_px[r])
    kinds = np.asarray(search_set.tokens.descriptor[r, : furniture.shape[0]])
    for (y0, x0, y1, x1), d in zip(furniture, kinds, strict=True):
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, alpha=0.35, linewidth=0.6,
                               facecolor=_colour(config.furniture_kinds, int(d)),
                               edgecolor="0.3"))
    centres = np.asarray(episodes.centres[n])
    valid = np.asarray(episodes.valid[n])
    for k in np.flatnonzero(valid):
        ax.annotate(f"T{k + 1}", (centres[k, 1], centres[k, 0]), xytext=(0, 9),
                    textcoords="offset points", ha="center", fontsize=_TEXT, color="0.15")
    category = config.categories[obj]
    seen = centres[int(search_set.slot_now[r, obj])]
    truth = centres[int(episodes.target[n])]
    ax.plot(seen[1], seen[0], "o", mfc="none", mec=category.colour, ms=11, mew=1.5)
    ax.plot(truth[1], truth[0], "*", color=category.colour, ms=14, mec="k", mew=0.5)
    start = np.asarray(episodes.start[n])
    path = np.asarray(outcome.path[n])
    stops = np.vstack([start, centres[path[path >= 0]]])
    found = bool(outcome.found[n])
    colour = "tab:green" if found else "tab:red"
    ax.plot(stops[:, 1], stops[:, 0], "-", color=colour, linewidth=1.6, alpha=0.85)
    ax.plot(start[1], start[0], "kx", ms=8, mew=2)
    for look, (y, x) in enumerate(stops[1:], start=1):
        offset = 4.0 * (np.sum(np.all(stops[1:look] == (y, x), axis=1)))  # repeated visits
        ax.annotate(str(look), (x + offset, y + offset), ha="center", va="center", fontsize=_TEXT,
                    color="white", bbox={"boxstyle": "circle,pad=0.2", "fc": colour,
                                         "ec": "none"})
    ax.set_xlim(0, size)
    ax.set_ylim(size, 0)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    looks, travel = int(outcome.looks[n]), float(outcome.travel[n])
    ax.set_title((title + "\n" if title else "")
                 + f"{looks} look{'' if looks == 1 else 's'}, {travel:.0f} px"
                 + ("" if found else " (not found)"), fontsize=9.5)


def draw_episode_beliefs(ax: Axes, episodes: Episodes, outcome: Outcome, n: int) -> None:
    """The belief each look of episode ``n`` was decided on (row l: before look l, i.e. after
    l − 1 failures), over the route's tables T1..TK; the looked-at table is boxed, the true
    table's column is marked ★."""
    looks = max(int(outcome.looks[n]), 1)
    valid = np.asarray(episodes.valid[n])
    k = int(valid.sum())
    belief = np.asarray(outcome.belief[n, :looks, :k])
    ax.imshow(belief, cmap="Blues", vmin=0.0, vmax=1.0, aspect="auto")
    for (row, col), value in np.ndenumerate(belief):
        ax.text(col, row, f"{value:.2f}", ha="center", va="center", fontsize=_TEXT,
                color="white" if value > 0.6 else "0.1")
    path = np.asarray(outcome.path[n, :looks])
    for row, col in enumerate(path):
        if col >= 0:
            ax.add_patch(Rectangle((col - 0.5, row - 0.5), 1, 1, fill=False, linewidth=1.5,
                                   edgecolor="tab:orange"))
    target = int(episodes.target[n])
    ax.set_xticks(range(k), [f"T{i + 1}" + ("★" if i == target else "") for i in range(k)],
                  fontsize=_TEXT)
    ax.set_yticks(range(looks), [f"look {i + 1}" for i in range(looks)], fontsize=_TEXT)


def plot_episodes(search_set: SearchSet, runs: Mapping[str, tuple[Episodes, Outcome]],
                  picks: Sequence[int], config: FlowSimConfig, policy: str = "optimal") -> Figure:
    """Per picked episode and prior in ``runs`` ({row name: (Episodes, Outcome)}): the episode on
    the map and the belief before every look."""
    if not runs or not picks:
        raise ValueError("runs and picks must not be empty")
    names = list(runs)
    m = search_set.queries.descriptor.shape[1]
    fig = Figure(figsize=(len(picks) * (_MAP + _BELIEF) + 0.3, len(names) * (_MAP + 0.3) + 1.0),
                 layout="constrained")
    columns = np.atleast_1d(fig.subfigures(1, len(picks)))
    for column, n in zip(columns, picks, strict=True):
        r, obj = divmod(int(n), m)
        grid = column.add_gridspec(len(names), 2, width_ratios=[_MAP, _BELIEF])
        for row, name in enumerate(names):
            episodes, outcome = runs[name]
            draw_episode_map(column.add_subplot(grid[row, 0]), search_set, episodes, outcome, n,
                             config, name)
            beliefs = column.add_subplot(grid[row, 1])
            draw_episode_beliefs(beliefs, episodes, outcome, n)
            if row == 0:
                beliefs.set_title("belief before each look\n(orange: the table looked at)",
                                  fontsize=9.5)
        column.suptitle(f"{config.categories[obj].name}, seen at τ = {int(search_set.tau[r])}, "
                        f"searched at τ_q = {int(search_set.tau_q[r])}", fontsize=11)
    fig.suptitle(f"Search episodes, policy: {POLICY_LABELS.get(policy, policy)}\n"
                 "× start, ○ last seen, ★ true table; numbered circles: the looks in order "
                 "(green path: found, red: not found within the budget)", fontsize=11)
    return fig


def _curve_figure(results: dict, title: str, xlabel: str, series) -> Figure:
    policies = results["protocol"]["policies"]
    fig = Figure(figsize=(4.2 * len(policies), 3.6), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(policies), sharey=True))
    for ax, policy in zip(axes, policies, strict=True):
        for i, (name, entry) in enumerate(results["rows"].items()):
            x, y = series(entry["policies"][policy]["curves"])
            style = "--" if i == 0 else "-"
            ax.plot(x, y, style, color=f"C{i}", label=name, linewidth=1.4, marker=".",
                    markersize=3)
        ax.set(title=POLICY_LABELS.get(policy, policy), xlabel=xlabel, ylim=(0, 1.02))
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("success rate")
    axes[-1].legend(fontsize=7, loc="lower right")
    fig.suptitle(title, fontsize=10)
    return fig


def plot_success_vs_looks(results: dict) -> Figure:
    """Success rate within k looks, k = 1..budget, for every row; one panel per policy."""
    return _curve_figure(results, "Found within k looks (dashed: exact posterior)", "looks k",
                         lambda c: (np.arange(1, len(c["looks"]) + 1), c["looks"]))


def plot_success_vs_distance(results: dict) -> Figure:
    """Success rate within d pixels driven, for every row; one panel per policy."""
    return _curve_figure(results, "Found within d pixels of travel (dashed: exact posterior)",
                         "distance driven d [px]",
                         lambda c: (c["distance"]["d"], c["distance"]["success"]))
