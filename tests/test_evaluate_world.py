"""Tests for the evaluation on FlowSim worlds with habits and histories (``--world`` /
``--history`` of ``python -m flowmaps_jax.evaluate``): the paper's routine protocol is untouched,
a habits world's eval set holds the exact posterior given the history, its extra reference rows
and one table per habit, and a model that reads several maps is given them.

Tiny models (``support.TINY``, one of them reading 2 maps) and a handful of environments.
"""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest
from support import TINY, perturb

from flowmaps_jax import evaluation as ev
from flowmaps_jax import model
from flowmaps_jax.evaluation.cli import main
from flowmaps_jax.evaluation.run import model_view
from flowmaps_jax.flowsim import HABITS, FlowSimConfig, validation_split
from flowmaps_jax.flowsim.dynamics import exact_posterior
from flowmaps_jax.flowsim.habits import (
    available_history,
    empirical_frequency,
    habit_family,
    history_posterior,
    observed_history,
)
from flowmaps_jax.flowsim.worlds import world_config
from flowmaps_jax.predictor import Predictor

SIM = FlowSimConfig()
MIXED = world_config("mixed", SIM)
NUM_ENVS = 8
COUNTS = (4,)
KL_DRAWS = 4
H2 = dataclasses.replace(TINY, history=2)


@pytest.fixture(scope="module")
def mixed_scenes():
    return validation_split(MIXED, num_envs=NUM_ENVS)


@pytest.fixture(scope="module")
def predictors():
    """A one-map and a two-map FlowMaps, perturbed so that their output depends on the map."""
    one = Predictor.from_params(perturb(model.init_params(jax.random.key(0), TINY),
                                        jax.random.key(1)), TINY)
    two = Predictor.from_params(perturb(model.init_params(jax.random.key(0), H2),
                                        jax.random.key(1)), H2)
    return one, two


@pytest.fixture(scope="module")
def mixed_report(mixed_scenes, predictors, tmp_path_factory):
    out = tmp_path_factory.mktemp("eval-mixed")
    results, rows, evalset = ev.run_evaluation(
        list(predictors), mixed_scenes, MIXED, out, seed=0, sample_counts=COUNTS,
        kl_draws=KL_DRAWS, chunk_envs=NUM_ENVS, likelihood_steps=None, figures=False,
        progress=False)
    return out, results, rows, evalset


def _flat(evalset):
    e, m = np.shape(evalset.obj)
    return (np.repeat(np.arange(e), m), np.tile(np.arange(m), e),
            np.repeat(np.asarray(evalset.tau), m), np.asarray(evalset.horizon).reshape(-1))


# --------------------------------------------------------------------------- the paper's world


def test_routine_world_with_one_map_is_the_papers_protocol():
    """History 1 in the routine world: no history fields, and q is exactly (bit for bit) the
    paper's ``exact_posterior``, not the history posterior (equal only up to rounding)."""
    scenes = validation_split(SIM, num_envs=NUM_ENVS)
    evalset = ev.build_eval_queries(scenes, SIM, jax.random.key(0), kl_draws=KL_DRAWS)
    assert evalset.habit is None and evalset.history is None
    assert evalset.exact_h1 is None and evalset.empirical is None
    want = exact_posterior(np.asarray(evalset.num_slots), np.asarray(evalset.slot_now),
                           np.asarray(evalset.horizon), SIM,
                           tau=np.asarray(evalset.tau)[:, None] + np.zeros((1, 3), np.int32))
    np.testing.assert_array_equal(np.asarray(evalset.slot_probs), np.asarray(want))
    assert [r.name for r in ev.reference_rows(evalset, COUNTS)] == list(ev.REFERENCE_ROWS)
    # ... and an H = 8 eval set of the same world: the same times, and (the routine being
    # Markov with a known habit) the same posterior up to rounding, all on the routine
    eight = ev.build_eval_queries(scenes, SIM, jax.random.key(0), kl_draws=KL_DRAWS, history=8)
    np.testing.assert_array_equal(eight.tau, evalset.tau)
    np.testing.assert_array_equal(eight.tau_q, evalset.tau_q)
    np.testing.assert_allclose(eight.slot_probs, evalset.slot_probs, atol=1e-5)
    assert eight.history == 8 and np.all(np.asarray(eight.habit) == HABITS.index("routine"))


def test_routine_report_has_no_habit_sections(predictors, tmp_path):
    scenes = validation_split(SIM, num_envs=NUM_ENVS)  # the scenes of the test above
    results, rows, evalset = ev.run_evaluation(
        [predictors[0]], scenes, SIM, tmp_path, sample_counts=COUNTS, kl_draws=KL_DRAWS,
        chunk_envs=NUM_ENVS, likelihood_steps=None, figures=False, progress=False)
    assert evalset.habit is None
    assert [r.name for r in rows] == [*ev.REFERENCE_ROWS, "FlowMaps"]
    assert "by_habit" not in results
    assert not {"world", "history", "habits"} & set(results["protocol"])
    text = (tmp_path / "results.md").read_text()
    assert "Habit" not in text and "World" not in text


# --------------------------------------------------------------------------- a habits world


def test_mixed_world_ground_truth_is_the_history_posterior(mixed_scenes):
    evalset = ev.build_eval_queries(mixed_scenes, MIXED, jax.random.key(0), kl_draws=KL_DRAWS,
                                    history=6)
    env, obj, tau, horizon = _flat(evalset)
    shape = np.shape(evalset.slot_probs)
    seen = available_history(tau, 6)
    assert np.any(seen < 6) and np.any(seen == 6)  # early queries see fewer maps
    want = history_posterior(mixed_scenes, MIXED, env, obj, tau, horizon, seen)
    np.testing.assert_allclose(evalset.slot_probs, np.reshape(want, shape), atol=1e-6)
    one = history_posterior(mixed_scenes, MIXED, env, obj, tau, horizon, 1)
    np.testing.assert_allclose(evalset.exact_h1, np.reshape(one, shape), atol=1e-6)
    slots, valid = observed_history(mixed_scenes, env, obj, tau, seen, max_history=6)
    np.testing.assert_allclose(evalset.empirical, np.reshape(
        empirical_frequency(slots, valid, MIXED.num_furniture), shape), atol=1e-6)
    np.testing.assert_array_equal(evalset.habit, habit_family(mixed_scenes, env, obj).reshape(
        shape[:2]))
    assert evalset.history == 6
    assert not np.allclose(evalset.slot_probs, evalset.exact_h1, atol=1e-3)  # history matters
    # the times are drawn as in the paper's protocol: the same for every history
    plain = ev.build_eval_queries(mixed_scenes, MIXED, jax.random.key(0), kl_draws=KL_DRAWS)
    np.testing.assert_array_equal(plain.tau_q, evalset.tau_q)
    assert plain.history == 1 and plain.exact_h1 is None  # H = 1: the history rows are q, last-seen
    # take keeps the history fields with the environments
    part = evalset.take(np.array([3, 1]))
    np.testing.assert_array_equal(part.habit, np.asarray(evalset.habit)[[3, 1]])
    np.testing.assert_array_equal(part.empirical, np.asarray(evalset.empirical)[[3, 1]])
    assert part.history == 6


def test_mixed_report_rows_and_habit_tables(mixed_report):
    out, results, rows, evalset = mixed_report
    names = [r.name for r in rows]
    assert names == ["oracle", "oracle samples", "smoothed-q samples", "exact, H = 1",
                     "empirical frequency, H = 8", "last-seen", "uniform", "FlowMaps (H = 1)",
                     "FlowMaps (H = 2)"]
    assert evalset.history == 8  # the default: 8 in a world with habits
    assert results["protocol"]["world"] == "mixed" and results["protocol"]["history"] == 8
    by_row = {r.name: r for r in rows}
    np.testing.assert_allclose(by_row["exact, H = 1"].slots[4]["p_hat"][..., :-1],
                               evalset.exact_h1, atol=1e-6)
    habit = np.asarray(evalset.habit)
    by_habit = results["by_habit"]
    assert list(by_habit) == [HABITS[h] for h in np.unique(habit)]
    assert len(by_habit) >= 2  # the fixture's objects follow more than one habit
    assert sum(part["count"] for part in by_habit.values()) == evalset.num_queries
    model_row = by_row["FlowMaps (H = 2)"]
    for name, part in by_habit.items():
        sel = habit == HABITS.index(name)
        assert part["count"] == int(sel.sum())
        assert list(part["rows"]) == names
        oracle = part["rows"]["oracle"]
        assert oracle["slots"]["4"]["tv"]["mean"] == pytest.approx(0.0, abs=1e-6)
        assert oracle["kl"]["mean"] == pytest.approx(0.0, abs=1e-5)
        got = part["rows"]["FlowMaps (H = 2)"]
        assert got["kl"]["mean"] == pytest.approx(float(np.mean(model_row.kl[sel])), rel=1e-5)
        for metric in ev.SLOT_METRICS:
            assert got["slots"]["4"][metric]["mean"] == pytest.approx(
                float(np.mean(model_row.slots[4][metric][sel])), rel=1e-5, abs=1e-7)
        assert got["slots"]["4"]["off"]["mean"] == pytest.approx(
            float(np.mean(model_row.slots[4]["p_hat"][..., -1][sel])), abs=1e-7)
    data = json.loads((out / "results.json").read_text())
    assert data["by_habit"] == json.loads(json.dumps(by_habit))
    text = (out / "results.md").read_text()
    for name, part in by_habit.items():
        assert f"## Habit: {name} ({part['count']} queries, @4)" in text
    assert "World: mixed" in text and "H = 8" in text
    # the figures show the models only, not the history's reference rows
    fig = ev.plot_kl(results)
    labels = [t.get_text() for t in fig.axes[0].get_xticklabels()]
    assert labels == ["FlowMaps (H = 1)", "FlowMaps (H = 2)"]


def test_a_history_model_reads_its_maps(mixed_scenes, predictors, mixed_report):
    """The two-map model's row is scored on tokens of its last 2 maps (with ``age``), not on the
    eval set's one-map tokens: it equals an evaluation on those tokens and differs from one on
    the one-map tokens."""
    _, _, rows, evalset = mixed_report
    two = predictors[1]
    view = model_view(evalset, mixed_scenes, MIXED, two)
    tokens = view.tokens
    assert evalset.tokens.age is None and tokens.age is not None
    f, m = MIXED.num_furniture, MIXED.num_objects
    past = np.asarray(evalset.tau) >= 1
    np.testing.assert_array_equal(np.asarray(tokens.mask).sum(-1), f + m + m * past)
    np.testing.assert_array_equal(np.asarray(tokens.age)[:, f + m:f + 2 * m], 1)
    np.testing.assert_array_equal(view.slot_probs, evalset.slot_probs)  # the same ground truth
    assert model_view(evalset, mixed_scenes, MIXED, predictors[0]) is evalset
    row = next(r for r in rows if r.name == "FlowMaps (H = 2)")
    key = jax.random.key(0)
    again = ev.evaluate_predictor(two, view, key, COUNTS, chunk_envs=NUM_ENVS,
                                  likelihood_steps=None, progress=False)
    np.testing.assert_allclose(again.samples, row.samples, atol=1e-5)
    np.testing.assert_allclose(again.kl, row.kl, rtol=1e-4, atol=1e-4)
    blind = ev.evaluate_predictor(two, evalset, key, COUNTS, chunk_envs=NUM_ENVS,
                                  likelihood_steps=None, progress=False)
    assert np.max(np.abs(blind.samples - row.samples)) > 1e-3


def test_default_history_and_bad_history(mixed_scenes, predictors):
    one, two = predictors
    assert ev.default_history([one], SIM) == 1
    assert ev.default_history([one, two], SIM) == 2
    assert ev.default_history([one, two], MIXED) == 8
    with pytest.raises(ValueError, match="history"):
        ev.build_eval_queries(mixed_scenes, MIXED, jax.random.key(0), history=0)
    with pytest.raises(ValueError, match="history"):
        ev.run_evaluation([one], mixed_scenes, MIXED, history=SIM.num_timesteps + 1,
                          progress=False)


# --------------------------------------------------------------------------- CLI


def test_cli_refuses_a_bogus_world_cleanly(tmp_path, capsys):
    code = main(["--checkpoint", "pretrained:flowmaps", "--world", "bogus", "--out",
                 str(tmp_path), "--no-progress"])
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --world must be one of") and "bogus" in err
    assert "Traceback" not in err
    assert main(["--checkpoint", "pretrained:flowmaps", "--history", "0", "--out",
                 str(tmp_path)]) == 2
    assert "--history" in capsys.readouterr().err


@pytest.mark.slow  # end to end: pytest -m slow (tests/conftest.py)
def test_cli_evaluates_a_history_model_on_another_world(tmp_path, capsys):
    """A two-map checkpoint trained on the routine world, evaluated on the preferences world
    with ``--history 3``: the world's scenes, its habit table, the model's own 2 maps."""
    from flowmaps_jax.store.checkpoint_store import CheckpointStore
    from flowmaps_jax.training import state as train_state
    from flowmaps_jax.training.config import get_preset

    run = tmp_path / "run"
    cfg = dataclasses.replace(get_preset("smoke"), model=H2)
    with CheckpointStore(run / "checkpoints", keep_last=1) as store:
        store.save(train_state.init_state(cfg), cfg.to_dict())
    out = tmp_path / "eval"
    # NUM_ENVS environments in one chunk, as mixed_report: the same compiled programs
    code = main(["--checkpoint", str(run), "--world", "preferences", "--history", "3",
                 "--num-envs", str(NUM_ENVS), "--samples", "4", "--kl-draws", "4",
                 "--likelihood-steps", "0", "--no-figures", "--no-progress", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    data = json.loads((out / "results.json").read_text())
    assert data["protocol"]["world"] == "preferences" and data["protocol"]["history"] == 3
    assert list(data["by_habit"]) == ["preferences"]
    assert data["by_habit"]["preferences"]["count"] == NUM_ENVS * SIM.num_objects
    assert {"exact, H = 1", "empirical frequency, H = 3", "FlowMaps (H = 2)"} <= set(data["rows"])
    printed = capsys.readouterr().out
    assert "of the preferences world" in printed
    assert f"## Habit: preferences ({NUM_ENVS * SIM.num_objects} queries, @4)" in printed
    assert "route offsets" not in printed  # no object on a routine: no routine diagnostic


def test_the_size_check_counts_a_history_models_own_tokens(monkeypatch):
    """The evaluate CLI's work estimate uses each model's token count: 34 for a model reading
    8 maps, 20 for a one-map model, whatever the evaluation config's own count is."""
    import argparse
    import types

    from flowmaps_jax.evaluation import cli

    seen = []
    real = cli.network_flops
    monkeypatch.setattr(cli, "network_flops",
                        lambda net, tokens, gaussian: seen.append(tokens) or real(net, tokens,
                                                                                 gaussian))
    sim = FlowSimConfig()
    wide = dataclasses.replace(sim, max_tokens=34)
    models = [types.SimpleNamespace(model=dataclasses.replace(TINY, history=8),
                                    family_name="flowmaps",
                                    flowsim=wide),
              types.SimpleNamespace(model=TINY, family_name="flowmaps", flowsim=sim)]
    args = argparse.Namespace(kl_draws=4, samples=[8], chunk_envs=4, num_steps=8,
                              logp_steps=None, method="euler", likelihood_steps=0)
    cli.check_size(models, 4, sim, args)
    assert seen == [34, 20]
