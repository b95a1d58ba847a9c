"""Model-facing views: normalised boxes, tokens, slot boxes, queries, train batches, splits,
the endless stream and .npz I/O."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest
from conftest import SMALL_NUM_ENVS

from flowmaps_jax import tokens as tok
from flowmaps_jax.flowsim import (
    denormalise_boxes,
    draw_query_times,
    load_scenes,
    make_train_batch,
    normalise_boxes,
    save_scenes,
    scene_tokens,
    slot_boxes,
    train_split,
    validation_split,
)
from flowmaps_jax.flowsim.scenes import FORMAT_VERSION


def test_normalise_round_trip_and_values(flowsim_config):
    px = np.array([[0.0, 0.0, 255.0, 255.0], [10.0, 20.0, 35.0, 84.0]])
    norm = np.asarray(normalise_boxes(px, flowsim_config))
    np.testing.assert_allclose(norm[0], [0, 0, 1, 1])
    np.testing.assert_allclose(norm[1], np.array([10, 20, 25, 64]) / 255)
    np.testing.assert_allclose(denormalise_boxes(norm, flowsim_config), px, atol=1e-4)
    with pytest.raises(ValueError, match="boxes_px"):
        normalise_boxes(np.zeros((3, 5)), flowsim_config)


def test_scene_tokens_content(small_scenes, flowsim_config):
    env, tau = np.array([0, 5, 7]), np.array([0, 9, 18])
    tokens = scene_tokens(small_scenes, env, tau, flowsim_config)
    tok.validate_tokens(tokens, flowsim_config.num_descriptors, max_tokens=20)
    f, m = 10, 3
    assert tokens.boxes.shape == (3, 20, 4)
    np.testing.assert_array_equal(tokens.mask[0], np.arange(20) < f + m)
    np.testing.assert_array_equal(tokens.kind[0, :f + m], [0] * f + [1] * m)
    np.testing.assert_array_equal(tokens.descriptor[1, f:f + m], [0, 1, 2])
    np.testing.assert_array_equal(tokens.descriptor[1, :f], small_scenes.furniture_kind[5])
    np.testing.assert_allclose(tokens.boxes[2, :f],
                               normalise_boxes(small_scenes.furniture_boxes[7], flowsim_config))
    np.testing.assert_allclose(tokens.boxes[2, f:f + m],
                               normalise_boxes(small_scenes.object_boxes[7, 18], flowsim_config))
    assert np.all(np.asarray(tokens.boxes)[:, f + m:] == 0)
    np.testing.assert_array_equal(tokens.tau, tau)


def test_scene_tokens_rejects_bad_input(small_scenes, flowsim_config):
    with pytest.raises(ValueError, match="max_tokens"):
        scene_tokens(small_scenes, np.array([0]), np.array([0]),
                     dataclasses.replace(flowsim_config, max_tokens=12))
    with pytest.raises(ValueError, match="env"):
        scene_tokens(small_scenes, np.array([SMALL_NUM_ENVS]), np.array([0]), flowsim_config)
    with pytest.raises(ValueError, match="tau"):
        scene_tokens(small_scenes, np.array([0]), np.array([20]), flowsim_config)
    with pytest.raises(ValueError, match="scenes"):
        scene_tokens({"boxes": 1}, np.array([0]), np.array([0]), flowsim_config)


def test_slot_boxes_match_object_boxes(small_scenes, flowsim_config):
    env = np.arange(SMALL_NUM_ENVS).repeat(3)
    obj = np.tile(np.arange(3), SMALL_NUM_ENVS)
    boxes = np.asarray(slot_boxes(small_scenes, env, obj, flowsim_config))  # (N, F, 4)
    slot = np.asarray(small_scenes.slot)[env, :, obj]  # (N, T)
    actual = np.asarray(normalise_boxes(small_scenes.object_boxes, flowsim_config))[env, :, obj]
    np.testing.assert_allclose(np.take_along_axis(boxes, slot[..., None], axis=1), actual,
                               atol=1e-6)
    k = np.asarray(small_scenes.num_slots)[env, obj]
    beyond = np.arange(10)[None, :] >= k[:, None]
    assert np.all(boxes[beyond] == 0) and np.all(boxes[~beyond][:, 2:] > 0)


def test_query_times_follow_the_papers_law(flowsim_config):
    tau, tau_q = jax.jit(lambda k: draw_query_times(k, (20_000,), (20_000,), flowsim_config))(
        jax.random.key(0))
    tau, tau_q = np.asarray(tau), np.asarray(tau_q)
    assert tau.min() == 0 and tau.max() == 18
    assert (tau_q > tau).all() and tau_q.max() == 19
    # tau is uniform over 0..18 and tau_q uniform over tau+1..19 (spot checks).
    assert abs(np.mean(tau == 0) - 1 / 19) < 0.01
    assert abs(np.mean(tau_q[tau == 17] == 18) - 0.5) < 0.1
    # one τ per scene shared by its queries; short horizons when asked
    tau, tau_q = draw_query_times(jax.random.key(1), (500,), (500, 4), flowsim_config, 1.0, 1)
    expected = np.broadcast_to(np.minimum(np.asarray(tau)[:, None] + 1, 19), (500, 4))
    np.testing.assert_array_equal(np.asarray(tau_q), expected)


def test_make_train_batch(small_scenes, flowsim_config):
    batch = make_train_batch(jax.random.key(1), small_scenes, 16, 4, flowsim_config)
    tok.check_train_batch(batch)
    assert batch.target.shape == (16, 4, 4) and batch.tokens.boxes.shape == (16, 20, 4)
    tok.validate_tokens(batch.tokens, flowsim_config.num_descriptors, max_tokens=20)
    tok.validate_queries(batch.queries, batch.tokens.tau, flowsim_config.num_descriptors, 20)
    # Each target is the queried object's box at tau_q in the scene the tokens come from:
    # find the scene by its furniture tokens, the object by its descriptor.
    furniture = np.asarray(normalise_boxes(small_scenes.furniture_boxes, flowsim_config))
    objects = np.asarray(normalise_boxes(small_scenes.object_boxes, flowsim_config))
    for b in range(16):
        match = np.all(np.abs(furniture - np.asarray(batch.tokens.boxes[b, :10])) < 1e-6,
                       axis=(1, 2))
        env = int(np.argmax(match))
        assert match[env]
        tau = int(batch.tokens.tau[b])
        np.testing.assert_allclose(batch.tokens.boxes[b, 10:13], objects[env, tau], atol=1e-6)
        for q in range(4):
            obj = int(batch.queries.descriptor[b, q])  # descriptor == object index here
            tau_q = int(batch.queries.tau_q[b, q])
            np.testing.assert_allclose(batch.target[b, q], objects[env, tau_q, obj], atol=1e-6)
    again = make_train_batch(jax.random.key(1), small_scenes, 16, 4, flowsim_config)
    np.testing.assert_array_equal(again.target, batch.target)
    with pytest.raises(ValueError, match="batch_size"):
        make_train_batch(jax.random.key(1), small_scenes, 0, 4, flowsim_config)
    with pytest.raises(ValueError, match="queries_per_scene"):
        make_train_batch(jax.random.key(1), small_scenes, 4, -1, flowsim_config)
    with pytest.raises(ValueError, match="key"):
        make_train_batch(5, small_scenes, 4, 2, flowsim_config)


def test_make_train_batch_under_jit(small_scenes, flowsim_config):
    fn = jax.jit(lambda key, scenes: make_train_batch(key, scenes, 8, 2, flowsim_config))
    batch = fn(jax.random.key(2), small_scenes)
    tok.check_train_batch(batch)


def test_splits_are_fixed_and_disjoint(flowsim_config):
    train = train_split(flowsim_config, num_envs=SMALL_NUM_ENVS)
    again = train_split(flowsim_config, num_envs=SMALL_NUM_ENVS)
    valid = validation_split(flowsim_config, num_envs=SMALL_NUM_ENVS)
    same_seed = validation_split(flowsim_config, num_envs=SMALL_NUM_ENVS, seed=0)
    np.testing.assert_array_equal(train.object_boxes, again.object_boxes)
    flat = {name: np.asarray(s.furniture_boxes).reshape(SMALL_NUM_ENVS, -1)
            for name, s in (("train", train), ("valid", valid), ("same_seed", same_seed))}
    rows = {name: {r.tobytes() for r in arr} for name, arr in flat.items()}
    assert not rows["train"] & rows["valid"]
    assert not rows["train"] & rows["same_seed"]


def test_npz_round_trip(tmp_path, small_scenes, flowsim_config):
    path = tmp_path / "scenes.npz"
    save_scenes(path, small_scenes, flowsim_config)
    loaded, config = load_scenes(path)
    assert config == flowsim_config
    for name, value in dataclasses.asdict(small_scenes).items():
        np.testing.assert_array_equal(np.asarray(getattr(loaded, name)), np.asarray(value))


def _rewrite(src, dst, drop=(), **replace):
    with np.load(src) as data:
        arrays = {k: data[k] for k in data.files if k not in drop}
    arrays.update(replace)
    np.savez(dst, **arrays)


def test_npz_refuses_broken_files(tmp_path, small_scenes, flowsim_config):
    good = tmp_path / "good.npz"
    save_scenes(good, small_scenes, flowsim_config)
    cases = {
        "old.npz": ({"format_version": np.int64(FORMAT_VERSION + 1)}, (),
                    "format_version must be one of"),
        "missing.npz": ({}, ("slot",), "missing arrays"),
        "noversion.npz": ({}, ("format_version",), "format_version"),
        "shape.npz": ({"slot": np.zeros((3, 3), np.int32)}, (), "slot must have shape"),
        "config.npz": ({"config_json": np.asarray('{"map_size": -5}')}, (), "invalid config"),
    }
    for name, (replace, drop, match) in cases.items():
        path = tmp_path / name
        _rewrite(good, path, drop=drop, **replace)
        with pytest.raises(ValueError, match=match) as err:
            load_scenes(path)
        assert name in str(err.value)
    junk = tmp_path / "junk.npz"
    junk.write_text("not a zip")
    with pytest.raises(ValueError, match="not a readable"):
        load_scenes(junk)
    with pytest.raises(ValueError, match="does not exist"):
        load_scenes(tmp_path / "absent.npz")
