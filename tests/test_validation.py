"""The shared checks of ``flowmaps_jax.validation`` and the issue-12 inputs they now refuse in
the simulator, the tokens and the scene files. No JAX compilation beyond the session's scenes."""

from __future__ import annotations

import json
import math
import os
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from flowmaps_jax import boxes, resources, tokens
from flowmaps_jax import validation as v
from flowmaps_jax.flowsim import (
    FlowSimConfig,
    Scenes,
    load_scenes,
    save_scenes,
    scene_tokens,
)

# ------------------------------------------------------------------------------ scalars


@pytest.mark.parametrize("value", [True, np.bool_(False), 2.0, "3", None, 1 + 0j, [1]])
def test_check_int_refuses_non_ints(value):
    with pytest.raises(ValueError, match="count must be an int"):
        v.check_int("count", value)


def test_check_int_accepts_numpy_and_bounds():
    assert v.check_int("n", np.int64(4)) == 4 and type(v.check_int("n", np.int64(4))) is int
    assert v.check_int("n", np.array(3)) == 3
    assert v.check_int("n", -5, None) == -5
    with pytest.raises(ValueError, match=r"n must be an int in 0\.\.9; got 10"):
        v.check_int("n", 10, 0, 9)


@pytest.mark.parametrize("value", [True, 1j, "0.1", None, math.nan, math.inf, -math.inf,
                                   10**400, [0.5]])
def test_check_real_refuses(value):
    with pytest.raises(ValueError, match="lr must be a finite real number"):
        v.check_real("lr", value)


def test_check_real_bounds_and_numpy():
    assert v.check_real("p", np.float32(0.5), 0, 1) == 0.5
    assert v.check_real("p", 1, 0, 1) == 1.0
    assert v.check_real("p", jnp.float32(0.25)) == 0.25
    with pytest.raises(ValueError, match=r"lr must be > 0"):
        v.check_real("lr", 0.0, 0.0, low_open=True)
    with pytest.raises(ValueError, match=r"p must be in \[0, 1\]"):
        v.check_real("p", 1.5, 0, 1)


def test_flags_choices_instances_seeds():
    assert v.check_flag("pixels", np.bool_(True)) is True
    for bad in ("yes", 1, None):
        with pytest.raises(ValueError, match="pixels must be True or False"):
            v.check_flag("pixels", bad)
    assert v.check_choice("method", "euler", ("euler", "midpoint")) == "euler"
    for bad in ("heun", None, 1):
        with pytest.raises(ValueError, match="method must be one of"):
            v.check_choice("method", bad, ("euler", "midpoint"))
    with pytest.raises(ValueError, match="must be one of"):
        v.check_choice("flag", True, (0, 1))
    with pytest.raises(ValueError, match="config must be a FlowSimConfig; got dict"):
        v.check_instance("config", {}, FlowSimConfig)
    assert v.check_seed("seed", 2**32 - 1) == 2**32 - 1
    for bad in (2**32, -1, 99999999999999999999, 1.0):
        with pytest.raises(ValueError, match=r"seed must be an int in 0\.\.4294967295"):
            v.check_seed("seed", bad)


def test_check_key_typed_and_raw():
    typed = v.check_key(jax.random.PRNGKey(3))
    assert jnp.issubdtype(typed.dtype, jax.dtypes.prng_key)
    np.testing.assert_array_equal(jax.random.key_data(typed),
                                  jax.random.key_data(jax.random.key(3)))
    keys = jax.random.split(jax.random.key(0), 4)
    assert v.check_key(keys, shapes=((), (4,))) is keys
    with pytest.raises(ValueError, match=r"key must be a key array of shape \(\)"):
        v.check_key(keys)
    for bad in (7, np.zeros(2, np.int32), np.zeros(3, np.uint32), "key"):
        with pytest.raises(ValueError, match="key must be a JAX PRNG key"):
            v.check_key(bad)


# ------------------------------------------------------------------------------ arrays


@pytest.mark.parametrize(("value", "words"), [
    (np.array([True, False]), "booleans"), (np.array([1 + 2j]), "complex numbers"),
    (np.array(["0.5"]), "strings"), (np.array([None]), "Python objects"),
    ("0.5", "numeric array"), ([[1.0], [1.0, 2.0]], "numeric array"), (None, "numeric array"),
])
def test_real_arrays_name_the_dtype(value, words):
    with pytest.raises(ValueError, match=f"boxes .*{words}"):
        v.check_real_array("boxes", value)


def test_real_array_shapes_and_finiteness():
    assert v.check_real_array("b", [[0, 1, 2, 3]], (..., 4)).shape == (1, 4)
    with pytest.raises(ValueError, match=r"b must have shape \(\.\.\., 4\); got \(2, 3\)"):
        v.check_real_array("b", np.zeros((2, 3)), (..., 4))
    with pytest.raises(ValueError, match="b contains NaN or inf"):
        v.check_real_array("b", [0.0, math.nan])
    assert np.isnan(v.check_real_array("b", [math.nan], finite=False)).all()
    with pytest.raises(ValueError, match="must be an array"):
        v.check_array("tokens.mask", [True, False])


def test_int_arrays():
    with pytest.raises(ValueError, match="slot must hold integers; got dtype float64"):
        v.check_int_array("slot", np.array([1.0]))
    with pytest.raises(ValueError, match="slot must hold integers; got booleans"):
        v.check_int_array("slot", np.array([True]))
    with pytest.raises(ValueError, match=r"tau must lie in 0\.\.19; got values in 0\.\.20"):
        v.check_int_array("tau", [0, 20], 0, 19)
    with pytest.raises(ValueError, match=r"slot must lie in 0\.\.num_slots - 1"):
        v.check_int_array("slot", [2, 2], 0, np.array([3, 2]) - 1, high_name="num_slots - 1")
    with pytest.raises(ValueError, match="does not broadcast"):
        v.check_int_array("slot", [0, 0, 0], 0, np.array([3, 2]))
    # Under jit the dtype is checked, the values are not (they are unknown).
    jax.jit(lambda x: v.check_int_array("x", x, 0, 1))(jnp.arange(5))
    with pytest.raises(ValueError, match="x must hold integers"):
        jax.jit(lambda x: v.check_int_array("x", x, 0, 1))(jnp.ones(3))


def test_masks():
    np.testing.assert_array_equal(v.check_mask("mask", [1.0, 0.0]), [True, False])
    for bad in ([0.5, 1.0], [2, 0], np.array([1 + 0j])):
        with pytest.raises(ValueError, match="mask"):
            v.check_mask("mask", bad)


def test_probabilities_name_the_problem():
    np.testing.assert_allclose(v.check_probabilities("p", np.float32([0.2, 0.7, 0.1])),
                               [0.2, 0.7, 0.1], atol=1e-7)
    cases = [(("0.2", 0.7, 0.1), "p must be real numbers"),
             ((True, 0.0, 0.0), "p must be real numbers"),
             (np.array(["0.2", "0.8"]), "p must hold real numbers; got strings"),
             ((0.5, -0.1, 0.6), "non-negative"), ((0.5, math.nan, 0.5), "NaN"),
             ((0.2, 0.2, 0.2), "must sum to 1")]
    for probs, match in cases:
        with pytest.raises(ValueError, match=match):
            v.check_probabilities("p", probs)
    assert v.check_probabilities("p", [0.5, 2.0], normalised=False).sum() == 2.5


@pytest.mark.parametrize("probs, total", [([0.5, 0.500002], "1.000002"),
                                          ([0.5, 0.4999985], "0.9999985"),
                                          (np.float32([0.5, 0.5000015]), "1.0000014")])
def test_a_sum_off_by_more_than_the_tolerance_is_not_printed_as_1(probs, total):
    """'must sum to 1; found a sum of 1': the sum was rounded to 6 digits."""
    with pytest.raises(ValueError, match=rf"must sum to 1 \(within 1e-06\); found a sum of "
                                         rf"{re.escape(total)}"):
        v.check_probabilities("p", probs)
    from flowmaps_jax.evaluation.receptacle_scores import check_reference

    with pytest.raises(ValueError, match=r"sums to 1\.0000004\d*, not 1"):
        check_reference(np.float64([[0.5, 0.5000004]]), tolerance=1e-7)


@pytest.mark.parametrize("command, argv, bad", [
    ("evaluate", ["--checkpoint", "x", "--num-envs", "{}"], "\u0662"),
    ("evaluate", ["--checkpoint", "x", "--seed", "{}"], "1_0"),
    ("search", ["--checkpoint", "x", "--budget", "{}"], "\uff13"),
    ("search", ["--checkpoint", "x", "--p-miss", "{}"], "\u0660.5"),
    ("train", ["--steps", "{}"], "\u0662"),
    ("data", ["from-homes", "--homes", "{}", "--out", "x"], "\u0662"),
    ("data", ["from-homes", "--homes", "2", "--mask", "{}", "--out", "x"], "\u0660.3")])
def test_number_flags_take_ascii_digits_only(command, argv, bad, capsys):
    """``--num-envs \u0662`` was read as 2 (Python's int reads every script's digits)."""
    import importlib

    module = {"evaluate": "evaluation.cli", "search": "search.cli", "train": "training.cli",
              "data": "data.__main__"}[command]
    parser = importlib.import_module(f"flowmaps_jax.{module}").build_parser()
    flag = argv[argv.index("{}") - 1]
    with pytest.raises(SystemExit) as info:
        parser.parse_args([a.format(bad) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert info.value.code == 2 and f"argument {flag}: expected a" in err, err
    assert "(ASCII digits)" in err
    parser.parse_args([a.format("0") for a in argv])  # ASCII digits are still read


# ------------------------------------------------------------------------------ files


def test_paths(tmp_path):
    for bad in (None, 123, b"x", ""):
        with pytest.raises(ValueError, match="path must be a"):
            v.check_path("path", bad)
    with pytest.raises(ValueError, match="is a directory, not a file"):
        v.check_file("path", tmp_path)
    with pytest.raises(ValueError, match="does not exist"):
        v.check_file("path", tmp_path / "absent")
    a_file = tmp_path / "file.txt"
    a_file.write_text("x")
    assert v.check_file("path", a_file) == str(a_file)
    assert v.check_output_file("out", a_file) == str(a_file)
    with pytest.raises(ValueError, match="already exists"):
        v.check_output_file("out", a_file, overwrite=False)
    with pytest.raises(ValueError, match="is a directory"):
        v.check_output_file("out", tmp_path)
    with pytest.raises(ValueError, match="does not exist"):
        v.check_output_file("out", tmp_path / "missing" / "x.npz")
    with pytest.raises(ValueError, match="is not a directory"):
        v.check_output_file("out", a_file / "x.npz")
    assert v.check_dir("checkpoint_dir", tmp_path) == str(tmp_path)
    with pytest.raises(ValueError, match="is a file, not a directory"):
        v.check_dir("checkpoint_dir", a_file)
    with pytest.raises(ValueError, match="does not exist"):
        v.check_dir("checkpoint_dir", tmp_path / "absent")
    assert v.check_output_dir("run_dir", tmp_path / "new" / "deeper")
    with pytest.raises(ValueError, match="is a file, not a directory"):
        v.check_output_dir("run_dir", a_file)
    with pytest.raises(ValueError, match=r"lies under .*, which is a file"):
        v.check_output_dir("run_dir", a_file / "run")
    with pytest.raises(ValueError, match="is not empty"):
        v.check_output_dir("run_dir", tmp_path, empty=True)
    if os.geteuid() != 0:  # root may write anywhere
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        with pytest.raises(ValueError, match="not writable"):
            v.check_output_dir("run_dir", locked / "run")


def test_request_size():
    assert resources.array_bytes((10**7, 4)) == 1.6e8
    assert resources.check_request_size("x", 100, limit=1000) == 100
    with pytest.raises(ValueError, match=r"sample\(N=10\*\*9\) would need about 36 GB"):
        resources.check_request_size("sample(N=10**9)", 36 * 10**9, limit=16 * 10**9)
    assert resources.memory_limit() > 2**28


# ------------------------------------------------------------------------------ boxes


def test_box_geometry_has_one_home():
    # boxes is the one home of the box geometry: tokens no longer re-exports it
    assert not hasattr(tokens, "to_centre") and not hasattr(tokens, "from_centre")
    b = np.array([[0.1, 0.2, 0.3, 0.4]], np.float32)
    np.testing.assert_allclose(boxes.from_centre(boxes.to_centre(b)), b, atol=1e-7)
    px = np.array([[10.0, 20.0, 35.0, 84.0]], np.float32)
    np.testing.assert_allclose(boxes.denormalise(boxes.normalise(px, 256), 256), px, atol=1e-4)
    np.testing.assert_allclose(boxes.corner_centres(px), [[22.5, 52.0]])
    np.testing.assert_allclose(boxes.centred_squares(np.array([5.0, 6.0]), 1.0), [4, 5, 6, 7])


# ------------------------------------------------------------------------------ FlowSimConfig


@pytest.mark.parametrize("map_size", [10, 12, 16, 20, 49])
def test_maps_too_small_for_their_objects_are_refused(map_size):
    with pytest.raises(ValueError, match=r"objects would leave the map.*map_size >= 50"):
        FlowSimConfig(map_size=map_size)
    FlowSimConfig(map_size=50)  # the smallest map the paper's fractions allow


def test_configs_that_cannot_make_scenes_are_refused():
    with pytest.raises(ValueError, match="objects would leave the map"):
        FlowSimConfig(object_frac=0.5)  # 32 px objects on tables as small as 25 px
    with pytest.raises(ValueError, match="objects would leave the map"):
        FlowSimConfig(min_object_px=26)
    # One table per kind: objects never move, so only min_object_px can exceed a table.
    FlowSimConfig(min_per_kind=1, num_furniture=3, object_frac=1.0)
    with pytest.raises(ValueError, match="max_tokens=12 is smaller than the 13 tokens"):
        FlowSimConfig(max_tokens=12)
    with pytest.raises(ValueError, match=r"layout_budget must be an int in 1\.\.2147483647"):
        FlowSimConfig(layout_budget=2**40)


def test_config_types_are_named_and_numpy_numbers_normalised():
    c = FlowSimConfig(map_size=np.int64(256), object_frac=np.float64(0.4),
                      transition_probs=(np.float32(0.2), np.float32(0.7), np.float32(0.1)))
    assert type(c.map_size) is int and type(c.transition_probs[0]) is float
    json.dumps(c.to_dict())  # JSON-able
    assert FlowSimConfig(transition_probs=[0.2, 0.7, 0.1]) == FlowSimConfig()
    with pytest.raises(ValueError, match="transition_probs must be real numbers"):
        FlowSimConfig(transition_probs=("0.2", "0.7", "0.1"))
    with pytest.raises(ValueError, match="table_min_frac must be a finite real number"):
        FlowSimConfig(table_min_frac=True)
    with pytest.raises(ValueError, match="object_frac must be a finite real number"):
        FlowSimConfig(object_frac=0.4 + 0j)
    assert FlowSimConfig().object_descriptors == (0, 1, 2)


# ------------------------------------------------------------------------------ tokens


@pytest.fixture(scope="module")
def good_tokens(small_scenes, flowsim_config):
    t = scene_tokens(small_scenes, np.arange(3), np.array([0, 5, 9]), flowsim_config)
    return jax.tree_util.tree_map(np.asarray, t)


@pytest.mark.parametrize(("field", "make", "match"), [
    ("boxes", lambda a: a > 0.5, "tokens.boxes must hold real numbers; got booleans"),
    ("boxes", lambda a: a + 0j, "tokens.boxes must hold real numbers; got complex numbers"),
    ("boxes", lambda a: a.astype(str), "tokens.boxes must hold real numbers; got strings"),
    ("boxes", lambda a: a.tolist(), "tokens.boxes must be an array"),
    ("mask", lambda a: a.tolist(), "tokens.mask must be an array"),
    ("mask", lambda a: a * 0.5, "tokens.mask must hold only 0/1"),
    ("mask", lambda a: a.astype(np.int32) * 2, "tokens.mask must hold only 0/1"),
    ("kind", lambda a: a.astype(float), "tokens.kind must hold integers"),
    ("tau", lambda a: a.astype(float), "tokens.tau must hold integers"),
    ("descriptor", lambda a: a[:, :-1], "tokens.descriptor must have shape"),
])
def test_malformed_tokens(good_tokens, field, make, match):
    tokens.validate_tokens(good_tokens, 6, max_tokens=20, num_timesteps=20)
    bad = good_tokens.replace(**{field: make(getattr(good_tokens, field))})
    with pytest.raises(ValueError, match=match):
        tokens.validate_tokens(bad, 6)
    with pytest.raises(ValueError, match=r"tokens\.tau must lie in 0\.\.3"):
        tokens.validate_tokens(good_tokens, 6, num_timesteps=5)


def test_a_query_names_an_object_not_a_table(good_tokens, flowsim_config):
    table = tokens.Queries(descriptor=np.full((3, 1), 3), tau_q=np.full((3, 1), 19))
    tokens.validate_queries(table, good_tokens.tau, 6, 20)  # a known id: fine without roles
    with pytest.raises(ValueError, match=r"must name object categories \[0, 1, 2\]; got \[3\]"):
        tokens.validate_queries(table, good_tokens.tau, 6, 20,
                                object_descriptors=flowsim_config.object_descriptors)
    with pytest.raises(ValueError, match=r"queries\.tau_q must hold integers"):
        tokens.validate_queries(table.replace(tau_q=np.full((3, 1), 19.0)), good_tokens.tau,
                                6, 20)


# ------------------------------------------------------------------------------ scene files


@pytest.fixture(scope="module")
def saved(tmp_path_factory, small_scenes, flowsim_config):
    path = tmp_path_factory.mktemp("scenes") / "good.npz"
    save_scenes(path, small_scenes, flowsim_config)
    return path


def _set(array, index, value, dtype=None):
    out = np.array(array, dtype=dtype)
    out[index] = value
    return out


TAMPERED = {
    "slot out of range": ("slot", lambda a: _set(a, (0, 3, 1), 9), "slot must lie in"),
    "negative slot": ("slot", lambda a: _set(a, (0, 3, 1), -1), "slot must lie in"),
    "float slots": ("slot", lambda a: a.astype(np.float32), "slot must hold integers"),
    "NaN box": ("furniture_boxes", lambda a: _set(a, (1, 2, 0), np.nan), "NaN"),
    "negative box": ("object_boxes", lambda a: _set(a, (1, 2, 0, 0), -3.0), "within the map"),
    "box off the map": ("furniture_boxes", lambda a: _set(a, (0, 0, 2), 300.0),
                        "within the map"),
    "empty box": ("furniture_boxes", lambda a: _set(a, (0, 0, 2), a[0, 0, 0]), "y1 > y0"),
    "bool boxes": ("object_boxes", lambda a: a > 100, "object_boxes must hold real numbers"),
    "unknown kind": ("furniture_kind", lambda a: a + 10, "descriptor ids outside"),
    "visit order": ("visit_order", lambda a: _set(a, (0, 0, -1), 3), "visit_order"),
    "num_slots": ("num_slots", lambda a: _set(a, (0, 0), 11), "num_slots must lie in 1..10"),
    "zero size": ("object_size", lambda a: _set(a, (0, 0), 0.0), "object_size must be positive"),
    "redraws": ("layout_redraws", lambda a: _set(a, 0, -1), "layout_redraws must lie"),
    "shape": ("object_kind", lambda a: a[:, :2],
              r"object_kind must have shape \(\d+, 3\); got \(\d+, 2\)"),
    "version": ("format_version", lambda a: np.asarray("1"), "format_version must be an int"),
}


@pytest.mark.parametrize("case", list(TAMPERED))
def test_load_scenes_checks_every_array_and_names_the_file(saved, tmp_path, case):
    field, make, match = TAMPERED[case]
    with np.load(saved) as data:
        arrays = {k: data[k] for k in data.files}
    arrays[field] = make(arrays[field])
    path = tmp_path / "tampered.npz"
    np.savez(path, **arrays)
    with pytest.raises(ValueError, match=match) as err:
        load_scenes(path)
    assert "tampered.npz" in str(err.value)


def test_scene_file_paths(tmp_path, small_scenes, flowsim_config, saved):
    with pytest.raises(ValueError, match="is a directory, not a file"):
        load_scenes(tmp_path)
    for bad in (None, 123):
        with pytest.raises(ValueError, match="path must be a path"):
            load_scenes(bad)
    with pytest.raises(ValueError, match="is a directory"):
        save_scenes(tmp_path, small_scenes, flowsim_config)
    with pytest.raises(ValueError, match="does not exist"):
        save_scenes(tmp_path / "missing" / "scenes.npz", small_scenes, flowsim_config)
    # A refused save leaves an existing file as it was, and no partial file behind.
    target = tmp_path / "keep.npz"
    target.write_bytes(b"old")
    broken = small_scenes.replace(slot=np.asarray(small_scenes.slot) + 50)
    with pytest.raises(ValueError, match="slot must lie in"):
        save_scenes(target, broken, flowsim_config)
    assert target.read_bytes() == b"old" and os.listdir(tmp_path) == ["keep.npz"]
    loaded, config = load_scenes(saved)
    assert config == flowsim_config and isinstance(loaded, Scenes)
    assert loaded.slot.dtype == jnp.int32 and loaded.object_boxes.dtype == jnp.float32


def test_shapes_are_ints_none_or_a_leading_ellipsis():
    v.check_shape("q", (2, 3), (2, 3))
    v.check_shape("q", (2, 3), (None, 3))
    v.check_shape("q", (5, 2, 3), (..., 3))
    v.check_shape("q", (3,), (..., 3))
    v.check_shape("q", (2, 3), None)
    with pytest.raises(ValueError, match=r"^p_hat must have shape \(2, 4\) \(one more than q\); "
                                         r"got \(2, 3\)$"):
        v.check_shape("p_hat", (2, 3), (2, 4), "one more than q")
    with pytest.raises(ValueError, match=r"q must have shape \(\*, 3\); got \(3,\)"):
        v.check_shape("q", (3,), (None, 3))
    with pytest.raises(ValueError, match=r"q must have shape \(\.\.\., 3\); got \(3, 2\)"):
        v.check_shape("q", (3, 2), (..., 3))


def test_real_array_bounds_name_the_argument_and_the_range():
    from flowmaps_jax.validation import check_real_array

    assert check_real_array("boxes", np.array([0.0, 1.0]), low=0, high=1).shape == (2,)
    with pytest.raises(ValueError, match=r"boxes must lie in \[0, 1\] \(normalised\)"):
        check_real_array("boxes", np.array([0.5, 1.5]), low=0, high=1, what="normalised")


def test_mixture_and_table_checks():
    import dataclasses

    from flowmaps_jax.validation.fields import Int, Text

    assert v.check_mixture("habits", [("b", 0.25), ("a", 0.75)], ("a", "b"), "habit") == (
        ("b", 0.25), ("a", 0.75))
    for bad, match in ((3, "pairs"), ((("c", 1.0),), "habit name"),
                       ((("a", 0.5), ("a", 0.5)), "named twice"),
                       ((("a", 0.5), ("b", 0.4)), " probabilities must sum")):
        with pytest.raises(ValueError, match=f"^habits.*{match}"):
            v.check_mixture("habits", bad, ("a", "b"), "habit")

    @dataclasses.dataclass(frozen=True)
    class Kind:
        name: str
        descriptor: int

    @dataclasses.dataclass(frozen=True)
    class Cat:
        name: str
        descriptor: int
        kind: str

    entry = {"name": Text(), "descriptor": Int(0)}
    kinds = v.check_table("kinds", (Kind("k", np.int64(1)),), Kind, entry,
                          unique=("name", "descriptor"))
    assert type(kinds[0].descriptor) is int

    def cats(value):
        return v.check_table("cats", value, Cat, entry, unique=("name", "descriptor"),
                             earlier=kinds, refers=("kind",), labels={"kind": "sits on kind"})

    assert cats((Cat("c", 0, "k"),)) == (Cat("c", 0, "k"),)
    for value, match in (((Cat("c", 1, "k"),), "cats: descriptor 1 is used twice"),
                         ((Cat("k", 0, "k"),), "cats: name 'k' is used twice"),
                         ((Cat("c", 0, "sofa"),), "cats: 'c' sits on kind must be one of"),
                         ((Cat("c", -1, "k"),), "cats: 'c' descriptor must be"),
                         ((), "cats must be a non-empty tuple of Cat"),
                         ((Kind("k", 0),), "cats entries must be a Cat")):
        with pytest.raises(ValueError, match=match):
            cats(value)


def test_a_config_table_takes_rules_or_plain_checks():
    import types

    from flowmaps_jax.validation.fields import Int, Optional

    rules = {"steps": Int(1, 10, why="a test"), "seed": v.check_seed, "flag": v.check_flag,
             "name": Optional(v.check_plain_name)}
    config = types.SimpleNamespace(steps=np.int64(3), seed=7, flag=np.bool_(True), name=None)
    assert v.check_fields(config, rules, store=False) == {"steps": 3, "seed": 7, "flag": True,
                                                          "name": None}
    assert type(config.steps) is int and type(config.flag) is bool  # numpy numbers replaced
    for field, value, match in (("steps", 11, r"^steps must be <= 10 \(a test\); got 11$"),
                                ("seed", -1, "^seed must be an int in"),
                                ("flag", 1, "^flag must be True or False"),
                                ("name", "a/b", "^name ")):
        with pytest.raises(ValueError, match=match):
            v.check_fields(types.SimpleNamespace(**{**vars(config), field: value}), rules)


def test_warmup_steps_are_below_steps():
    from flowmaps_jax.training.config import TrainConfig

    assert TrainConfig(steps=10, warmup_steps=np.int64(9)).warmup_steps == 9
    assert type(TrainConfig(steps=10, warmup_steps=np.int64(9)).warmup_steps) is int
    with pytest.raises(ValueError, match=r"^warmup_steps must be an int in 0\.\.steps-1 "
                                         r"\(steps = 10\); got 10$"):
        TrainConfig(steps=10, warmup_steps=10)
    with pytest.raises(ValueError, match=r"^warmup_steps must be an int >= 0"):
        TrainConfig(steps=10, warmup_steps=-1)
