"""The exact reference rows of recorded data made from FlowSim homes (issue 47 item 6):
``worlds.recorded_references`` and ``evaluate --data``'s table."""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest
from support import run_python_in_process

from flowmaps_jax.evaluation import priors as pr
from flowmaps_jax.evaluation import realised
from flowmaps_jax.flowsim.homes import (
    REGIMES,
    HomesConfig,
    filtered_posterior,
    generate_homes,
    homes_history_posterior,
    homes_posterior,
)
from flowmaps_jax.recorded.format import Recorded, load_recorded, save_recorded
from flowmaps_jax.recorded.from_homes import from_homes
from flowmaps_jax.worlds import recorded as rw
from flowmaps_jax.worlds import recorded_references as refs

SEED, HOMES, HOURS = 4, 3, 72
CONFIG = HomesConfig(regime="mixed", num_hours=HOURS)  # what from-homes --hours 72 makes


def _from_homes(tmp_path_factory, mask: float):
    path = tmp_path_factory.mktemp("from_homes") / "data"
    code, out = run_python_in_process(
        ["-m", "flowmaps_jax.data", "from-homes", "--homes", str(HOMES), "--hours", str(HOURS),
         "--seed", str(SEED), "--mask", str(mask), "--out", str(path), "--no-progress"],
        path.parent)
    assert code == 0, out
    return path


@pytest.fixture(scope="module")
def full_dir(tmp_path_factory):
    return _from_homes(tmp_path_factory, 0.0)


@pytest.fixture(scope="module")
def masked_dir(tmp_path_factory):
    return _from_homes(tmp_path_factory, 0.3)


@pytest.fixture(scope="module")
def homes():
    return generate_homes(jax.random.key(SEED), CONFIG, HOMES)


def _queries(data, num: int = 12):
    queries, valid = realised.realised_queries(jax.random.key(1), data, num, 24)
    assert valid.all()
    return queries


def _original(homes, e: int, fn):
    """fn(home, slots, objects) on home e of the original homes, its numbering."""
    slots = np.flatnonzero(np.asarray(homes.receptacle_valid[e]))
    objects = np.flatnonzero(np.asarray(homes.object_valid[e]))
    return fn(homes.home(e), slots, objects)


def test_at_0_percent_the_rows_are_the_homes_posteriors_of_the_original_homes(full_dir, homes):
    recorded = load_recorded(full_dir)
    data = rw.recorded_homes(recorded, rw.homes_config_of(recorded))
    queries = _queries(data)
    rows, note, regime = refs.reference_rows(recorded.environments, data, queries)
    assert set(rows) == {refs.EXACT_ROW, refs.FILTER_ROW} and "seed 4, 3 homes" in note
    obj, tau, tau_q = (np.asarray(a) for a in (queries.object_index, queries.tau,
                                               queries.tau_q))
    for e in range(HOMES):
        for k in range(obj.shape[1]):
            def mapped(home, slots, objects, e=e, k=k):
                i, t, tq = int(objects[obj[e, k]]), int(tau[e, k]), int(tau_q[e, k])
                exact = homes_history_posterior(home, i, t, tq, min(168, t + 1), CONFIG)
                known = homes_posterior(home, i, t, tq, CONFIG)
                return np.asarray(exact)[slots], np.asarray(known)[slots]

            exact, known = _original(homes, e, mapped)
            n = len(exact)
            np.testing.assert_allclose(rows[refs.EXACT_ROW][e, k, :n], exact, atol=1e-6)
            np.testing.assert_allclose(rows[refs.FILTER_ROW][e, k, :n], known, atol=1e-6)
            assert np.all(rows[refs.EXACT_ROW][e, k, n:] == 0)
            objects = np.flatnonzero(np.asarray(homes.object_valid[e]))
            law = int(np.asarray(homes.regime)[e, objects[obj[e, k]]])
            assert regime[e, k] == REGIMES[law]  # the query's object's regime, by name


def test_with_masking_the_filter_sees_only_the_observed_hours(masked_dir, homes):
    recorded = load_recorded(masked_dir)
    data = rw.recorded_homes(recorded, rw.homes_config_of(recorded))
    queries = _queries(data)
    rows, _, _ = refs.reference_rows(recorded.environments, data, queries)
    obj, tau, tau_q = (np.asarray(a) for a in (queries.object_index, queries.tau,
                                               queries.tau_q))
    gap = 0.0
    for e, env in enumerate(recorded.environments):
        def mapped(home, slots, objects, e=e, env=env):
            observed = np.zeros((HOURS, CONFIG.max_objects), bool)
            observed[:, objects] = np.asarray(env.location) >= 0
            out = []
            for k in range(obj.shape[1]):
                i, t, tq = int(objects[obj[e, k]]), int(tau[e, k]), int(tau_q[e, k])
                out.append([np.asarray(filtered_posterior(home, i, observed, t, tq, CONFIG)),
                            np.asarray(homes_posterior(home, i, t, tq, CONFIG))])
            return np.asarray(out)[..., slots]

        want = _original(homes, e, mapped)
        n = want.shape[-1]
        np.testing.assert_allclose(rows[refs.FILTER_ROW][e, :, :n], want[:, 0], atol=1e-6)
        gap = max(gap, np.abs(want[:, 0] - want[:, 1]).max())
    assert gap > 0.05  # hidden hours change what the filter knows


def test_data_not_written_by_from_homes_gets_no_rows_and_a_reason(full_dir, homes):
    recorded = load_recorded(full_dir)
    envs = recorded.environments
    data = rw.recorded_homes(recorded, rw.homes_config_of(recorded))
    queries = _queries(data, 2)
    bare = from_homes(homes, CONFIG).environments  # the API: no generator seed
    other = dataclasses.replace(envs[0], source={"from": "a robot"})
    location = np.asarray(envs[1].location).copy()
    allowed = np.asarray(envs[1].allowed)
    m = int(np.flatnonzero(allowed.sum(1) > 1)[0])
    elsewhere = np.flatnonzero(allowed[m] & (np.arange(allowed.shape[1]) != location[5, m]))[0]
    location[5, m] = elsewhere
    edited = dataclasses.replace(envs[1], location=location)
    shifted = dataclasses.replace(envs[2], source={**envs[2].source, "home": 0})
    for environments, reason in (
            (bare, "no generator seed"),
            ((other, *envs[1:]), "is not FlowSim homes"),
            ((envs[0], edited, envs[2]), "is not its regenerated home"),
            ((*envs[:2], shifted), "is not its regenerated home")):
        rows, note, _ = refs.reference_rows(environments, data, queries)
        assert rows == {} and note.startswith("No exact reference rows: ") and reason in note


@pytest.mark.slow  # end to end: pytest -m slow (tests/conftest.py)
def test_evaluate_data_adds_the_rows_for_from_homes_data_and_says_why_not_otherwise(
        full_dir, homes, tmp_path):
    """The shipped homes model reads from-homes data (its vocabulary); the table gets the two
    exact rows, and says in one line when it cannot."""
    code, out = run_python_in_process(
        ["-m", "flowmaps_jax.evaluate", "--checkpoint", "pretrained:flowmaps-homes", "--data",
         str(full_dir), "--out", str(tmp_path / "e"), "--queries", "4", "--no-progress",
         "--no-figures"], tmp_path)
    assert code == 0, out
    results = json.loads((tmp_path / "e" / "results.json").read_text())
    assert list(results["posterior"])[:3] == ["FlowMaps", refs.EXACT_ROW, refs.FILTER_ROW]
    assert all(b["row"] not in (refs.EXACT_ROW, refs.FILTER_ROW, "FlowMaps")
               for b in results["best_reference"]["posterior"].values())
    assert results["protocol"]["references"].startswith("Exact reference rows")
    assert f"| {refs.FILTER_ROW} |" in out
    by_regime = results["posterior"]["FlowMaps"]["metrics"]["log_score"]["by_regime"]
    assert set(by_regime) <= set(REGIMES) and "by the object's regime" in out
    assert sum(v["count"] for v in by_regime.values()) == results["protocol"]["queries"]
    bare = tmp_path / "bare"
    save_recorded(Recorded(from_homes(homes, CONFIG).environments), bare)
    code, out = run_python_in_process(
        ["-m", "flowmaps_jax.evaluate", "--checkpoint", "pretrained:flowmaps-homes", "--data",
         str(bare), "--out", str(tmp_path / "b"), "--queries", "4", "--no-progress",
         "--no-figures"], tmp_path)
    assert code == 0, out
    results = json.loads((tmp_path / "b" / "results.json").read_text())
    assert refs.EXACT_ROW not in results["posterior"] and len(results["posterior"]) == 6
    assert {pr.COUNT_ROW, pr.STAY_ROW} <= set(results["posterior"])
    assert results["protocol"]["count_table"]["fitted_on"].startswith("the evaluated")
    best = results["best_reference"]["posterior"]  # per object class, no exact row, no model
    classes = results["posterior"]["FlowMaps"]["metrics"]["log_score"]["by_object_class"]
    assert list(best) == ["overall", *classes]
    assert {b["row"] for b in best.values()} <= set(results["posterior"]) - {"FlowMaps"}
    assert "No exact reference rows: " in (tmp_path / "b" / "results.md").read_text()
    assert "by_regime" not in results["posterior"]["FlowMaps"]["metrics"]["log_score"]


def test_the_test_part_lists_its_environments_in_the_homes_order(full_dir):
    recorded = load_recorded(full_dir)
    config = rw.homes_config_of(recorded)
    split = (0.0, 0.34, 0.25, 0)
    parts = rw.split(recorded, split)
    data, index = rw.part_of(recorded, config, parts, "test"), parts["test"][0]
    assert len(index) == data.num_homes == HOMES
    alone = rw.recorded_homes(recorded, config, index)
    np.testing.assert_array_equal(np.asarray(alone.homes.receptacle),
                                  np.asarray(data.homes.receptacle))
