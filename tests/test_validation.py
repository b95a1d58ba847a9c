"""The shared checks of ``flowmaps_jax.validation`` and the issue-12 inputs they now refuse in
the simulator, the tokens and the scene files. No JAX compilation beyond the session's scenes."""

from __future__ import annotations

import json
import math
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from flowmaps_jax import boxes, tokens
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
    assert v.array_bytes((10**7, 4)) == 1.6e8
    assert v.check_request_size("x", 100, limit=1000) == 100
    with pytest.raises(ValueError, match=r"sample\(N=10\*\*9\) would need about 36 GB"):
        v.check_request_size("sample(N=10**9)", 36 * 10**9, limit=16 * 10**9)
    assert v.memory_limit() > 2**28


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


def test_named_sizes_must_agree_across_the_arguments_of_one_check():
    from flowmaps_jax.validation.fields import Distribution, Int, IntArray, Mask, check_args

    @check_args(q=Distribution(("*B", "K")), p_hat=Distribution(("*B", "K+1"), support="mask"),
                mask=Mask(("*B", "K")))
    def score(q, mask, p_hat):
        return q.shape

    q = np.full((2, 3), 1 / 3)
    mask = np.ones((2, 3), bool)
    assert score(q, mask, np.full((2, 4), 0.25)) == (2, 3)
    with pytest.raises(ValueError, match=r"p_hat must have shape \(\*B, K\+1\) with K = 3 "
                                         r"\(from q\); got \(2, 3\)"):
        score(q, mask, np.full((2, 3), 1 / 3))
    with pytest.raises(ValueError, match=r"mask must have shape .* with \*B = \(2,\) \(from q\)"):
        score(q, np.ones((1, 3), bool), np.full((2, 4), 0.25))
    with pytest.raises(ValueError, match="p_hat puts probability where mask is False"):
        score(q, np.array([[1, 1, 0], [1, 1, 1]], bool), np.full((2, 4), 0.25))

    @check_args(num_slots=Int(size="K"), slot_now=IntArray(0, "K-1"))
    def last_seen(slot_now, num_slots):
        return num_slots

    assert last_seen(np.array([0, 2]), 3) == 3
    with pytest.raises(ValueError, match=r"slot_now must lie in 0..K-1; got values in 0..3"):
        last_seen(np.array([0, 3]), 3)


def test_real_array_bounds_name_the_argument_and_the_range():
    from flowmaps_jax.validation import check_real_array

    assert check_real_array("boxes", np.array([0.0, 1.0]), low=0, high=1).shape == (2,)
    with pytest.raises(ValueError, match=r"boxes must lie in \[0, 1\] \(normalised\)"):
        check_real_array("boxes", np.array([0.5, 1.5]), low=0, high=1, what="normalised")


def test_mixture_and_table_rules():
    import dataclasses

    from flowmaps_jax.validation.composite import Mixture, Table
    from flowmaps_jax.validation.fields import Int, Text, check_fields

    mix = Mixture(("a", "b"), "habit")
    assert mix("habits", [("b", 0.25), ("a", 0.75)]) == (("b", 0.25), ("a", 0.75))
    for bad, match in ((3, "pairs"), ((("c", 1.0),), "habit name"),
                       ((("a", 0.5), ("a", 0.5)), "named twice"),
                       ((("a", 0.5), ("b", 0.4)), " probabilities must sum")):
        with pytest.raises(ValueError, match=f"^habits.*{match}"):
            mix("habits", bad)

    @dataclasses.dataclass(frozen=True)
    class Kind:
        name: str
        descriptor: int

    @dataclasses.dataclass(frozen=True)
    class Cat:
        name: str
        descriptor: int
        kind: str

    @dataclasses.dataclass
    class Cfg:
        kinds: tuple
        cats: tuple

    entry = {"name": Text(), "descriptor": Int(0)}
    rules = {"kinds": Table(Kind, entry, unique=("name", "descriptor")),
             "cats": Table(Cat, entry, unique=("name", "descriptor"), after="kinds",
                           refers=("kind",), labels={"kind": "sits on kind"})}
    cfg = Cfg((Kind("k", np.int64(1)),), (Cat("c", 0, "k"),))
    check_fields(cfg, rules)
    assert type(cfg.kinds[0].descriptor) is int and cfg.cats == (Cat("c", 0, "k"),)
    for cats, match in (((Cat("c", 1, "k"),), "cats: descriptor 1 is used twice"),
                        ((Cat("k", 0, "k"),), "cats: name 'k' is used twice"),
                        ((Cat("c", 0, "sofa"),), "cats: 'c' sits on kind must be one of"),
                        ((Cat("c", -1, "k"),), "cats: 'c' descriptor must be"), ((), "cats")):
        with pytest.raises(ValueError, match=match):
            check_fields(Cfg((Kind("k", 1),), cats), rules)


def test_fields_checks_a_pytrees_fields_in_the_arguments_scope():
    from flowmaps_jax.validation.composite import Fields
    from flowmaps_jax.validation.fields import Int, IntArray, Mask, Optional, check_args

    rules = {"mask": Mask(("*B", "S")), "kind": IntArray(0, "K-1", ("*B", "S")),
             "tau": IntArray(0, "T", ("*B",))}

    @check_args(num_kinds=Int(size="K"), horizon=Optional(Int(size="T")),
                tokens=Fields(tokens.SceneTokens, rules, where="mask", padded=("kind",)))
    def count(tokens, num_kinds, horizon=None):
        return int(np.asarray(tokens.mask).sum())

    mask = np.array([[True, False]])
    good = tokens.SceneTokens(boxes=None, descriptor=None, kind=np.array([[1, 7]]), mask=mask,
                              tau=np.array([5]))
    assert count(good, 2) == 1  # kind 7 on padding is free; no horizon: tau unbounded
    with pytest.raises(ValueError, match=r"tokens.kind must lie in 0..1; got values in 2..2"):
        count(good.replace(kind=np.array([[2, 0]])), 2)
    with pytest.raises(ValueError, match=r"tokens.tau must lie in 0..4"):
        count(good, 2, horizon=4)
    with pytest.raises(ValueError, match=r"tokens.tau must have shape \(\*B,\) with \*B = \(1,\)"):
        count(good.replace(tau=np.array([1, 2])), 2)
    with pytest.raises(ValueError, match=r"tokens\.kind must be an array"):
        count(good.replace(kind=[[1, 0]]), 2)
    with pytest.raises(ValueError, match="tokens must be a SceneTokens"):
        count(mask, 2)


def test_pattern_rule_names_the_field_and_clips_the_value():
    from flowmaps_jax.validation.composite import Pattern

    rule = Pattern("[0-9a-f]{4}", "four hex digits")
    assert rule("digest", "00af") == "00af"
    for bad in ("00AF", "00af0", None, 7):
        with pytest.raises(ValueError, match="digest must be four hex digits"):
            rule("digest", bad)
    with pytest.raises(ValueError, match=r"got 'xxxx+'$"):
        rule("digest", "x" * 1000)


def test_fields_rule_checks_nested_shapes_in_one_scope():
    import dataclasses as dc

    from flowmaps_jax.validation.composite import Fields
    from flowmaps_jax.validation.fields import Array, check_args

    @dc.dataclass
    class Inner:
        a: object

    @dc.dataclass
    class Outer:
        inner: Inner
        b: object

    @check_args(x=Fields(Outer, {"inner": Fields(Inner, {"a": Array(("B", 2))}),
                                 "b": Array(("B",))}))
    def f(x):
        return x

    ok = Outer(Inner(np.zeros((3, 2))), np.zeros(3))
    assert f(ok) is ok
    with pytest.raises(ValueError, match=r"x.b must have shape \(B,\) with B = 3 "
                                         r"\(from x.inner.a\)"):
        f(Outer(Inner(np.zeros((3, 2))), np.zeros(4)))
    with pytest.raises(ValueError, match=r"x\.inner must be a Inner"):
        f(Outer(np.zeros(3), np.zeros(3)))


def test_output_dir_rule_gives_a_path_and_refuses_a_file(tmp_path):
    import pathlib

    from flowmaps_jax.validation.composite import OutputDir

    assert OutputDir()("run_dir", str(tmp_path / "new")) == tmp_path / "new"
    assert isinstance(OutputDir()("run_dir", str(tmp_path)), pathlib.Path)
    (tmp_path / "f").write_text("x")
    with pytest.raises(ValueError, match=r"run_dir .* is a file, not a directory"):
        OutputDir()("run_dir", tmp_path / "f")
    with pytest.raises(ValueError, match="run_dir must be a non-empty path"):
        OutputDir()("run_dir", "")


def test_int_below_is_bounded_by_a_field_checked_before_it():
    from flowmaps_jax.validation.composite import IntBelow
    from flowmaps_jax.validation.fields import Int, check_args

    @check_args(steps=Int(), warmup=IntBelow("steps"))
    def schedule(steps, warmup):
        return warmup

    assert schedule(10, 9) == 9
    with pytest.raises(ValueError, match=r"warmup must be an int in 0\.\.steps-1 \(steps = 10\); "
                                         r"got 10"):
        schedule(10, 10)
    with pytest.raises(ValueError, match="warmup must be an int >= 0"):
        schedule(10, -1)


def test_a_rule_after_others_reads_their_checked_values():
    import types

    from flowmaps_jax.validation.composite import After
    from flowmaps_jax.validation.fields import Each, Int, check_args, check_fields

    @check_args(steps=Int(), warmup=After(lambda got: Int(0, got["steps"] - 1)))
    def schedule(warmup, steps):
        return warmup, steps

    assert schedule(steps=10, warmup=9) == (9, 10)
    with pytest.raises(ValueError, match=r"warmup must be an int in 0\.\.9"):
        schedule(steps=10, warmup=10)
    with pytest.raises(ValueError, match="steps"):
        schedule(steps="10", warmup=0)  # checked before the rule that reads it
    rules = {"history": Int(1, 10),
             "horizons": After(lambda got: Each(Int(1, 12 - got["history"]), what="horizons"))}
    assert check_fields(types.SimpleNamespace(history=4, horizons=[1, 8]), rules,
                        store=False) == {"history": 4, "horizons": (1, 8)}
    with pytest.raises(ValueError, match=r"horizons must be an int in 1\.\.8"):
        check_fields(types.SimpleNamespace(history=4, horizons=[1, 9]), rules)


def test_index_rule_bounds_by_a_named_size():
    from flowmaps_jax.validation.composite import Index
    from flowmaps_jax.validation.fields import IntArray, check_args

    @check_args(x=IntArray(shape=("E", 2)), env=Index("E"))
    def pick(x, env):
        return env

    assert pick(np.zeros((3, 2), np.int32), np.int64(2)) == 2
    for env in (3, -1, 0.5, True):
        with pytest.raises(ValueError, match=r"env must be an int in 0\.\.2"):
            pick(np.zeros((3, 2), np.int32), env)
    with pytest.raises(TypeError, match="not bound"):
        check_args(env=Index("E"))(lambda env: env)(0)


def test_positive_array_rule():
    from flowmaps_jax.validation.composite import PositiveArray

    rule = PositiveArray(what=" (sides)")
    assert rule("size", np.array([1.0, 2.5])).shape == (2,)
    for bad in (np.array([1.0, 0.0]), np.array([-1.0]), np.array([np.nan]), np.array([True])):
        with pytest.raises(ValueError, match=r"^size (must|contains)"):
            rule("size", bad)


def test_needs_refuses_a_value_given_without_or_with_another_argument():
    import types

    from flowmaps_jax.validation.composite import Needs
    from flowmaps_jax.validation.fields import Optional, check_args, check_fields

    @check_args(from_step=Needs("resume", "needs resume=True"))
    def run(resume=False, from_step=None):
        return from_step

    assert run() is None and run(True, 0) == 0
    with pytest.raises(ValueError, match="from_step needs resume=True"):
        run(False, 0)  # 0 is given: only None (or False) is not
    rules = {"resume": Optional(Needs("run_dir", "needs --run-dir")),
             "overwrite": Needs("resume", "and --resume exclude each other", needs=False)}
    check_fields(types.SimpleNamespace(run_dir=None, resume=False, overwrite=True), rules,
                 store=False)
    with pytest.raises(ValueError, match=r"^--overwrite and --resume exclude each other$"):
        check_fields(types.SimpleNamespace(run_dir="r", resume=True, overwrite=True),
                     {"run_dir": Optional(lambda n, v: v), **rules}, prefix="--", store=False)
    with pytest.raises(ValueError, match=r"^resume needs --run-dir$"):
        check_fields(types.SimpleNamespace(run_dir=None, resume=True, overwrite=False),
                     {"run_dir": Optional(lambda n, v: v), **rules}, store=False)


def test_non_empty_rule():
    from flowmaps_jax.validation.composite import NonEmpty
    from flowmaps_jax.validation.fields import Array, Each, Int

    rule = NonEmpty(Array((None, None)), "at least one query")
    assert rule("q", np.zeros((2, 3))).shape == (2, 3)
    with pytest.raises(ValueError, match=r"q must not be empty \(at least one query\); got "
                                         r"shape \(2, 0\)"):
        rule("q", np.zeros((2, 0)))
    assert NonEmpty(Each(Int()))("sizes", [1, 2]) == (1, 2)
    with pytest.raises(ValueError, match="sizes must not be empty"):  # a sequence: its length
        NonEmpty(lambda name, value: value)("sizes", [])
