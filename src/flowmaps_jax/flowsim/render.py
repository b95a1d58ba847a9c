"""Matplotlib drawings of FlowSim scenes: one map, a timeline, visiting orders, posteriors.
Every function returns a Figure (or draws into ``ax``), no global pyplot state; pixel boxes
(y0, x0, y1, x1), y down; artists carry a ``gid`` (``"furniture"``, ``"object"``, ...)."""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import PatchCollection
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle, FancyArrowPatch, Patch, Polygon, Rectangle

from flowmaps_jax.flowsim.config import FlowSimConfig
from flowmaps_jax.flowsim.generate import Scenes, validate_scenes
from flowmaps_jax.validation import (
    check_flag,
    check_instance,
    check_int,
    check_int_array,
    check_probabilities,
    check_real_array,
)

# matplotlib marker used in legends for each object shape.
_LEGEND_MARKERS = {"square": "s", "circle": "o", "triangle": "^", "diamond": "D",
                   "pentagon": "p", "hexagon": "h", "star": "*"}
_POLYGON_SIDES = {"pentagon": 5, "hexagon": 6}
_ANGULAR_ORDERINGS = ("clockwise", "counter_clockwise")

_FURNITURE_ALPHA = 0.55
_POSTERIOR_MAX_ALPHA = 0.7  # opacity of the most probable place in draw_posterior
_PANEL_SIZE = 4.0  # inches per map panel


# --------------------------------------------------------------------------------------------
# Validation and config look-ups
# --------------------------------------------------------------------------------------------

def _check_scene_env(scenes: Scenes, env: int, config: FlowSimConfig) -> int:
    """Every figure's ``config``, ``scenes`` (shapes and dtypes) and ``env``, as an int."""
    check_instance("config", config, FlowSimConfig)
    validate_scenes(scenes, values=False)
    return check_int("env", env, 0, scenes.num_envs - 1)


def _by_descriptor(entries: Sequence[Any]) -> dict[int, Any]:
    """Map descriptor id -> entry of ``config.furniture_kinds`` or ``config.categories``."""
    return {int(entry.descriptor): entry for entry in entries}


def _lookup(table: dict[int, Any], descriptor: int, field: str) -> Any:
    try:
        return table[int(descriptor)]
    except KeyError:
        raise ValueError(
            f"scenes use descriptor id {int(descriptor)} that config.{field} does not define "
            f"(known: {sorted(table)}); pass the config the scenes were generated with") from None


class _EnvView:
    """The numpy arrays of one environment, plus its config entries (built once per figure)."""

    def __init__(self, scenes: Scenes, env: int, config: FlowSimConfig):
        self.map_size = float(config.map_size)
        self.furniture_boxes = np.asarray(scenes.furniture_boxes[env], dtype=float)  # (F, 4)
        self.object_boxes = np.asarray(scenes.object_boxes[env], dtype=float)  # (T, M, 4)
        self.slot = np.asarray(scenes.slot[env])  # (T, M)
        self.visit_order = np.asarray(scenes.visit_order[env])  # (M, F)
        self.num_slots = np.asarray(scenes.num_slots[env])  # (M,)
        self.object_size = np.asarray(scenes.object_size[env], dtype=float)  # (M,)
        kinds = _by_descriptor(config.furniture_kinds)
        categories = _by_descriptor(config.categories)
        self.furniture_entries = [_lookup(kinds, d, "furniture_kinds")
                                  for d in np.asarray(scenes.furniture_kind[env])]
        self.categories = [_lookup(categories, d, "categories")
                           for d in np.asarray(scenes.object_kind[env])]
        self.kinds_in_config = list(config.furniture_kinds)

    @property
    def num_objects(self) -> int:
        return len(self.categories)

    def furniture_centres(self) -> np.ndarray:
        """(F, 2) centres (y, x) in pixels."""
        b = self.furniture_boxes
        return np.stack([(b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2], axis=-1)

    def order(self, obj: int) -> np.ndarray:
        """Furniture indices of object ``obj``'s visiting order (length num_slots)."""
        return self.visit_order[obj, : int(self.num_slots[obj])]


# --------------------------------------------------------------------------------------------
# Primitive drawing helpers
# --------------------------------------------------------------------------------------------

def _new_axes(figsize: tuple[float, float]) -> tuple[Figure, Axes]:
    fig = Figure(figsize=figsize, layout="constrained")
    return fig, fig.add_subplot()


def _setup_map_axes(ax: Axes, map_size: float) -> None:
    """Equal aspect, y inverted (image coordinates), a map border, light ticks."""
    ax.set_xlim(-2, map_size + 2)
    ax.set_ylim(map_size + 2, -2)
    ax.set_aspect("equal")
    ax.add_patch(Rectangle((0, 0), map_size, map_size, fill=False, edgecolor="0.2",
                           linewidth=1.5, zorder=0.5, gid="border"))
    ax.set_facecolor("white")
    ticks = np.linspace(0, map_size, 5)
    ax.set_xticks(ticks)
    ax.set_yticks(ticks)
    ax.tick_params(labelsize=7, length=2, colors="0.4")
    for spine in ax.spines.values():
        spine.set_visible(False)


def _regular_vertices(cy: float, cx: float, radius: float, n: int,
                      inner: float | None = None) -> np.ndarray:
    """(n or 2n, 2) vertices (x, y) of a regular polygon (or star) with a vertex pointing up."""
    if inner is None:
        angles, radii = 2 * np.pi * np.arange(n) / n, np.full(n, radius)
    else:
        angles = np.pi * np.arange(2 * n) / n
        radii = np.where(np.arange(2 * n) % 2 == 0, radius, inner * radius)
    return np.stack([cx + radii * np.sin(angles), cy - radii * np.cos(angles)], axis=-1)


def _box_patch(box: np.ndarray, shape: str, **style: Any):
    """A patch of the given shape inscribed in a pixel box (y0, x0, y1, x1); "up" is small y."""
    y0, x0, y1, x1 = (float(v) for v in box)
    cy, cx, radius = (y0 + y1) / 2, (x0 + x1) / 2, min(x1 - x0, y1 - y0) / 2
    if shape == "square":
        return Rectangle((x0, y0), x1 - x0, y1 - y0, **style)
    if shape == "circle":
        return Circle((cx, cy), radius, **style)
    if shape == "triangle":
        return Polygon([(cx, y0), (x1, y1), (x0, y1)], closed=True, **style)
    if shape == "diamond":
        return Polygon([(cx, y0), (x1, cy), (cx, y1), (x0, cy)], closed=True, **style)
    if shape in _POLYGON_SIDES:
        return Polygon(_regular_vertices(cy, cx, radius, _POLYGON_SIDES[shape]), closed=True,
                       **style)
    # "star", the last of config.SHAPES (a config names only those)
    return Polygon(_regular_vertices(cy, cx, 1.1 * radius, 5, inner=0.45), closed=True, **style)


def _draw_furniture(ax: Axes, view: _EnvView, emphasise: set[int] | None = None) -> None:
    """One rectangle per furniture piece; pieces outside ``emphasise`` (if given) are faded."""
    for f, (box, kind) in enumerate(zip(view.furniture_boxes, view.furniture_entries,
                                        strict=True)):
        faded = emphasise is not None and f not in emphasise
        colour = kind.colour
        ax.add_patch(Rectangle(
            (box[1], box[0]), box[3] - box[1], box[2] - box[0],
            facecolor=to_rgba(colour, 0.12 if faded else _FURNITURE_ALPHA),
            edgecolor=to_rgba(colour, 0.3 if faded else 1.0), linewidth=1.2, zorder=1,
            gid="furniture"))


def _draw_object(ax: Axes, box: np.ndarray, category: Any, ghost: bool = False,
                 highlight: bool = False) -> None:
    colour = category.colour
    if ghost:
        style = dict(facecolor=to_rgba(colour, 0.15), edgecolor=to_rgba(colour, 0.8),
                     linestyle=(0, (2, 1.5)), linewidth=1.2, zorder=2, gid="ghost")
    else:
        style = dict(facecolor=colour, edgecolor="white", linewidth=1.2, zorder=3, gid="object")
    ax.add_patch(_box_patch(box, category.shape, **style))
    if highlight:
        y0, x0, y1, x1 = box
        pad = 0.35 * (y1 - y0) + 2
        ax.add_patch(Circle(((x0 + x1) / 2, (y0 + y1) / 2), (y1 - y0) / 2 + pad, fill=False,
                            edgecolor="gold", linewidth=2.5, zorder=2.5, gid="highlight"))


def _legend_handles(view: _EnvView, kinds: bool = True, objects: bool = True) -> list:
    """Legend entries for every furniture kind in the config and every object in the scene."""
    handles: list = []
    if kinds:
        for kind in view.kinds_in_config:
            handles.append(Patch(facecolor=to_rgba(kind.colour, _FURNITURE_ALPHA),
                                 edgecolor=kind.colour, label=kind.name.replace("_", " ")))
    if objects:
        for category in view.categories:
            handles.append(Line2D([], [], linestyle="none", marker=_LEGEND_MARKERS[category.shape],
                                  markersize=8, markerfacecolor=category.colour,
                                  markeredgecolor="white", label=category.name))
    return handles


def _add_legend_entries(ax: Axes, handles: Sequence[Any]) -> None:
    """Append ``handles`` to the legend of ``ax`` (made beside the map as in :func:`draw_scene`
    if there is none yet)."""
    legend = ax.get_legend()
    old = list(legend.legend_handles) if legend is not None else []
    labels = [t.get_text() for t in legend.get_texts()] if legend is not None else []
    labels += [h.get_label() for h in handles]
    ax.legend(handles=[*old, *handles], labels=labels, loc="upper left",
              bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False, borderaxespad=0.0)


def _draw_order_arrows(ax: Axes, view: _EnvView, obj: int, numbers: bool = True,
                       curvature: float = 0.2) -> None:
    """Arrows from each piece of ``obj``'s visiting order to the next (cyclic), numbered 1..K."""
    centres = view.furniture_centres()
    order = view.order(obj)
    colour = view.categories[obj].colour
    k = len(order)
    for i in range(k if k > 1 else 0):
        a, b = order[i], order[(i + 1) % k]
        wrap = i == k - 1
        ax.add_patch(FancyArrowPatch(
            (centres[a, 1], centres[a, 0]), (centres[b, 1], centres[b, 0]),
            connectionstyle=f"arc3,rad={curvature}", arrowstyle="-|>,head_length=6,head_width=3",
            color=colour, linewidth=1.6, linestyle=(0, (4, 2)) if wrap else "-",
            shrinkA=9, shrinkB=9, zorder=4, alpha=0.9, gid="order"))
    if numbers:
        for i, f in enumerate(order):
            ax.text(centres[f, 1], centres[f, 0], str(i + 1), ha="center", va="center",
                    fontsize=8, fontweight="bold", color="white", zorder=5, gid="order_label",
                    bbox=dict(boxstyle="circle,pad=0.25", facecolor=colour, edgecolor="white",
                              linewidth=0.8))


# --------------------------------------------------------------------------------------------
# Public figures
# --------------------------------------------------------------------------------------------

def draw_scene(scenes: Scenes, env: int, tau: int, config: FlowSimConfig, ax: Axes | None = None,
               show_orders: bool = False, highlight: int | None = None, legend: bool = True,
               title: str | None = None) -> Figure:
    """Draw environment ``env`` at timestep ``tau`` (into ``ax``, or a new figure); return the
    figure. ``show_orders``: each category's visiting order as arrows; ``highlight``: ring
    object index in [0, M); ``legend``: a furniture/object legend.
    """
    env = _check_scene_env(scenes, env, config)
    tau = check_int("tau", tau, 0, scenes.slot.shape[1] - 1)
    if highlight is not None:
        highlight = check_int("highlight", highlight, 0, scenes.object_kind.shape[1] - 1)
    if ax is not None:
        check_instance("ax", ax, Axes)
    show_orders = check_flag("show_orders", show_orders)
    legend = check_flag("legend", legend)
    if title is not None:
        check_instance("title", title, str)
    view = _EnvView(scenes, env, config)
    return _draw_scene(view, env, tau, ax, show_orders, highlight, legend, title)


def _draw_scene(view: _EnvView, env: int, tau: int, ax: Axes | None, show_orders: bool,
                highlight: int | None, legend: bool, title: str | None) -> Figure:
    """:func:`draw_scene` of checked arguments (its other figures' panels)."""
    if ax is None:
        _, ax = _new_axes((_PANEL_SIZE + 1.9, _PANEL_SIZE))
    _setup_map_axes(ax, view.map_size)
    _draw_furniture(ax, view)
    for m, category in enumerate(view.categories):
        _draw_object(ax, view.object_boxes[tau, m], category, highlight=highlight == m)
    if show_orders:
        for m in range(view.num_objects):
            _draw_order_arrows(ax, view, m, numbers=False, curvature=0.25)
    ax.set_title(f"environment {env}, τ = {tau}" if title is None else title, fontsize=10)
    if legend:
        ax.legend(handles=_legend_handles(view), loc="upper left", bbox_to_anchor=(1.02, 1.0),
                  fontsize=8, frameon=False, borderaxespad=0.0)
    return ax.figure


def draw_timeline(scenes: Scenes, env: int, taus: Sequence[int], config: FlowSimConfig) -> Figure:
    """Panels of environment ``env`` at strictly increasing ``taus``, each object's previous box
    a dashed ghost with an arrow to where it is now (paper Fig. 1)."""
    env = _check_scene_env(scenes, env, config)
    taus = check_int_array("taus", taus, 0, scenes.slot.shape[1] - 1, shape=(None,))
    taus = [int(t) for t in np.asarray(taus).tolist()]
    if not taus or any(b <= a for a, b in itertools.pairwise(taus)):
        raise ValueError(f"taus must be a non-empty, strictly increasing sequence of timestep "
                         f"indices; got {taus}")
    view = _EnvView(scenes, env, config)
    fig = Figure(figsize=(_PANEL_SIZE * len(taus), _PANEL_SIZE + 0.9), layout="constrained")
    axes = fig.subplots(1, len(taus), squeeze=False)[0]
    for i, (ax, tau) in enumerate(zip(axes, taus, strict=True)):
        _draw_scene(view, env, tau, ax, False, None, False, f"τ = {tau}")
        if i == 0:
            ax.set_xlabel("start", fontsize=8)
            continue
        prev = taus[i - 1]
        moves = []
        for m, category in enumerate(view.categories):
            k = int(view.num_slots[m])
            step = int(view.slot[tau, m] - view.slot[prev, m]) % max(k, 1)
            stayed = step == 0 and tau - prev == 1  # over several steps +0 may mean a full lap
            moves.append(f"{category.name} stays" if stayed else f"{category.name} +{step}")
            old, new = view.object_boxes[prev, m], view.object_boxes[tau, m]
            if np.allclose(old, new):
                continue
            _draw_object(ax, old, category, ghost=True)
            ax.add_patch(FancyArrowPatch(
                ((old[1] + old[3]) / 2, (old[0] + old[2]) / 2),
                ((new[1] + new[3]) / 2, (new[0] + new[2]) / 2),
                connectionstyle="arc3,rad=0.2", arrowstyle="-|>,head_length=7,head_width=3.5",
                color=category.colour, linewidth=1.8, shrinkA=4, shrinkB=7, zorder=4,
                gid="move"))
        ax.set_xlabel(", ".join(moves), fontsize=8)
    fig.legend(handles=_legend_handles(view), loc="outside lower center",
               ncol=len(view.kinds_in_config) + view.num_objects, fontsize=8, frameon=False)
    fig.suptitle(f"FlowSim environment {env}: objects move along their visiting orders "
                 "(dashed: previous place)", fontsize=10)
    return fig


def draw_visit_orders(scenes: Scenes, env: int, config: FlowSimConfig) -> Figure:
    """One panel per object category: its visiting order as numbered (1..K), cyclic arrows."""
    env = _check_scene_env(scenes, env, config)
    view = _EnvView(scenes, env, config)
    m_count = view.num_objects
    fig = Figure(figsize=(_PANEL_SIZE * m_count, _PANEL_SIZE + 0.7), layout="constrained")
    axes = fig.subplots(1, m_count, squeeze=False)[0]
    for m, ax in enumerate(axes):
        category = view.categories[m]
        order = view.order(m)
        _setup_map_axes(ax, view.map_size)
        _draw_furniture(ax, view, emphasise={int(f) for f in order})
        _draw_order_arrows(ax, view, m)
        c = view.map_size / 2
        ax.plot([c], [c], marker="+", markersize=10, color="0.4", zorder=1.5)
        if category.ordering in _ANGULAR_ORDERINGS:  # show the angles the order is sorted by
            centres = view.furniture_centres()[order]
            ax.plot([c, c], [c, c - 0.12 * view.map_size], color="0.4", linewidth=1.0,
                    zorder=1.5, gid="ray")
            ax.text(c + 3, c - 0.12 * view.map_size, "0", fontsize=7, color="0.4",
                    va="center", ha="left")
            for cy, cx in centres:
                ax.plot([c, cx], [c, cy], color=category.colour, linewidth=0.8,
                        linestyle=":", alpha=0.6, zorder=1.5, gid="ray")
        kind = view.furniture_entries[int(order[0])].name.replace("_", " ") if len(order) else "?"
        ordering = category.ordering.replace("_", "-")
        ax.set_title(f"{category.name}: {ordering}\n({len(order)} × {kind})", fontsize=10,
                     color=category.colour)
    fig.legend(handles=_legend_handles(view, objects=False), loc="outside lower center",
               ncol=len(view.kinds_in_config), fontsize=8, frameon=False)
    fig.suptitle(f"FlowSim environment {env}: visiting orders (dashed arrow closes the cycle)",
                 fontsize=10)
    return fig


def draw_posterior(scenes: Scenes, env: int, obj: int, tau: int, probs: Any, config: FlowSimConfig,
                   ax: Axes | None = None) -> Figure:
    """Shade the places of object ``obj`` by ``probs`` (num_slots,) or zero-padded (F,), not
    necessarily normalised, over the scene at ``tau``."""
    env = _check_scene_env(scenes, env, config)
    obj = check_int("obj", obj, 0, scenes.object_kind.shape[1] - 1)
    tau = check_int("tau", tau, 0, scenes.slot.shape[1] - 1)
    probs = check_probabilities("probs", probs, (None,), atol=0.0, min_value=-0.0,
                                normalised=False)
    if ax is not None:
        check_instance("ax", ax, Axes)
    view = _EnvView(scenes, env, config)
    k = int(view.num_slots[obj])
    if len(probs) < k or np.any(probs[k:] > 1e-6):
        raise ValueError(f"probs must be a 1-D array over the {k} places of object {obj}, "
                         f"optionally padded with zeros (no mass beyond them); got {probs}")
    probs = probs[:k]
    fig = _draw_scene(view, env, tau, ax, False, obj, ax is None, None)
    ax = fig.axes[0] if ax is None else ax
    category = view.categories[obj]
    centres = view.furniture_centres()
    half = view.object_size[obj] / 2
    top = probs.max() if probs.max() > 0 else 1.0
    for slot, f in enumerate(view.order(obj)):
        cy, cx = centres[f]
        p = probs[slot]
        ax.add_patch(Rectangle(
            (cx - 1.6 * half, cy - 1.6 * half), 3.2 * half, 3.2 * half,
            facecolor=to_rgba(category.colour, _POSTERIOR_MAX_ALPHA * p / top),
            edgecolor=category.colour, linewidth=1.0, linestyle="-" if p > 0 else ":",
            zorder=2.2, gid="posterior"))
        below = cy + 1.9 * half + 4  # label under the place, or above it at the map's bottom
        y, va = (below, "top") if below + 10 < view.map_size else (cy - 1.9 * half - 4, "bottom")
        ax.text(cx, y, f"{p:.2f}", ha="center", va=va, fontsize=8, color="0.1", zorder=5,
                gid="posterior_label",
                bbox=dict(boxstyle="round,pad=0.15", facecolor="white", edgecolor="none",
                          alpha=0.8))
    ax.set_title(f"{category.name}: where could it be? (map at τ = {tau})", fontsize=10)
    if ax.get_legend() is not None:  # own figure: name the marks this figure adds
        _add_legend_entries(ax, [
            Line2D([], [], linestyle="none", marker="o", markersize=11, markerfacecolor="none",
                   markeredgecolor="gold", markeredgewidth=2.5,
                   label=f"the {category.name} at τ = {tau}"),
            Patch(facecolor=to_rgba(category.colour, 0.45), edgecolor=category.colour,
                  label="its possible places\n(shade ∝ probability)")])
        fig.set_size_inches(_PANEL_SIZE + 2.3, _PANEL_SIZE)
    return fig


def overlay_boxes(ax: Axes, boxes_norm: Any, config: FlowSimConfig, label: str | None = None,
                  **style: Any) -> PatchCollection:
    """Draw normalised (y, x, h, w) boxes ``boxes_norm`` (N, 4) or (4,) over the map in ``ax``
    (``style`` for the PatchCollection, ``label`` a legend entry); returns the collection.
    """
    check_instance("ax", ax, Axes)
    boxes_norm = check_real_array("boxes_norm", boxes_norm)
    check_instance("config", config, FlowSimConfig)
    if label is not None:
        check_instance("label", label, str)
    boxes = np.asarray(boxes_norm, dtype=float)
    if boxes.ndim == 1:
        boxes = boxes[None]
    if boxes.ndim != 2 or boxes.shape[1] != 4:
        raise ValueError(f"boxes_norm must have shape (N, 4) or (4,) as (y, x, h, w); "
                         f"got {np.shape(boxes_norm)}")
    scale = float(config.map_size) - 1.0
    y, x, h, w = (boxes * scale).T
    patches = [Rectangle((xi, yi), wi, hi) for yi, xi, hi, wi in zip(y, x, h, w, strict=True)]
    options = dict(facecolor="none", edgecolor="black", linewidth=1.0, alpha=0.7, zorder=6,
                   gid="overlay")
    options.update(style)
    collection = PatchCollection(patches, match_original=False, **options)
    ax.add_collection(collection)
    if label is not None:
        _add_legend_entries(ax, [Patch(facecolor="none", edgecolor=options["edgecolor"],
                                       linewidth=options["linewidth"], label=label)])
    return collection
