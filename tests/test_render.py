"""flowsim.render: figures save as real PNGs, artists match the scene, bad input raises."""

from __future__ import annotations

import dataclasses

import matplotlib

matplotlib.use("Agg")

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.colors import to_rgba
from matplotlib.image import imread

from flowmaps_jax.flowsim import render
from flowmaps_jax.flowsim.config import FlowSimConfig, ObjectCategory
from flowmaps_jax.flowsim.generate import Scenes, generate

NUM_TIMESTEPS = 6


def hand_built_scenes(config: FlowSimConfig, num_envs: int = 2) -> Scenes:
    """A deterministic Scenes for ``config`` without the simulator: tables on a grid, kinds
    round-robin, each object visiting its kind's tables in index order (object m advances m + 1
    places per step, so some objects stay put)."""
    f_count, m_count, t_count = config.num_furniture, config.num_objects, config.num_timesteps
    cell = config.map_size // 4
    kind_ids = [k.descriptor for k in config.furniture_kinds]
    fb = np.zeros((num_envs, f_count, 4), np.float32)
    for e in range(num_envs):
        for f in range(f_count):
            r, c = divmod((f + e) % 16, 4)
            side = 0.4 * cell + 3 * (f % 3)
            fb[e, f] = [r * cell + 4, c * cell + 4, r * cell + 4 + side, c * cell + 4 + side + e]
    fk = np.tile([kind_ids[f % len(kind_ids)] for f in range(f_count)], (num_envs, 1))
    vo = -np.ones((num_envs, m_count, f_count), np.int32)
    ns = np.zeros((num_envs, m_count), np.int32)
    size = np.zeros((num_envs, m_count), np.float32)
    slot = np.zeros((num_envs, t_count, m_count), np.int32)
    ob = np.zeros((num_envs, t_count, m_count, 4), np.float32)
    for m, cat in enumerate(config.categories):
        kind = next(k.descriptor for k in config.furniture_kinds if k.name == cat.furniture_kind)
        order = np.flatnonzero(fk[0] == kind)
        vo[:, m, : len(order)] = order
        ns[:, m] = len(order)
        for e in range(num_envs):
            start = fb[e, order[0]]
            size[e, m] = max(5, np.floor(0.4 * min(start[2] - start[0], start[3] - start[1])))
            for t in range(t_count):
                slot[e, t, m] = (t * (m + 1)) % len(order)
                table = fb[e, order[slot[e, t, m]]]
                cy, cx = (table[0] + table[2]) / 2, (table[1] + table[3]) / 2
                half = size[e, m] / 2
                ob[e, t, m] = [cy - half, cx - half, cy + half, cx + half]
    return Scenes(
        furniture_boxes=jnp.asarray(fb), furniture_kind=jnp.asarray(fk, jnp.int32),
        object_kind=jnp.asarray(np.tile([c.descriptor for c in config.categories],
                                        (num_envs, 1)), jnp.int32),
        object_size=jnp.asarray(size), visit_order=jnp.asarray(vo), num_slots=jnp.asarray(ns),
        slot=jnp.asarray(slot), object_boxes=jnp.asarray(ob),
        layout_redraws=jnp.zeros((num_envs,), jnp.int32),
        habit=jnp.zeros((num_envs, config.num_objects), jnp.int32))


@pytest.fixture(scope="module")
def config() -> FlowSimConfig:
    return FlowSimConfig(num_timesteps=NUM_TIMESTEPS)


@pytest.fixture(scope="module")
def scenes(config) -> Scenes:
    """Two environments from the real simulator (the hand-built helper covers other configs)."""
    return generate(jax.random.key(3), 2, config)


# ------------------------------------------------------------------------------------ helpers

def by_gid(ax, gid: str) -> list:
    return [a for a in [*ax.patches, *ax.texts] if a.get_gid() == gid]


def data_centre(patch) -> tuple[float, float]:
    """(x, y) centre of a patch's bounding box in data coordinates."""
    bbox = patch.get_path().transformed(patch.get_patch_transform()).get_extents()
    return (bbox.x0 + bbox.x1) / 2, (bbox.y0 + bbox.y1) / 2


def box_centre(box) -> tuple[float, float]:
    y0, x0, y1, x1 = np.asarray(box, float)
    return (x0 + x1) / 2, (y0 + y1) / 2


def assert_png(fig, path) -> None:
    """Save ``fig`` and check the file is a real, non-blank image."""
    fig.savefig(path, dpi=60)
    assert path.stat().st_size > 5_000
    image = imread(path)
    assert image.ndim == 3 and image.shape[0] > 100 and image.shape[1] > 100
    assert image[..., :3].std() > 0.05  # not a blank canvas


# ------------------------------------------------------------------------------------ scene

def test_draw_scene_matches_scene(scenes, config, tmp_path):
    env, tau = 1, 3
    fig = render.draw_scene(scenes, env, tau, config)
    assert_png(fig, tmp_path / "scene.png")
    ax = fig.axes[0]
    furniture = by_gid(ax, "furniture")
    objects = by_gid(ax, "object")
    assert len(furniture) == scenes.furniture_boxes.shape[1]
    assert len(objects) == config.num_objects
    # each furniture patch has its kind's colour, each object sits at its box at tau
    colours = {k.descriptor: k.colour for k in config.furniture_kinds}
    for patch, kind in zip(furniture, np.asarray(scenes.furniture_kind[env]), strict=True):
        assert patch.get_edgecolor() == pytest.approx(to_rgba(colours[int(kind)]))
    for m, patch in enumerate(objects):
        assert data_centre(patch) == pytest.approx(box_centre(scenes.object_boxes[env, tau, m]))
        assert patch.get_facecolor() == pytest.approx(to_rgba(config.categories[m].colour))
    # image coordinates: y axis inverted, equal aspect; legend names every kind and category
    assert ax.get_ylim()[0] > ax.get_ylim()[1]
    assert ax.get_aspect() == 1.0
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ([k.name.replace("_", " ") for k in config.furniture_kinds]
                      + [c.name for c in config.categories])
    assert plt.get_fignums() == []  # no pyplot state: figures are plain Figure objects


def test_draw_scene_into_given_axes_with_orders_and_highlight(scenes, config):
    from matplotlib.figure import Figure

    fig = Figure()
    ax = fig.add_subplot()
    assert render.draw_scene(scenes, 0, 0, config, ax=ax, show_orders=True, highlight=2) is fig
    num_slots = np.asarray(scenes.num_slots[0])
    assert len(by_gid(ax, "order")) == int(num_slots.sum())  # K arrows per cyclic order
    ring = by_gid(ax, "highlight")
    assert len(ring) == 1
    assert data_centre(ring[0]) == pytest.approx(box_centre(scenes.object_boxes[0, 0, 2]))


# ------------------------------------------------------------------------------------ timeline

def test_draw_timeline_arrows_follow_moves(scenes, config, tmp_path):
    env, taus = 0, [0, 1, 2, 4]
    fig = render.draw_timeline(scenes, env, jnp.asarray(taus), config)  # any 1-D int sequence
    assert_png(fig, tmp_path / "timeline.png")
    axes = [ax for ax in fig.axes if by_gid(ax, "furniture")]
    assert len(axes) == len(taus)
    boxes = np.asarray(scenes.object_boxes[env])
    assert not by_gid(axes[0], "move")
    for ax, prev, now in zip(axes[1:], taus[:-1], taus[1:], strict=True):
        moved = [m for m in range(config.num_objects)
                 if not np.allclose(boxes[prev, m], boxes[now, m])]
        assert len(by_gid(ax, "move")) == len(moved)
        ghosts = by_gid(ax, "ghost")
        assert len(ghosts) == len(moved)
        for ghost, m in zip(ghosts, moved, strict=True):
            assert data_centre(ghost) == pytest.approx(box_centre(boxes[prev, m]))
    # x-labels state each object's advance along its order (mod K) since the previous panel
    slot, k = np.asarray(scenes.slot[env]), np.asarray(scenes.num_slots[env])
    for ax, prev, now in zip(axes[1:], taus[:-1], taus[1:], strict=True):
        steps = np.mod(slot[now] - slot[prev], k)
        expected = [f"{c.name} stays" if s == 0 and now - prev == 1 else f"{c.name} +{s}"
                    for c, s in zip(config.categories, steps, strict=True)]
        assert ax.get_xlabel() == ", ".join(expected)


# ------------------------------------------------------------------------------------ orders

def test_draw_visit_orders_numbers_tables_in_order(scenes, config, tmp_path):
    env = 1
    fig = render.draw_visit_orders(scenes, env, config)
    assert_png(fig, tmp_path / "orders.png")
    axes = [ax for ax in fig.axes if by_gid(ax, "furniture")]
    assert len(axes) == config.num_objects
    boxes = np.asarray(scenes.furniture_boxes[env])
    for m, ax in enumerate(axes):
        k = int(scenes.num_slots[env, m])
        order = np.asarray(scenes.visit_order[env, m, :k])
        assert len(by_gid(ax, "order")) == k
        labels = by_gid(ax, "order_label")
        assert [t.get_text() for t in labels] == [str(i + 1) for i in range(k)]
        for text, f in zip(labels, order, strict=True):
            assert text.get_position() == pytest.approx(box_centre(boxes[f]))
        assert config.categories[m].name in ax.get_title()


# ------------------------------------------------------------------------------------ posterior

def test_draw_posterior_shades_by_probability(scenes, config, tmp_path):
    env, obj = 0, 1
    k = int(scenes.num_slots[env, obj])
    probs = np.zeros(scenes.furniture_boxes.shape[1])
    probs[:k] = np.linspace(1.0, 2.0, k) / np.linspace(1.0, 2.0, k).sum()
    fig = render.draw_posterior(scenes, env, obj, 2, probs, config)
    ax = fig.axes[0]
    shaded = by_gid(ax, "posterior")
    assert len(shaded) == k
    alphas = np.array([p.get_facecolor()[3] for p in shaded])
    assert alphas / alphas.max() == pytest.approx(probs[:k] / probs[:k].max())  # opacity ∝ p
    assert [t.get_text() for t in by_gid(ax, "posterior_label")] == [f"{p:.2f}" for p in probs[:k]]
    samples = np.array([[0.1, 0.2, 0.05, 0.05], [0.5, 0.5, 0.1, 0.2], [0.9, 0.1, 0.05, 0.05]])
    collection = render.overlay_boxes(ax, samples, config, edgecolor="orange")
    assert len(collection.get_paths()) == len(samples)
    first = collection.get_paths()[0].get_extents()
    scale = config.map_size - 1
    assert (first.x0, first.y0) == pytest.approx((0.2 * scale, 0.1 * scale))
    assert (first.width, first.height) == pytest.approx((0.05 * scale, 0.05 * scale))
    assert_png(fig, tmp_path / "posterior.png")


@pytest.mark.parametrize("probs, match", [
    (np.ones((2, 10)) / 20, r"probs must have shape \(\*,\)"),
    (np.array([0.5]), "probs must be a 1-D"),
    (np.array([0.5, -0.1, 0.6, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]), "non-negative"),
    (np.array([0.5, 0.3, 0.1, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.1]), "beyond"),
])
def test_draw_posterior_rejects_bad_probs(scenes, config, probs, match):
    with pytest.raises(ValueError, match=match):
        render.draw_posterior(scenes, 0, 0, 0, probs, config)


def test_overlay_boxes_rejects_bad_shape(config):
    from matplotlib.figure import Figure

    ax = Figure().add_subplot()
    with pytest.raises(ValueError, match="boxes_norm"):
        render.overlay_boxes(ax, np.zeros((3, 3)), config)
    with pytest.raises(ValueError, match="boxes_norm"):
        render.overlay_boxes(ax, np.full((1, 4), np.nan), config)


# ------------------------------------------------------------------------------------ bad input

@pytest.mark.parametrize("call, match", [
    (lambda s, c: render.draw_scene(s, 2, 0, c), "env"),
    (lambda s, c: render.draw_scene(s, -1, 0, c), "env"),
    (lambda s, c: render.draw_scene(s, 0.5, 0, c), "env"),
    (lambda s, c: render.draw_scene(s, True, 0, c), "env"),
    (lambda s, c: render.draw_scene(s, 0, NUM_TIMESTEPS, c), "tau"),
    (lambda s, c: render.draw_scene(s, 0, 0, c, highlight=3), "highlight"),
    (lambda s, c: render.draw_timeline(s, 0, [], c), "taus"),
    (lambda s, c: render.draw_timeline(s, 0, [2, 1], c), "taus"),
    (lambda s, c: render.draw_timeline(s, 0, [0, 99], c), "taus"),
    (lambda s, c: render.draw_timeline(s, 5, [0, 1], c), "env"),
    (lambda s, c: render.draw_timeline(s, 0, [0.5, 1], c), "taus"),
    (lambda s, c: render.draw_timeline(s, 0, "01", c), "taus"),
    (lambda s, c: render.draw_scene(s, 0, 0, c.to_dict()), "config"),
    (lambda s, c: render.draw_visit_orders({"slot": 0}, 0, c), "scenes"),
    (lambda s, c: render.draw_visit_orders(s, 7, c), "env"),
    (lambda s, c: render.draw_posterior(s, 0, 3, 0, np.ones(10) / 10, c), "obj"),
    (lambda s, c: render.draw_posterior(s, 0, 0, -2, np.ones(10) / 10, c), "tau"),
])
def test_bad_indices_raise_value_error(scenes, config, call, match):
    with pytest.raises(ValueError, match=match):
        call(scenes, config)


def test_scenes_from_another_config_are_refused(scenes, config):
    other = dataclasses.replace(config, categories=config.categories[:2])
    with pytest.raises(ValueError, match=r"config\.categories"):
        render.draw_scene(scenes, 0, 0, other)


# ------------------------------------------------------------------------------------ 4th category

def test_fourth_category_renders_from_data_only(tmp_path):
    mug = ObjectCategory("mug", 6, "orange", "star", "office_desk", "left_to_right")
    config = FlowSimConfig(num_timesteps=3, categories=(*FlowSimConfig().categories, mug))
    scenes = hand_built_scenes(config, num_envs=1)
    fig = render.draw_scene(scenes, 0, 1, config)
    ax = fig.axes[0]
    objects = by_gid(ax, "object")
    assert len(objects) == 4
    assert objects[3].get_facecolor() == pytest.approx(to_rgba("orange"))
    assert "mug" in [t.get_text() for t in ax.get_legend().get_texts()]
    orders = render.draw_visit_orders(scenes, 0, config)
    assert len([a for a in orders.axes if by_gid(a, "furniture")]) == 4
    assert_png(orders, tmp_path / "orders4.png")
