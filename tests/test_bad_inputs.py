"""Property tests: random malformed inputs to the simulator's, the tokens' and the renderer's
public functions raise ``ValueError``, never another exception, and never pass.

Every strategy builds an input that is invalid for its argument (a wrong type, dtype or shape,
NaN, a value out of range); the other arguments stay valid. Validation runs before anything is
jitted, so no example compiles a function.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re

import jax
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from matplotlib.figure import Figure

from flowmaps_jax import tokens as tok
from flowmaps_jax.flowsim import (
    FlowSimConfig,
    ObjectCategory,
    Scenes,
    denormalise_boxes,
    exact_posterior,
    generate,
    load_scenes,
    make_train_batch,
    normalise_boxes,
    render,
    save_scenes,
    scene_tokens,
    slot_boxes,
    train_split,
    transition_matrix,
)

FAST = settings(max_examples=25, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow])
CONFIG = FlowSimConfig()
INT32_MAX = 2**31 - 1


def raises_value_error(call, *args, **kwargs) -> None:
    with pytest.raises(ValueError):
        call(*args, **kwargs)


# ------------------------------------------------------------------------------ strategies

junk = st.one_of(st.none(), st.text(max_size=3), st.just(b"x"), st.just({}), st.just(object()),
                 st.complex_numbers(max_magnitude=5, allow_nan=False).filter(lambda z: z.imag))
"""Values that are no number and no array at all."""

not_an_int = st.one_of(junk, st.booleans(), st.floats(allow_nan=True), st.just([1]),
                       st.just(np.float32(2.0)))
not_a_real = st.one_of(junk, st.booleans(), st.sampled_from([math.nan, math.inf, -math.inf]),
                       st.just([0.5]), st.just("0.5"))


def ints_outside(low: int | None, high: int | None) -> st.SearchStrategy:
    """Ints below ``low`` or above ``high`` (either may be None: no bound on that side)."""
    sides = []
    if low is not None:
        sides.append(st.integers(max_value=low - 1))
    if high is not None:
        sides.append(st.integers(min_value=high + 1))
    return st.one_of(*sides)


@st.composite
def broken_array(draw, array, low=None, high=None, index=0, shapes=True):
    """``array`` (numpy) made invalid: another dtype or (if ``shapes``) shape, NaN (float
    arrays) or a value outside ``low..high`` at ``index`` (where it is checked: a real token)."""
    array = np.asarray(array)
    is_float = np.issubdtype(array.dtype, np.floating)
    options = ["bool", "complex", "str", "object"] + (["drop_dim", "add_dim"] if shapes else [])
    options += ["nan"] if is_float else ["float"]
    options += ["low"] if low is not None else []
    options += ["high"] if high is not None else []
    how = draw(st.sampled_from(options))
    if how in ("bool", "complex", "str"):
        return array.astype({"bool": bool, "complex": complex, "str": str}[how])
    if how == "object":
        return array.astype(object)
    if how == "float":
        return array.astype(np.float32)
    if how == "drop_dim":
        return array[..., 0] if array.ndim else array[None]
    if how == "add_dim":
        return array[None, ...]
    out = array.copy()
    flat = np.unravel_index(index, out.shape)
    if how == "nan":
        out[flat] = draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    elif how == "low":
        out[flat] = low - draw(st.integers(1, 1000))
    else:
        out[flat] = high + draw(st.integers(1, 1000))
    return out


# ------------------------------------------------------------------------------ FlowSimConfig

_INT_FIELDS = {  # values every one of which makes the (otherwise default) config invalid
    "map_size": ints_outside(50, 1024),  # below 50 the paper's objects leave the map
    "num_furniture": st.one_of(ints_outside(9, None), st.integers(18, 40)),  # 18+: > 20 tokens
    "min_per_kind": ints_outside(1, 3),
    "min_object_px": ints_outside(1, 25),
    "num_timesteps": ints_outside(2, INT32_MAX),
    "max_tokens": ints_outside(13, INT32_MAX),
    "layout_budget": ints_outside(1, INT32_MAX),
    "layout_candidates": ints_outside(1, INT32_MAX),
}
_FRACTIONS = ("table_min_frac", "table_max_frac", "object_frac")
bad_probs = st.one_of(
    junk, st.just([0.2, 0.7]), st.tuples(st.floats(0, 1), st.floats(0, 1)),
    st.tuples(not_a_real, st.just(0.5), st.just(0.5)),
    st.tuples(st.floats(-1, -1e-3), st.just(0.5), st.just(0.5)),
    st.tuples(st.floats(0.4, 0.6), st.floats(0.7, 0.9), st.just(0.0)),  # sum above 1
    st.just(np.array([0.2, 0.7, 0.1])))
bad_categories = st.one_of(
    junk, st.just(()), st.just(list(CONFIG.categories)), st.just(({"name": "fork"},)),
    st.sampled_from([dataclasses.replace(CONFIG.categories[0], **change) for change in (
        {"ordering": "zigzag"}, {"shape": "blob"}, {"furniture_kind": "sofa"}, {"descriptor": 3},
        {"descriptor": -1}, {"descriptor": 1.0}, {"name": ""}, {"colour": None})]).map(
        lambda cat: (*CONFIG.categories[1:], cat)))


@st.composite
def bad_config_kwargs(draw):
    field = draw(st.sampled_from([*_INT_FIELDS, *_FRACTIONS, "transition_probs", "jitter_probs",
                                  "dynamics", "categories", "furniture_kinds"]))
    if field in _INT_FIELDS:
        value = draw(st.one_of(not_an_int, _INT_FIELDS[field]))
    elif field in _FRACTIONS:
        limit = {"table_min_frac": 0.25, "table_max_frac": 1.0, "object_frac": 0.41}[field]
        value = draw(st.one_of(not_a_real, st.floats(-2, 0), st.floats(1.0001, 5),
                               st.floats(limit + 1e-3, 5)))
        if field == "table_max_frac":  # below table_min_frac
            value = draw(st.one_of(st.just(value), st.floats(0.01, 0.099)))
    elif field in ("transition_probs", "jitter_probs"):
        value = draw(bad_probs)
    elif field == "dynamics":
        value = draw(st.one_of(junk, st.text(min_size=1, max_size=5), st.just(["markov"])))
    elif field == "categories":
        value = draw(bad_categories)
    else:
        value = draw(st.one_of(junk, st.just(()), st.just(CONFIG.categories)))
    return {field: value}


@FAST
@given(bad_config_kwargs())
def test_flowsim_config(kwargs):
    raises_value_error(FlowSimConfig, **kwargs)
    raises_value_error(FlowSimConfig.from_dict, {**CONFIG.to_dict(), **{
        k: v for k, v in kwargs.items() if k not in ("categories", "furniture_kinds")}}
        if not {"categories", "furniture_kinds"} & set(kwargs) else kwargs)


# ------------------------------------------------------------------------------ generate


bad_key = st.one_of(not_an_int, st.integers(), st.just(np.zeros(2, np.int32)),
                    st.just(np.zeros(3, np.uint32)), st.just(jax.random.split(jax.random.key(0))))


@FAST
@given(which=st.sampled_from(["key", "num_envs", "config"]), data=st.data())
def test_generate(which, data):
    args = {"key": jax.random.key(0), "num_envs": 4, "config": CONFIG}
    args[which] = data.draw({"key": bad_key,
                             "num_envs": st.one_of(not_an_int, st.integers(max_value=0),
                                                   st.integers(10**12, 10**15)),
                             "config": st.one_of(junk, st.just(CONFIG.to_dict()))}[which])
    raises_value_error(generate, args["key"], args["num_envs"], args["config"])


@FAST
@given(which=st.sampled_from(["key", "batch", "short_frac", "seed"]), data=st.data())
def test_queries_batches_splits(small_scenes, which, data):
    key = jax.random.key(0)
    if which == "key":
        raises_value_error(make_train_batch, data.draw(bad_key), small_scenes, 8, 2, CONFIG)
    elif which == "batch":
        b = data.draw(st.one_of(not_an_int, st.integers(max_value=0), st.just(10**12)))
        raises_value_error(make_train_batch, key, small_scenes, b, 2, CONFIG)
    elif which == "short_frac":
        frac = data.draw(st.one_of(not_a_real, st.floats(1.001, 9), st.floats(-9, -0.001)))
        raises_value_error(make_train_batch, key, small_scenes, 8, 2, CONFIG, frac)
    else:
        seed = data.draw(st.one_of(not_an_int, st.integers(max_value=-1),
                                   st.integers(min_value=2**32)))
        raises_value_error(train_split, CONFIG, 4, seed)


# ------------------------------------------------------------------------------ posterior


@FAST
@given(which=st.sampled_from(["num_slots", "slot_now", "horizon", "tau", "dynamics", "config"]),
       data=st.data())
def test_exact_posterior_and_transition_matrix(which, data):
    args = {"num_slots": np.array([3, 4]), "slot_now": np.array([0, 3]),
            "horizon": np.array([1, 5]), "config": CONFIG, "dynamics": "schedule_jitter",
            "tau": np.array([2, 3])}
    # Bounds of entry 0 (tau + horizon <= 19); shapes broadcast, so only values and dtypes break.
    bounds = {"num_slots": (1, 10), "slot_now": (0, 2), "horizon": (0, 17), "tau": (0, 18)}
    if which in bounds:
        low, high = bounds[which]
        args[which] = data.draw(st.one_of(junk, broken_array(args[which], low, high,
                                                             shapes=False)))
    else:  # dynamics=None means the config's: valid
        args[which] = data.draw(st.one_of(junk.filter(lambda x: x is not None),
                                          st.text(max_size=4), st.just(CONFIG.to_dict())))
    raises_value_error(exact_posterior, **args)
    if which in ("num_slots", "config"):
        raises_value_error(transition_matrix, args["num_slots"], args["config"])


# ------------------------------------------------------------------------------ scene views


@pytest.fixture(scope="module")
def few_scenes(small_scenes) -> Scenes:
    """Eight environments of the session's scenes, as numpy arrays."""
    return jax.tree_util.tree_map(lambda a: np.asarray(a)[:8], small_scenes)


_SCENE_BOUNDS = {"furniture_boxes": (0, 256), "object_boxes": (0, 256), "object_size": (1, None),
                 "furniture_kind": (3, 5), "object_kind": (0, 2), "visit_order": (-1, 9),
                 "num_slots": (1, 10), "slot": (0, None), "layout_redraws": (0, None)}


@st.composite
def broken_scenes(draw, scenes: Scenes):
    field = draw(st.sampled_from(list(_SCENE_BOUNDS)))
    low, high = _SCENE_BOUNDS[field]
    value = getattr(scenes, field)
    bad = draw(st.one_of(broken_array(value, low, high), st.just(value.tolist()), junk))
    return scenes.replace(**{field: bad})


@FAST
@given(data=st.data(), which=st.sampled_from(["scenes", "env", "tau", "obj", "config"]))
def test_scene_tokens_and_slot_boxes(few_scenes, data, which):
    args = {"scenes": few_scenes, "env": np.array([0, 7]), "tau": np.array([0, 19]),
            "obj": np.array([0, 2]), "config": CONFIG}
    highs = {"env": 7, "tau": 19, "obj": 2}
    if which == "scenes":
        # Shapes and dtypes are checked on every call; values only where files come and go.
        args["scenes"] = data.draw(st.one_of(junk, st.just(dict(
            few_scenes.__dict__)), broken_scenes(few_scenes).filter(
            lambda s: not all(np.shape(getattr(s, f)) == np.shape(getattr(few_scenes, f))
                              and np.asarray(getattr(s, f)).dtype.kind
                              == np.asarray(getattr(few_scenes, f)).dtype.kind
                              for f in _SCENE_BOUNDS))))
    elif which == "config":
        args["config"] = data.draw(st.one_of(junk, st.just(dataclasses.replace(
            CONFIG, num_timesteps=10))))
    else:
        args[which] = data.draw(st.one_of(junk, st.lists(st.integers(0, 1), max_size=3).map(
            lambda x: np.array(x, np.int64)[:, None]), broken_array(args[which], 0,
                                                                    highs[which])))
    if which != "obj":
        raises_value_error(scene_tokens, args["scenes"], args["env"], args["tau"],
                           args["config"])
    if which != "tau":
        raises_value_error(slot_boxes, args["scenes"], args["env"], args["obj"], args["config"])


@FAST
@given(data=st.data())
def test_scene_files(few_scenes, tmp_path_factory, data):
    folder = tmp_path_factory.mktemp("files")
    bad_path = data.draw(st.one_of(st.none(), st.integers(), st.just(b"x"), st.just(""),
                                   st.just(folder), st.just(folder / "missing" / "s.npz")))
    raises_value_error(save_scenes, bad_path, few_scenes, CONFIG)
    raises_value_error(load_scenes, bad_path)
    broken = data.draw(broken_scenes(few_scenes))
    raises_value_error(save_scenes, folder / "s.npz", broken, CONFIG)
    # The same arrays written behind save_scenes' back are refused when loaded.
    arrays = {f: getattr(broken, f) for f in _SCENE_BOUNDS}
    try:
        stored = {f: np.asarray(a) for f, a in arrays.items()}
    except (ValueError, TypeError):  # numpy cannot store this junk at all: nothing to load
        return
    if all(a.dtype.kind == np.asarray(getattr(few_scenes, f)).dtype.kind
           and np.array_equal(a, getattr(few_scenes, f)) for f, a in stored.items()):
        return  # a list of the right numbers is stored as the right array: a valid file
    np.savez(folder / "t.npz", format_version=np.int64(1),
             config_json=np.asarray(json.dumps(CONFIG.to_dict())), **stored)
    raises_value_error(load_scenes, folder / "t.npz")


# ------------------------------------------------------------------------------ tokens


@pytest.fixture(scope="module")
def tokens_queries(small_scenes):
    t = scene_tokens(small_scenes, np.arange(3), np.array([0, 5, 9]), CONFIG)
    t = jax.tree_util.tree_map(np.asarray, t)
    q = tok.Queries(descriptor=np.array([[0, 1], [2, 0], [1, 1]], np.int32),
                    tau_q=np.array([[1, 19], [6, 7], [10, 19]], np.int32))
    return t, q


_TOKEN_BOUNDS = {"boxes": (0, 1), "descriptor": (0, 5), "kind": (0, 1), "mask": (None, None),
                 "tau": (0, 18)}


@FAST
@given(data=st.data(), field=st.sampled_from([*_TOKEN_BOUNDS, "descriptor_q", "tau_q",
                                              "roles", "whole"]))
def test_tokens_and_queries(tokens_queries, data, field):
    t, q = tokens_queries
    tok.validate_tokens(t, 6, 20, num_timesteps=20)
    tok.validate_queries(q, t.tau, 6, 20, object_descriptors=CONFIG.object_descriptors)
    if field in _TOKEN_BOUNDS:
        low, high = _TOKEN_BOUNDS[field]
        value = getattr(t, field)
        if field == "mask":
            bad = data.draw(st.one_of(
                st.sampled_from([0.5, 2, -1]).map(lambda x: np.where(value, x, 0)),
                st.just(np.zeros_like(value)), broken_array(value).filter(
                    lambda a: np.asarray(a).dtype.kind not in "biuf" or a.shape != value.shape),
                junk))
        else:
            bad = data.draw(st.one_of(broken_array(value, low, high), st.just(value.tolist()),
                                      junk))
        raises_value_error(tok.validate_tokens, t.replace(**{field: bad}), 6, 20,
                           num_timesteps=20)
    elif field in ("descriptor_q", "tau_q"):
        name = "descriptor" if field == "descriptor_q" else "tau_q"
        low, high = (0, 5) if name == "descriptor" else (None, 19)
        bad = data.draw(st.one_of(broken_array(getattr(q, name), low, high), junk))
        raises_value_error(tok.validate_queries, q.replace(**{name: bad}), t.tau, 6, 20)
    elif field == "roles":  # a table's descriptor (3, 4, 5) is not a query
        table = data.draw(st.integers(3, 5))
        bad = q.replace(descriptor=np.where(np.arange(2) == 1, table, q.descriptor))
        raises_value_error(tok.validate_queries, bad, t.tau, 6, 20,
                           object_descriptors=CONFIG.object_descriptors)
    else:
        raises_value_error(tok.validate_tokens, data.draw(st.one_of(junk, st.just(q))), 6)
        raises_value_error(tok.validate_queries, data.draw(st.one_of(junk, st.just(t))), t.tau,
                           6, 20)


# ------------------------------------------------------------------------------ the predictor


@pytest.fixture(scope="module")
def predictor():
    from support import TINY

    from flowmaps_jax.model import init_params
    from flowmaps_jax.predictor import Predictor

    return Predictor.from_params(init_params(jax.random.key(0), TINY), TINY)


@FAST
@given(data=st.data(), what=st.sampled_from(["tokens", "queries", "num_samples", "key",
                                             "num_steps", "method", "pixels", "x", "field"]))
def test_predictor_sample_and_log_prob(predictor, tokens_queries, data, what):
    """Predictor.sample / log_prob, the planner's entry points: only ValueError comes out."""
    t, q = tokens_queries
    good = {"inputs": t, "queries": q, "num_samples": 4, "key": jax.random.key(0),
            "num_steps": 3, "method": "euler", "pixels": False}
    bad = dict(good)
    if what in ("tokens", "queries"):
        bad["inputs" if what == "tokens" else what] = data.draw(
            st.one_of(junk, st.just(q if what == "tokens" else t)))
    elif what == "num_samples":
        bad[what] = data.draw(st.one_of(not_an_int, st.integers(max_value=0),
                                        st.just(10**9)))  # 10**9 boxes: more than memory
    elif what == "key":
        bad[what] = data.draw(bad_key)
    elif what == "num_steps":
        bad[what] = data.draw(st.one_of(not_an_int, st.integers(max_value=1)))
    elif what == "method":
        bad[what] = data.draw(st.one_of(junk, st.just("rk4")))
    elif what == "pixels":
        bad[what] = data.draw(st.one_of(st.just("yes"), st.just(1), st.none()))
    elif what == "field":  # one field of the tokens or queries broken
        name = data.draw(st.sampled_from(["boxes", "descriptor", "tau"]))
        low, high = _TOKEN_BOUNDS[name]
        bad["inputs"] = t.replace(**{name: data.draw(st.one_of(
            junk, st.just(getattr(t, name).tolist()), broken_array(getattr(t, name), low, high)))})
    else:
        x = data.draw(st.one_of(junk, st.just(np.full((3, 2, 4, 4), np.nan, np.float32)),
                                st.just(np.zeros((3, 2, 4), np.float32)),
                                st.just(np.zeros((3, 2, 4, 4), np.complex64))))
        raises_value_error(predictor.log_prob, t, q, x, num_steps=3, method="euler")
        return
    raises_value_error(predictor.sample, **bad)


@pytest.mark.parametrize("params", [{}, None, {"params": {}}, "weights"])
def test_predictor_params_that_are_not_the_models_are_named(predictor, params):
    """``Predictor(params={})`` was accepted, then a Flax error came out of the first call."""
    from flowmaps_jax.predictor import Predictor

    with pytest.raises(ValueError, match=r"^params: parameter \S+ is absent; the 'flowmaps' "
                                         r"|^params must be a Mapping; got (NoneType|str)"):
        Predictor(params=params, model=predictor.model)
    half = dict(predictor.params)
    half.pop(sorted(half)[0])
    with pytest.raises(ValueError, match=rf"^params: parameter {sorted(predictor.params)[0]}/"):
        Predictor.from_params(half, predictor.model)


def test_homes_queries_must_be_homes_queries_of_arrays():
    """A homes model's queries as lists, a tuple or a dict raised AttributeError; its params
    {} a Flax error."""
    from flowmaps_jax.flowsim.homes import HomesConfig, generate_homes
    from flowmaps_jax.flowsim.homes.queries import HomesQueries
    from flowmaps_jax.model.homes_family import HomesModelConfig, init_params
    from flowmaps_jax.predictor import Predictor

    config = HomesConfig(regime="mixed", num_hours=96)
    model = HomesModelConfig(dim=16, encoder_layers=1, weight_blocks=1, cdit_blocks=1, heads=2,
                             mlp_ratio=2, freq_bands=4, history=24)
    with pytest.raises(ValueError, match=r"^params: parameter \S+ is absent"):
        Predictor(params={}, model=model, family_name="flowmaps-homes", homes=config)
    homes_model = Predictor(params=init_params(jax.random.key(0), model, config), model=model,
                            family_name="flowmaps-homes", homes=config)
    homes = generate_homes(jax.random.key(0), config, 2)
    fields = (np.zeros((2, 3), np.int32), np.full((2, 3), 30, np.int32),
              np.full((2, 3), 31, np.int32))
    for queries, message in (
            (HomesQueries(*(f.tolist() for f in fields)), "queries.object_index must be an array"),
            (fields, "queries must be a HomesQueries; got tuple"),
            (list(fields), "queries must be a HomesQueries; got list"),
            (dict(zip(("object_index", "tau", "tau_q"), fields, strict=True)),
             "queries must be a HomesQueries; got dict")):
        for call in (lambda q: homes_model.probabilities(homes, q),
                     lambda q: homes_model.sample(homes, q, 2, jax.random.key(1)),
                     lambda q: homes_model.as_prior()(homes, q)):
            with pytest.raises(ValueError, match=f"^{re.escape(message)}"):
                call(queries)


# ------------------------------------------------------------------------------ boxes, render


@FAST
@given(data=st.data())
def test_box_conversions(data):
    good = np.array([[10.0, 20.0, 40.0, 60.0]])
    bad = data.draw(st.one_of(junk, broken_array(good).filter(
        lambda a: np.asarray(a).dtype.kind not in "iuf" or np.shape(a)[-1:] != (4,)
        or not np.all(np.isfinite(a)))))
    raises_value_error(normalise_boxes, bad, CONFIG)
    if np.asarray(bad).dtype.kind not in "f":  # denormalise lets NaN through (model samples)
        raises_value_error(denormalise_boxes, bad, CONFIG)
    raises_value_error(normalise_boxes, good, data.draw(junk))


@FAST
@given(data=st.data(), call=st.sampled_from(["scene", "timeline", "orders", "posterior",
                                             "overlay"]))
def test_render(few_scenes, data, call):
    index = st.one_of(not_an_int, st.integers(max_value=-1), st.integers(min_value=8))
    config = data.draw(st.one_of(st.just(CONFIG), junk))
    if call == "scene":
        env, tau = data.draw(index), data.draw(st.one_of(st.just(0), index))
        raises_value_error(render.draw_scene, few_scenes, env, tau, config)
        flag = data.draw(st.one_of(junk, st.just("yes"), st.just(1)))
        raises_value_error(render.draw_scene, few_scenes, 0, 0, CONFIG, show_orders=flag)
        raises_value_error(render.draw_scene, few_scenes, 0, 0, CONFIG, legend=flag)
    elif call == "timeline":
        taus = data.draw(st.one_of(junk, st.just([]), st.just([2, 1]), st.just([0, 20]),
                                   st.just([0.5, 1]), st.just("01")))
        raises_value_error(render.draw_timeline, few_scenes, 0, taus, CONFIG)
    elif call == "orders":
        scenes = data.draw(st.one_of(junk, broken_scenes(few_scenes).filter(
            lambda s: any(not hasattr(getattr(s, f), "shape")
                          or np.shape(getattr(s, f)) != np.shape(getattr(few_scenes, f))
                          or np.asarray(getattr(s, f)).dtype.kind
                          != np.asarray(getattr(few_scenes, f)).dtype.kind
                          for f in _SCENE_BOUNDS))))
        raises_value_error(render.draw_visit_orders, scenes, 0, CONFIG)
    elif call == "posterior":
        probs = data.draw(st.one_of(junk, st.just(np.array(["0.5"] * 10)),
                                    st.just(np.full(10, np.nan)), st.just(-np.ones(10)),
                                    st.just(np.ones((2, 10)))))
        raises_value_error(render.draw_posterior, few_scenes, 0, 0, 0, probs, CONFIG)
    else:
        ax = Figure().add_subplot()
        boxes = data.draw(st.one_of(junk, st.just(np.zeros((2, 3))), st.just(np.full(4, np.nan)),
                                    st.just(np.array([True] * 4)), st.just(np.zeros(4, complex))))
        raises_value_error(render.overlay_boxes, ax, boxes, CONFIG)
        raises_value_error(render.overlay_boxes, data.draw(junk), np.zeros(4), CONFIG)


def test_new_categories_do_not_weaken_the_checks():
    """A data-only fifth category goes through the same checks."""
    bad = ObjectCategory("cup", 6, "orange", "diamond", "office_desk", "sideways")
    raises_value_error(FlowSimConfig, categories=(*CONFIG.categories, bad))
