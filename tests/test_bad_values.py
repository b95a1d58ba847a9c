"""Bad values at the public entries: garbage priors, non-finite or absurd homes, ill-posed
queries, habit and config checks in the order that names the real error, numbers that must not
underflow, and traced out-of-range inputs (NaN, never another input's answer); one-line
``ValueError``s naming the argument.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support import error_line, run_cli

from flowmaps_jax import flowsim
from flowmaps_jax import validation as v
from flowmaps_jax.evaluation.receptacle_scores import posterior_scores
from flowmaps_jax.flowsim import FlowSimConfig, exact_posterior, generate, habits, scene_tokens
from flowmaps_jax.flowsim.generate import LayoutError
from flowmaps_jax.flowsim.homes import HomesConfig, generate_homes
from flowmaps_jax.flowsim.homes.posterior import (
    homes_history_posterior,
    homes_posterior,
    transition_matrix,
)
from flowmaps_jax.flowsim.homes.queries import HomesQueries
from flowmaps_jax.flowsim.kernels import distance_weights
from flowmaps_jax.model import ModelConfig, init_params
from flowmaps_jax.model.homes_family import HomesModelConfig
from flowmaps_jax.predictor import Predictor, load_pretrained
from flowmaps_jax.search import episodes as E
from flowmaps_jax.tables import table_probabilities
from flowmaps_jax.tokens import OBJECT, Queries
from flowmaps_jax.training import cli as train_cli
from flowmaps_jax.training.config import HomesTrainConfig, TrainConfig, apply_overrides, get_preset
from flowmaps_jax.validation.scalars import int_list

CFG = dataclasses.replace(get_preset("smoke"), routine_envs=0)
QUIET = ["--preset", "smoke", "--set", "routine_envs=0", "--no-progress"]


_cli, _error_line = run_cli, error_line  # tests/support.py


"""Per class: one entry per reproduction tried, True when it behaved (reported at the end)."""


# --------------------------------------------------------------- garbage priors


@pytest.fixture(scope="module")
def search_set(small_scenes, flowsim_config):
    scenes = jax.tree_util.tree_map(lambda a: a[:4], small_scenes)
    return E.build_search_set(scenes, flowsim_config, jax.random.key(3))


@pytest.mark.parametrize("garbage, match", [
    (np.nan, "NaN or inf"), (np.inf, "NaN or inf"), (-1.0, "negative"), (0.0, "sum to 1"),
    (0.5, "sum to 1")])
def test_make_episodes_refuses_garbage_priors(search_set, garbage, match):
    probs = np.asarray(E.exact_tables(search_set)).copy()
    E.make_episodes(search_set, probs)
    if garbage == 0.5:
        probs[1, 2] *= 0.5  # not normalised
    else:
        probs[1, 2] = garbage  # NaN, inf, negative everywhere, or all zero
    with pytest.raises(ValueError, match=f"table_probs .*{match}|table_probs {match}"):
        E.make_episodes(search_set, probs)


class _NaNModel:
    name, kind, source = "diverged", "flowmaps", "test"

    def sample(self, tokens, queries, num_samples, key):
        return np.full((*np.shape(queries.descriptor), num_samples, 4), np.nan, np.float32)


def test_a_model_with_nan_samples_gets_no_search_numbers(search_set):
    with pytest.raises(ValueError, match=r"diverged .*non-finite samples"):
        E.predictor_tables(_NaNModel(), search_set, 4, jax.random.key(0), progress=False)


def test_run_episodes_budget_is_bounded(search_set):
    episodes, _ = E.make_episodes(search_set, E.exact_tables(search_set))
    for call in (lambda: E.run_episodes(episodes, "greedy", budget=10**9),
                 lambda: E.expected_outcomes(episodes, E.truth_probs(search_set), "optimal",
                                             budget=10**8)):
        with pytest.raises(ValueError, match=r"budget=10+ looks .* GB"):
            call()


# ------------------------------------------------------------------------ names


def test_plain_names():
    for good in ("cpu", "smoke-2", "paper_v1.2", "a+b"):
        assert v.check_plain_name("preset", good) == good
    for bad in ("", "..", "a/b", "/x", ".x", "a..b", "<script>", "a b", "x" * 65, 3, None):
        with pytest.raises(ValueError, match="preset must be a plain name"):
            v.check_plain_name("preset", bad)


# ------------------------------------------------------------- checks under jit


def test_exact_posterior_under_jit_gives_nan_for_out_of_range_inputs():
    posterior = jax.jit(lambda k, s, h: exact_posterior(k, s, h))
    assert np.all(np.isnan(posterior(3, 7, 1)))  # the issue: slot 1's answer before
    assert np.all(np.isnan(posterior(0, 0, 1)))  # the issue: [1, 0, ...] before
    assert np.all(np.isnan(posterior(3, 1, 25)))  # a horizon past T - 1: no longer clipped
    np.testing.assert_array_equal(posterior(3, 1, 2), exact_posterior(3, 1, 2))
    batch = posterior(np.array([3, 3]), np.array([1, 5]), np.array([2, 2]))
    assert not np.any(np.isnan(batch[0])) and np.all(np.isnan(batch[1]))  # row by row
    jitter = jax.jit(lambda t: exact_posterior(3, 1, 2, dynamics="schedule_jitter", tau=t))
    assert np.all(np.isnan(jitter(19))) and not np.any(np.isnan(jitter(5)))
    assert np.all(np.isnan(jax.jit(flowsim.transition_matrix)(0)))
    for bad in (lambda: exact_posterior(3, 7, 1), lambda: exact_posterior(0, 0, 1)):
        with pytest.raises(ValueError):  # eagerly refused, as before
            bad()


# ----------------------------------------------------------------- habit checks


@pytest.mark.parametrize("probs, words", [((0.5, 0.3, 0.0), "sum to 1"),
                                          ((1.2, -0.2, 0.0), "negative"),
                                          ((math.nan, 0.5, 0.5), "NaN")])
def test_habit_prior_checks_its_probabilities(probs, words):
    with pytest.raises(ValueError, match="habit_probs") as info:
        habits.habit_prior(np.array([3, 4]), probs, 10)
    assert words in str(info.value)


def test_habit_prior_checks_num_slots_and_keeps_its_numbers():
    with pytest.raises(ValueError, match="num_slots"):
        habits.habit_prior(np.array([0, 4]), (1.0, 0.0, 0.0), 10)
    prior = habits.habit_prior(np.array([3, 4]), (0.5, 0.3, 0.2), 10)
    np.testing.assert_allclose(np.asarray(prior).sum(-1), 1.0, rtol=1e-6)
    traced = jax.jit(lambda p: habits.habit_prior(np.array([3]), p, 10))(
        jnp.array([0.5, 0.3, 0.2]))  # traced: used as given (documented)
    np.testing.assert_array_equal(traced, habits.habit_prior(np.array([3]), (0.5, 0.3, 0.2), 10))


@pytest.mark.parametrize("history_len", [3, 10])
def test_history_posterior_names_the_shape_first(history_len):
    from flowmaps_jax.flowsim.scenes import validation_split

    config = FlowSimConfig()
    scenes = validation_split(config, num_envs=1)
    with pytest.raises(ValueError, match=r"env must have shape \(Q,\)") as info:
        habits.history_posterior(scenes, config, 0, 0, 5, 1, history_len)
    assert "shape (Q,)" in str(info.value)
    # a 1-D call with too long a history: the clear error, not an IndexError
    with pytest.raises(ValueError, match="longer than the query's past"):
        habits.history_posterior(scenes, config, [0], [0], [5], [1], 10)
    with pytest.raises(ValueError, match="longer than the query's past"):
        habits.history_posterior(scenes, config, [0], [0], [5], [1], np.array([7]))


# ----------------------------------------------------------------- usage errors


@pytest.mark.parametrize("argv, words", [
    (["--set", "flowsim.layout_budget=0"], "layout_budget must be an int in 1.."),
    (["--set", "flowsim.layout_candidates=0"], "layout_candidates must be"),
])
def test_a_layout_the_config_cannot_place_is_a_usage_error(tmp_path, capsys, monkeypatch,
                                                          argv, words):
    monkeypatch.chdir(tmp_path)
    code, _, err = _cli(train_cli.main, [*QUIET, *argv], capsys)
    ok = code == 2 and words in _error_line(err) and list(tmp_path.iterdir()) == []
    assert ok, err


def test_a_generation_that_cannot_place_a_layout_is_a_value_error():
    from flowmaps_jax.flowsim import generate

    crowded = FlowSimConfig(table_min_frac=0.24, table_max_frac=0.25, layout_budget=2)
    with pytest.raises(LayoutError, match="layout_budget") as info:
        generate(jax.random.key(0), 64, crowded)
    ok = isinstance(info.value, ValueError) and isinstance(info.value, RuntimeError)
    assert ok


@pytest.mark.parametrize("run_dir, words", [
    ("x" * 300, "more than the 255"),
    ("ok/" + "y" * 300 + "/run", "more than the 255"),
    ("", "non-empty path"),
])
def test_a_run_dir_that_cannot_be_created_is_a_usage_error(tmp_path, capsys, monkeypatch,
                                                          run_dir, words):
    monkeypatch.chdir(tmp_path)
    code, _, err = _cli(train_cli.main, [*QUIET, "--run-dir", run_dir], capsys)
    ok = code == 2 and words in _error_line(err) and list(tmp_path.iterdir()) == []
    assert ok, err
    with pytest.raises(ValueError, match="more than the 255"):  # the other outputs too
        v.check_output_file("--out", tmp_path / ("z" * 300))


@pytest.mark.parametrize("overrides, words", [
    (["--steps", "2", "--set", "lr=inf"], "lr must be a finite"),
    (["--steps", "2", "--set", "b1=2"], "b1 must be"),
    (["--set", "lr=１"], "lr must be a finite real number"),
    (["--set", "batch_size=８"], "batch_size must be an int"),
])
def test_minor_overrides_name_the_real_error(tmp_path, capsys, monkeypatch, overrides, words):
    monkeypatch.chdir(tmp_path)
    code, _, err = _cli(train_cli.main, [*QUIET, *overrides], capsys)
    ok = code == 2 and words in _error_line(err) and "warmup_steps" not in _error_line(err)
    assert ok, err


def test_table_probabilities_by_weights_checks_num_samples():
    class Weights:
        def table_weights(self, tokens, queries):
            raise AssertionError("not reached")

    for bad in (-5, 2.5, "3"):
        with pytest.raises(ValueError, match="num_samples"):
            table_probabilities(Weights(), None, None, bad, None, method="weights")


# ----------------------------------------------------------------- config types


@pytest.mark.parametrize("make", [
    lambda: TrainConfig(batch_size=np.int64(8), lr=np.float32(1e-3), clip_norm=np.float64(1)),
    lambda: HomesTrainConfig(lr=np.float32(1e-3), steps=np.int32(1000)),
    lambda: HomesModelConfig(dim=np.int64(32), max_frequency=np.float32(8.0)),
    lambda: ModelConfig(dim=np.array(16), heads=np.int8(2), condition_on_dtau=np.bool_(True)),
    lambda: FlowSimConfig(num_furniture=np.int64(10), object_frac=np.float32(0.375)),
    lambda: HomesConfig(num_hours=np.int64(48)),
])
def test_config_dataclasses_hold_python_numbers(make):
    config = make()
    values = dataclasses.asdict(config)
    json.dumps(values)
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        assert not isinstance(value, (np.generic, np.ndarray)), (field.name, type(value))
    if hasattr(config, "to_dict"):
        json.dumps(config.to_dict())


# ------------------------------------------------------------------------ minor


@pytest.mark.parametrize("text", ["1,,2", "1,2,", ",1", "\u0661,2", "1,\uff12", "1.0,2", ""])
def test_int_list_refuses_what_set_refuses(text):
    with pytest.raises(argparse.ArgumentTypeError):
        int_list(text)


def test_int_list_still_reads_integers():
    assert int_list("1,4,16") == [1, 4, 16] and int_list(" 2, -3 ") == [2, -3]


@pytest.mark.parametrize("override,field", [("seed=1.0000000000000001", "seed"),
                                            ("steps=20.5", "steps"),
                                            ("clip_norm=1e-320", "clip_norm"),
                                            ("lr=1e-45", "lr")])
def test_set_refuses_a_value_the_field_would_lose(override, field):
    with pytest.raises(ValueError, match=rf"\({field}\): {field} must be"):
        apply_overrides(CFG, [override])


def test_set_still_reads_integers_written_as_reals():
    config = apply_overrides(CFG, ["steps=1e4", "seed=8.0", "clip_norm=1e-30"])
    assert (config.steps, config.seed, config.clip_norm) == (10_000, 8, 1e-30)
    with pytest.raises(ValueError, match=r"clip_norm must be > 0.0 and at least"):
        HomesTrainConfig(clip_norm=1e-320)


# --------------------------------------------------------------------- numerics


HOMES = HomesConfig(num_hours=96)


def _frequent(length: float) -> HomesConfig:
    return HomesConfig(regime="frequent", frequent_length=length, num_hours=96)


@pytest.mark.parametrize("length", [0.1, 1e-3, 3.0])  # 0.1: the reproduction (rows lost mass)
def test_the_frequent_posterior_keeps_its_mass_at_any_accepted_length(length):
    config = _frequent(length)
    homes = generate_homes(jax.random.key(0), config, 2)
    for e in range(2):
        home = homes.home(e)
        for i in np.flatnonzero(np.asarray(home.object_valid)):
            p = np.asarray(homes_posterior(home, int(i), 3, 90, config))
            assert abs(p.sum() - 1.0) < 1e-4, (length, e, i, p.sum())
            t = np.asarray(transition_matrix(home, int(i), 3, config))
            allowed = np.asarray(home.object_allowed[i])
            np.testing.assert_allclose(t[allowed].sum(-1), 1.0, atol=1e-5)


def test_the_distance_kernel_is_unchanged_to_the_bit_where_it_did_not_underflow():
    distance = jax.random.uniform(jax.random.key(3), (6, 6)) * 20.0
    others = ~np.eye(6, dtype=bool)
    others[:, 5] = False  # a place the object may not stand on
    plain = jnp.where(others, jnp.exp(-distance / 3.0), 0.0)
    weight, total = distance_weights(others, distance, 3.0)
    np.testing.assert_array_equal(weight, plain)
    np.testing.assert_array_equal(total, plain.sum(-1, keepdims=True))


@pytest.mark.parametrize("length", [1e-3, 1e-2])
def test_the_distance_kernel_keeps_its_rows_where_the_exponentials_underflow(length):
    distance = jnp.asarray([[0.0, 2.0, 3.0], [2.0, 0.0, 2.0], [3.0, 2.0, 0.0]], jnp.float32)
    others = ~np.eye(3, dtype=bool)
    weight, total = distance_weights(others, distance, length)
    kernel = np.asarray(weight / total)
    np.testing.assert_allclose(kernel.sum(-1), 1.0)
    np.testing.assert_allclose(kernel[0], [0.0, 1.0, 0.0])  # all to the nearest place
    np.testing.assert_allclose(kernel[1], [0.5, 0.0, 0.5])  # two equally near


def test_the_2d_dynamic_habit_moves_at_a_short_length():
    centres = jnp.asarray([[0.1, 0.1], [0.9, 0.9], [0.1, 0.9], [0.0, 0.0]], jnp.float32)
    matrix = np.asarray(habits._dynamic_matrix(3, centres, 0.5, 1e-3))  # 3 places, 1 padding
    np.testing.assert_allclose(matrix[:3].sum(-1), 1.0, atol=1e-6)
    assert matrix[0, 0] == 0.5 and matrix[0, 2] == 0.5  # moves to its nearest place
    with pytest.raises(ValueError, match="dynamic_length"):
        FlowSimConfig(dynamic_length=1e-45)


@pytest.mark.parametrize("kwargs,field", [
    (dict(frequent_length=1e-30), "frequent_length"),
    (dict(frequent_length=1e308), "frequent_length"),
    (dict(home_width=(1e308, 1e308)), "home_width"),  # the reproduction: infinite homes
    (dict(home_depth=(8.0, 1e300)), "home_depth"),
    (dict(door_width=1e30), "door_width"),
    (dict(wall_margin=1e300), "wall_margin"),
])
def test_homes_config_bounds_its_real_valued_sizes(kwargs, field):
    with pytest.raises(ValueError, match=field):
        HomesConfig(**kwargs)


def test_a_class_size_beyond_the_bound_is_refused():
    big = dataclasses.replace(HOMES.object_classes[0], size=(1e308, 0.1, 0.1))
    with pytest.raises(ValueError, match="object_classes"):
        HomesConfig(object_classes=(big, *HOMES.object_classes[1:]))


def test_a_reference_posterior_that_lost_mass_is_never_scored():
    q = np.array([[0.5, 0.5, 0.0], [0.0, 0.0, 0.0]], np.float32)  # row 1 lost its mass
    allowed = np.array([[True, True, False], [True, True, True]])
    with pytest.raises(ValueError, match=r"q: the reference posterior's row \(1,\) sums to 0"):
        posterior_scores(q, q, allowed)
    with pytest.raises(ValueError, match="reference posterior"):
        posterior_scores(q[:1], np.array([[np.nan, 1.0, 0.0]], np.float32), allowed[:1])
    assert float(posterior_scores(q[:1], q[:1], allowed[:1])["kl"][0]) == 0.0


# ------------------------------------------------------------ ill-posed queries


TABLES_MODEL = ModelConfig(dim=16, encoder_layers=1, cdit_blocks=1, heads=2, mlp_ratio=2,
                           dropout=0.0, head="mixture")


@pytest.fixture(scope="module")
def scene_model():
    """A mixture-head FlowMaps from init, two FlowSim maps and one query of each."""
    sim = FlowSimConfig()
    scenes = generate(jax.random.key(0), 2, sim)
    tokens = jax.tree.map(np.asarray, scene_tokens(scenes, np.arange(2), np.array([0, 5]), sim))
    is_object = (tokens.kind[0] == OBJECT) & tokens.mask[0]
    objects = [int(d) for d in tokens.descriptor[0][is_object]]
    queries = Queries(descriptor=np.array([[objects[0]], [objects[0]]], np.int32),
                      tau_q=np.array([[3], [9]], np.int32))
    model = Predictor.from_params(init_params(jax.random.key(1), TABLES_MODEL), TABLES_MODEL)
    return model, tokens, queries, objects


def _ill_posed(tokens, objects, how: str):
    """The maps with the first queried object (scene 0) absent, or present twice."""
    slot = {d: i for i, (d, k) in enumerate(zip(tokens.descriptor[0], tokens.kind[0], strict=True))
            if k == OBJECT}
    if how == "absent":
        mask = tokens.mask.copy()
        mask[0, slot[objects[0]]] = False
        return tokens.replace(mask=mask)
    descriptor = tokens.descriptor.copy()
    descriptor[0, slot[objects[1]]] = objects[0]
    return tokens.replace(descriptor=descriptor)


_TABLE_CALLS = {
    "table_weights": lambda m, t, q: m.table_weights(t, q),
    "weights": lambda m, t, q: m.table_probabilities(t, q, 4, jax.random.key(0),
                                                     method="weights"),
    "samples": lambda m, t, q: m.table_probabilities(t, q, 4, jax.random.key(0)),
    "tables.weights": lambda m, t, q: table_probabilities(m, t, q, 0, None, method="weights"),
}


@pytest.mark.parametrize("how", ["absent", "twice"])
@pytest.mark.parametrize("call", sorted(_TABLE_CALLS))
def test_every_table_method_refuses_an_ill_posed_query_alike(scene_model, how, call):
    model, tokens, queries, objects = scene_model
    found = 0 if how == "absent" else 2
    with pytest.raises(ValueError, match=rf"queries\.descriptor\[0, 0\] must name exactly one "
                                         rf"object token of its map .*; found {found}"):
        _TABLE_CALLS[call](model, _ill_posed(tokens, objects, how), queries)


def test_the_table_methods_still_answer_a_well_posed_query(scene_model):
    model, tokens, queries, _ = scene_model
    weights = np.asarray(model.table_weights(tokens, queries))
    np.testing.assert_allclose(weights.sum(-1), 1.0, atol=1e-5)
    np.testing.assert_array_equal(_TABLE_CALLS["weights"](model, tokens, queries), weights)


# --------------------------------------------------------- silent wrong answers


@pytest.fixture(scope="module")
def homes_model():
    """The packaged homes model, two short homes and three queries in each."""
    homes = generate_homes(jax.random.key(1), HOMES, 2)
    queries = HomesQueries(object_index=np.zeros((2, 3), np.int32),
                           tau=np.full((2, 3), 30, np.int32), tau_q=np.full((2, 3), 40, np.int32))
    return load_pretrained("flowmaps-homes"), homes, queries


_HOMES_CALLS = {
    "probabilities": lambda m, h, q: m.probabilities(h, q, HOMES),
    "sample": lambda m, h, q: m.sample(h, q, 2, jax.random.key(0), 2, config=HOMES),
}


@pytest.mark.parametrize("call", sorted(_HOMES_CALLS))
@pytest.mark.parametrize("field,change,message", [
    ("receptacle_box", lambda a: a.at[0, 0, 0].set(np.nan), "contains NaN or inf"),
    ("receptacle_distance", lambda a: a * 1e30, "must lie in"),
    ("home_size", lambda a: a.at[1, 0].set(np.inf), "contains NaN or inf"),
    ("room_box", lambda a: a * 1e6, "must lie in"),
])
def test_a_homes_model_refuses_non_finite_or_absurd_homes(homes_model, call, field, change,
                                                         message):
    model, homes, queries = homes_model
    bad = homes.replace(**{field: change(getattr(homes, field))})
    with pytest.raises(ValueError, match=rf"homes\.{field} {message}"):
        _HOMES_CALLS[call](model, bad, queries)


def test_a_homes_model_still_answers_valid_homes(homes_model):
    model, homes, queries = homes_model
    p = np.asarray(model.probabilities(homes, queries, HOMES))
    np.testing.assert_allclose(p.sum(-1), 1.0, atol=1e-5)


@pytest.fixture(scope="module")
def full_home():
    """A home whose 15 object slots are all used."""
    config = HomesConfig(num_hours=96, objects_per_home=(15, 15))
    home = generate_homes(jax.random.key(2), config, 1).home(0)
    assert bool(np.all(home.object_valid))
    return config, home


@pytest.mark.parametrize("index", [-1, 15, 1000])
def test_a_traced_object_index_out_of_range_gives_nans(full_home, index):
    config, home = full_home
    posterior = jax.jit(lambda i: homes_posterior(home, i, 3, 10, config))
    history = jax.jit(lambda i: homes_history_posterior(home, i, 30, 40, 24, config))
    matrix = jax.jit(lambda i: transition_matrix(home, i, 3, config))
    for fn in (posterior, history, matrix):
        assert np.all(np.isnan(np.asarray(fn(index)))), fn
    assert abs(float(posterior(14).sum()) - 1.0) < 1e-5  # the last slot still answers
    assert not np.any(np.isnan(np.asarray(matrix(14))))


def test_a_traced_hour_out_of_range_gives_nans(full_home):
    config, home = full_home
    matrix = jax.jit(lambda hour: transition_matrix(home, 0, hour, config))
    assert np.all(np.isnan(np.asarray(matrix(config.num_hours - 1))))
    assert np.all(np.isnan(np.asarray(matrix(-1))))
    assert not np.any(np.isnan(np.asarray(matrix(config.num_hours - 2))))


# ---------------------------------------------------------- raw errors, tracing


@pytest.mark.parametrize("rooms", [(["kitchen"],) * 6, ({"kitchen": 1},) * 6, "kitchen"])
def test_homes_config_refuses_unhashable_room_names(rooms):
    with pytest.raises(ValueError, match="rooms must be a non-empty tuple of room type names"):
        HomesConfig(rooms=rooms)


@pytest.mark.parametrize("call", sorted(_HOMES_CALLS))
def test_a_homes_model_refuses_no_queries_and_no_homes(homes_model, call):
    model, homes, queries = homes_model
    none = jax.tree.map(lambda a: a[:, :0], queries)
    with pytest.raises(ValueError, match=r"queries must hold at least one query per home"):
        _HOMES_CALLS[call](model, homes, none)
    with pytest.raises(ValueError, match=r"homes must hold at least one home; got 0"):
        _HOMES_CALLS[call](model, jax.tree.map(lambda a: a[:0], homes),
                           jax.tree.map(lambda a: a[:0], queries))


def _one_line_tracing_error(fn, *args):
    with pytest.raises(ValueError, match=r"takes concrete arrays.*outside jax\.jit") as info:
        fn(*args)
    assert "\n" not in str(info.value)


def test_a_homes_model_under_jit_says_it_takes_concrete_arrays(homes_model):
    model, homes, queries = homes_model
    _one_line_tracing_error(jax.jit(lambda h: model.probabilities(h, queries, HOMES)), homes)
    _one_line_tracing_error(jax.jit(lambda q: model.probabilities(homes, q, HOMES)), queries)
    _one_line_tracing_error(
        jax.jit(lambda k: model.sample(homes, queries, 2, k, 2, config=HOMES)), jax.random.key(0))


def test_a_scene_model_under_jit_says_it_takes_concrete_arrays(scene_model):
    model, tokens, queries, _ = scene_model
    _one_line_tracing_error(jax.jit(model.table_weights), tokens, queries)
    _one_line_tracing_error(jax.jit(lambda t: model.sample(t, queries, 2, jax.random.key(0))),
                            tokens)
    _one_line_tracing_error(jax.jit(lambda k: model.sample(tokens, queries, 2, k)),
                            jax.random.key(0))
    _one_line_tracing_error(jax.vmap(lambda d: model.validate(tokens, queries.replace(
        descriptor=d))), np.stack([queries.descriptor] * 2))
    _one_line_tracing_error(jax.jit(lambda t: model.table_probabilities(
        t, queries, 2, jax.random.key(0))), tokens)
