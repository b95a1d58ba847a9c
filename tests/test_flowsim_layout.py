"""FlowSim layouts, visiting orders and object placement, checked on every generated
environment with vectorised numpy (hypothesis varies the numeric config; all examples share one
compiled ``generate`` because they keep the same shapes and number of environments)."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest
from conftest import SMALL_NUM_ENVS
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from flowmaps_jax.flowsim import FlowSimConfig, ObjectCategory, generate
from flowmaps_jax.flowsim.config import sim_params, sim_shape
from flowmaps_jax.flowsim.generate import scenes_from_env_keys

EXTRA = (ObjectCategory("cup", 6, "orange", "diamond", "office_desk", "left_to_right"),
         ObjectCategory("book", 7, "yellow", "star", "kitchen_table", "bottom_to_top"))


def angle(cy, cx, map_size):
    return np.mod(np.arctan2(cx - map_size / 2, -(cy - map_size / 2)), 2 * np.pi)


def order_keys(centres, ordering, map_size):
    cy, cx = centres[..., 0], centres[..., 1]
    return {"clockwise": angle(cy, cx, map_size), "counter_clockwise": -angle(cy, cx, map_size),
            "top_to_bottom": cy, "bottom_to_top": -cy, "left_to_right": cx}[ordering]


def check_scenes(scenes, config: FlowSimConfig) -> None:
    """Assert every invariant of FlowSim on all environments (vectorised)."""
    boxes = np.asarray(scenes.furniture_boxes)  # (E, F, 4)
    e, f = boxes.shape[:2]
    kind = np.asarray(scenes.furniture_kind)
    lo, hi = config.table_side_range
    # In bounds, integer sizes in range.
    assert boxes.min() >= 0 and boxes.max() <= config.map_size
    h, w = boxes[..., 2] - boxes[..., 0], boxes[..., 3] - boxes[..., 1]
    assert h.min() >= lo and h.max() <= hi and w.min() >= lo and w.max() <= hi
    # No two pieces overlap (touching allowed).
    a, b = boxes[:, :, None, :], boxes[:, None, :, :]
    overlap = ((a[..., 0] < b[..., 2]) & (b[..., 0] < a[..., 2])
               & (a[..., 1] < b[..., 3]) & (b[..., 1] < a[..., 3]))
    overlap &= ~np.eye(f, dtype=bool)
    assert not overlap.any(), f"{overlap.any(axis=(1, 2)).sum()} environments overlap"
    # Every kind has at least min_per_kind pieces (so every category has a table).
    for fk in config.furniture_kinds:
        assert (np.sum(kind == fk.descriptor, axis=1) >= config.min_per_kind).all()
    assert np.isin(kind, [fk.descriptor for fk in config.furniture_kinds]).all()

    centres = 0.5 * (boxes[..., :2] + boxes[..., 2:])
    order = np.asarray(scenes.visit_order)
    slots = np.asarray(scenes.num_slots)
    slot = np.asarray(scenes.slot)
    obj = np.asarray(scenes.object_boxes)
    size = np.asarray(scenes.object_size)
    rows = np.arange(e)[:, None]
    kind_ids = {fk.name: fk.descriptor for fk in config.furniture_kinds}
    for m, cat in enumerate(config.categories):
        want = kind == kind_ids[cat.furniture_kind]  # (E, F)
        assert (slots[:, m] == want.sum(axis=1)).all()
        valid = np.arange(f)[None, :] < slots[:, m, None]
        assert ((order[:, m] >= 0) == valid).all()
        # The order is a permutation of exactly the pieces of the right kind.
        visited = (order[:, m, :, None] == np.arange(f)).sum(axis=1)  # (E, F) visits per piece
        assert (visited == want).all()
        # Monotone keys along the order (the order is cyclic: it starts at the smallest key).
        key = order_keys(centres, cat.ordering, config.map_size)
        along = np.take_along_axis(key, np.maximum(order[:, m], 0), axis=1)
        step_ok = (np.diff(along, axis=1) >= -1e-4) | ~valid[:, 1:]
        assert step_ok.all(), f"{cat.name}: order not monotone ({cat.ordering})"
        # Objects: start at slot 0, slots in range, always on a table of their kind, centred.
        assert (slot[:, 0, m] == 0).all()
        assert (slot[:, :, m] >= 0).all() and (slot[:, :, m] < slots[:, m, None]).all()
        table = np.take_along_axis(order[:, m], slot[:, :, m], axis=1)  # (E, T)
        assert (kind[rows, table] == kind_ids[cat.furniture_kind]).all()
        np.testing.assert_allclose(0.5 * (obj[:, :, m, :2] + obj[:, :, m, 2:]),
                                   centres[rows, table], atol=1e-4)
        start = boxes[np.arange(e), order[:, m, 0]]
        side = np.minimum(start[:, 2] - start[:, 0], start[:, 3] - start[:, 1])
        expected = np.maximum(config.min_object_px, np.floor(config.object_frac * side))
        np.testing.assert_allclose(size[:, m], expected)
        assert obj[:, :, m].min() >= 0 and obj[:, :, m].max() <= config.map_size  # on the map
        for far, near in ((2, 0), (3, 1)):
            side = obj[:, :, m, far] - obj[:, :, m, near]
            np.testing.assert_allclose(side, np.broadcast_to(size[:, m, None], side.shape),
                                       atol=1e-4)
    assert (np.asarray(scenes.object_kind) == [c.descriptor for c in config.categories]).all()
    assert (np.asarray(scenes.layout_redraws) >= 0).all()


def test_default_scenes_are_valid(small_scenes, flowsim_config):
    check_scenes(small_scenes, flowsim_config)
    assert small_scenes.num_envs == SMALL_NUM_ENVS


def test_known_orderings_on_a_hand_made_layout():
    """The key functions themselves: four tables at 12, 3, 6 and 9 o'clock."""
    centres = np.array([[20.0, 128.0], [128.0, 236.0], [236.0, 128.0], [128.0, 20.0]])
    for ordering, expected in [("clockwise", [0, 1, 2, 3]), ("counter_clockwise", [3, 2, 1, 0]),
                               ("top_to_bottom", [0, 1, 3, 2]), ("left_to_right", [3, 0, 2, 1])]:
        got = np.argsort(order_keys(centres, ordering, 256), kind="stable")
        assert got.tolist() == expected, ordering


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(map_size=st.integers(160, 400), lo=st.floats(0.05, 0.12), hi=st.floats(0.12, 0.25),
       per_kind=st.integers(1, 3), object_share=st.floats(0.3, 0.95), min_px=st.integers(1, 8),
       seed=st.integers(0, 2**31 - 1))
def test_layouts_valid_for_random_configs(map_size, lo, hi, per_kind, object_share, min_px,
                                          seed):
    # object_frac up to the largest the config allows: objects no larger than the smallest table
    config = FlowSimConfig(map_size=map_size, table_min_frac=lo, table_max_frac=hi,
                           min_per_kind=per_kind, object_frac=object_share * lo / hi,
                           min_object_px=min_px)
    check_scenes(generate(jax.random.key(seed), SMALL_NUM_ENVS, config), config)


def test_more_categories_by_data_only():
    """A fourth and fifth category (with the two extra orderings) need no code change."""
    config = FlowSimConfig(categories=(*FlowSimConfig().categories, *EXTRA))
    scenes = generate(jax.random.key(3), SMALL_NUM_ENVS, config)
    assert scenes.object_boxes.shape == (SMALL_NUM_ENVS, 20, 5, 4)
    check_scenes(scenes, config)


def test_determinism_by_key(small_scenes, flowsim_config):
    again = generate(jax.random.key(0), SMALL_NUM_ENVS, flowsim_config)
    for name, value in dataclasses.asdict(small_scenes).items():
        np.testing.assert_array_equal(np.asarray(value), np.asarray(getattr(again, name)), name)
    other = generate(jax.random.key(1), SMALL_NUM_ENVS, flowsim_config)
    assert not np.array_equal(other.furniture_boxes, small_scenes.furniture_boxes)
    legacy = generate(jax.random.PRNGKey(0), SMALL_NUM_ENVS, flowsim_config)
    assert legacy.furniture_boxes.shape == small_scenes.furniture_boxes.shape


def test_vectorised_equals_loop_over_environments(small_scenes, flowsim_config):
    """Environment e depends only on its own key: one environment at a time (a Python loop
    over single-environment calls) reproduces rows of the vectorised batch."""
    env_keys = jax.random.split(jax.random.key(0), SMALL_NUM_ENVS)
    params, shape = sim_params(flowsim_config), sim_shape(flowsim_config)
    redrawn = int(np.argmax(np.asarray(small_scenes.layout_redraws) > 0))
    for e in (0, 1, redrawn):
        single, ok = scenes_from_env_keys(env_keys[e:e + 1], params, shape)
        assert bool(ok[0])
        for name, value in dataclasses.asdict(single).items():
            np.testing.assert_array_equal(np.asarray(value)[0],
                                          np.asarray(getattr(small_scenes, name))[e], name)


def test_small_requests_share_one_program_and_are_their_own_rows(small_scenes,
                                                                 flowsim_config):
    """Fewer than SMALL_REQUEST environments are computed as that many and cut back: one
    compiled program for every small size, and the rows are the request's own, bit for bit."""
    compiled = scenes_from_env_keys._cache_size()
    for n in (1, 2, 5):
        scenes = generate(jax.random.key(0), n, flowsim_config)
        for field in dataclasses.fields(scenes):  # (asdict would deep-copy every array)
            value = getattr(scenes, field.name)
            assert not value.committed, field.name  # as a program's output: no new programs
            np.testing.assert_array_equal(np.asarray(value), np.asarray(
                getattr(small_scenes, field.name))[:n], field.name)
    assert scenes_from_env_keys._cache_size() - compiled <= 1


def test_some_layouts_are_redrawn_and_counted(small_scenes):
    redraws = np.asarray(small_scenes.layout_redraws)
    assert 0 < np.mean(redraws > 0) < 0.5


def test_exhausted_budget_raises(flowsim_config):
    crowded = FlowSimConfig(table_min_frac=0.24, table_max_frac=0.25, layout_budget=2)
    with pytest.raises(RuntimeError, match="layout_budget"):
        generate(jax.random.key(0), SMALL_NUM_ENVS, crowded)


@pytest.mark.parametrize(("args", "match"), [
    ((jax.random.key(0), 0), "num_envs"),
    ((jax.random.key(0), 2.5), "num_envs"),
    ((jax.random.split(jax.random.key(0), 2), 4), "key"),
    ((7, 4), "key"),
])
def test_bad_arguments_raise(args, match):
    with pytest.raises(ValueError, match=match):
        generate(*args)
    with pytest.raises(ValueError, match="config"):
        generate(jax.random.key(0), 4, config={"map_size": 256})
