"""Tests for flowmaps_jax.evaluation's protocol, report, figures and CLI: the protocol's queries,
reference rows with known answers, the wiring of model rows, the report and figures, and
``python -m flowmaps_jax.evaluate`` on a freshly trained checkpoint. The CLI on the shipped
models (``--checkpoint pretrained:flowmaps --baseline pretrained:mlp ...``, docs/results.md's
table) is README.md's command, run by tests/test_docs_commands.py; loading them by name is
tests/test_pretrained.py's.

Tiny models and a handful of environments; compiled functions are shared through module fixtures.
"""

from __future__ import annotations

import dataclasses
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support import TINY, mixture_log_density

from flowmaps_jax import evaluation as ev
from flowmaps_jax import model
from flowmaps_jax.evaluation.cli import main
from flowmaps_jax.flowsim import FlowSimConfig, normalise_boxes, validation_split
from flowmaps_jax.predictor import Predictor

SIM = FlowSimConfig()
CFG = TINY  # shared with test_sample: compiled sampling code is reused
NUM_ENVS = 6
COUNTS = (4, 8)
KL_DRAWS = 8


@pytest.fixture(scope="module")
def scenes():
    return validation_split(SIM, num_envs=NUM_ENVS)


@pytest.fixture(scope="module")
def evalset(scenes):
    return ev.build_eval_queries(scenes, SIM, jax.random.PRNGKey(0), kl_draws=KL_DRAWS)


@pytest.fixture(scope="module")
def predictors():
    flow = Predictor.from_params(model.init_params(jax.random.PRNGKey(0), CFG), CFG)
    mlp = Predictor.from_params(model.init_baseline(jax.random.PRNGKey(1), CFG), CFG,
                                family_name="mlp")
    return mlp, flow


@pytest.fixture(scope="module")
def report(scenes, predictors, tmp_path_factory):
    out = tmp_path_factory.mktemp("eval")
    results, rows, evalset = ev.run_evaluation(
        list(predictors), scenes, SIM, out, seed=0, sample_counts=COUNTS, kl_draws=KL_DRAWS,
        chunk_envs=4, progress=False)
    return out, results, rows, evalset


# --------------------------------------------------------------------------- the query set


def test_queries_follow_the_protocol(scenes, evalset):
    e, m, f = NUM_ENVS, SIM.num_objects, SIM.num_furniture
    tau, tau_q = np.asarray(evalset.tau), np.asarray(evalset.tau_q)
    assert evalset.num_queries == e * m
    assert np.all((tau >= 0) & (tau <= SIM.num_timesteps - 2))
    assert np.all((tau_q > tau) & (tau_q <= SIM.num_timesteps - 1))
    np.testing.assert_array_equal(evalset.queries.tau_q, np.repeat(tau_q[:, None], m, 1))
    np.testing.assert_array_equal(evalset.queries.descriptor, scenes.object_kind)
    np.testing.assert_array_equal(evalset.horizon, np.repeat((tau_q - tau)[:, None], m, 1))
    np.testing.assert_array_equal(evalset.tokens.tau, tau)
    q = np.asarray(evalset.slot_probs)
    assert q.shape == (e, m, f)
    np.testing.assert_allclose(q.sum(-1), 1.0, atol=1e-5)
    assert np.all(q[~np.asarray(evalset.slot_mask)] == 0)
    assert evalset.kl_points.shape == (e, m, KL_DRAWS, 4)
    points, boxes = np.asarray(evalset.kl_points), np.asarray(evalset.slot_boxes)
    log_q = np.asarray(evalset.kl_log_q)
    for i, j in np.ndindex(e, m):  # log q of each query's own mixture at its own draws
        np.testing.assert_allclose(log_q[i, j], mixture_log_density(points[i, j], q[i, j],
                                                                    boxes[i, j]),
                                   rtol=1e-4, atol=1e-3)


def test_slot_boxes_are_where_the_object_really_is(scenes, evalset):
    """b at the slot observed at τ is the object's box at τ and the object's token in the map the
    model is given, and the box at τ_q is one of the b_k that q gives positive probability."""
    env = np.asarray(evalset.env)
    boxes = np.asarray(evalset.slot_boxes)
    now = np.take_along_axis(boxes, np.asarray(evalset.slot_now)[..., None, None], axis=2)[:, :, 0]
    at_tau = normalise_boxes(np.asarray(scenes.object_boxes)[env, np.asarray(evalset.tau)], SIM)
    np.testing.assert_allclose(now, at_tau, atol=1e-6)
    # ... and it is what the model sees: the one object token with the query's descriptor
    tokens, desc = evalset.tokens, np.asarray(evalset.queries.descriptor)
    is_obj = np.asarray(tokens.mask) & (np.asarray(tokens.kind) == 1)  # (E, S)
    match = is_obj[:, None, :] & (np.asarray(tokens.descriptor)[:, None, :] == desc[..., None])
    assert np.all(match.sum(-1) == 1)
    seen = np.take_along_axis(np.asarray(tokens.boxes), match.argmax(-1)[..., None], axis=1)
    np.testing.assert_allclose(seen, now, atol=1e-6)
    slot_q = np.asarray(scenes.slot)[env, np.asarray(evalset.tau_q)]  # (E, M)
    at_tau_q = np.take_along_axis(boxes, slot_q[..., None, None], axis=2)[:, :, 0]
    np.testing.assert_allclose(at_tau_q, evalset.target, atol=1e-6)
    q_true = np.take_along_axis(np.asarray(evalset.slot_probs), slot_q[..., None], axis=2)
    assert np.all(q_true > 0)


# --------------------------------------------------------------------------- reference rows


def test_reference_rows_have_their_known_values(evalset):
    oracle, sampled, smoothed, last_seen, uniform = ev.reference_rows(evalset, COUNTS)
    q = np.asarray(evalset.slot_probs)
    assert tuple(r.name for r in (oracle, sampled, smoothed, last_seen, uniform)) == \
        ev.REFERENCE_ROWS
    # KL on the shared draws, a slot row's density being the mixture with the row's weights:
    # recomputed in float64 from the draws (q itself for the oracle and oracle samples)
    points, boxes = np.asarray(evalset.kl_points), np.asarray(evalset.slot_boxes)
    for row in (oracle, sampled, smoothed, last_seen, uniform):
        weights = q if row in (sampled, smoothed) else row.slots[COUNTS[0]]["p_hat"][..., :-1]
        for i, j in np.ndindex(q.shape[:2]):
            x, b = points[i, j], boxes[i, j]
            want = np.mean(mixture_log_density(x, q[i, j], b)
                           - mixture_log_density(x, weights[i, j], b))
            assert row.kl[i, j] == pytest.approx(want, rel=1e-4, abs=1e-3), (row.name, i, j)
    for n in COUNTS:  # n draws from q: histograms in steps of 1/n, nothing off, never above 1
        p_hat = sampled.slots[n]["p_hat"]
        np.testing.assert_allclose(p_hat * n, np.round(p_hat * n), atol=1e-4)
        np.testing.assert_allclose(p_hat[..., -1], 0.0)
        assert np.all(p_hat[..., :-1][~np.asarray(evalset.slot_mask)] == 0.0)
        assert np.all(sampled.slots[n]["tv"] > -1e-6) and np.all(sampled.slots[n]["tv"] < 1.0)
    assert np.mean(sampled.slots[COUNTS[-1]]["tv"]) < np.mean(sampled.slots[COUNTS[0]]["tv"])
    for n in COUNTS:
        np.testing.assert_allclose(oracle.slots[n]["tv"], 0.0, atol=1e-6)
        np.testing.assert_allclose(oracle.slots[n]["top1"], 1.0)
        np.testing.assert_allclose(oracle.slots[n]["search_cost_ratio"], 1.0, rtol=1e-6)
    q_now = np.take_along_axis(q, np.asarray(evalset.slot_now)[..., None], axis=-1)[..., 0]
    np.testing.assert_allclose(last_seen.slots[COUNTS[0]]["tv"], 1.0 - q_now, atol=1e-6)
    k = np.asarray(evalset.num_slots)[..., None]
    expected_tv = 0.5 * np.sum(np.where(np.asarray(evalset.slot_mask), np.abs(1.0 / k - q), 0.0),
                               -1)
    np.testing.assert_allclose(uniform.slots[COUNTS[0]]["tv"], expected_tv, atol=1e-6)
    # a predictor that ignores the dynamics is worse than the truth, in KL and search cost
    assert np.mean(last_seen.kl) > 1.0 and np.mean(uniform.kl) > 0.0
    assert np.all(last_seen.slots[COUNTS[0]]["search_cost_ratio"] >= 1.0 - 1e-6)


class _LastSeenSampler:
    """Stand-in model: every sample is exactly the box at the slot observed at τ (b_{slot now}),
    and its density is the ground-truth mixture q. So its KL must be 0 and its slot metrics must
    be exactly the last-seen row's — a check of how evaluate_predictor wires samples and
    likelihoods to the metrics. Used with one chunk holding every environment, in order."""

    family_name, source, step, name = "stand-in", None, None, "stand-in"

    def __init__(self, evalset):
        self.evalset = evalset

    def _check(self, tokens):
        np.testing.assert_array_equal(tokens.tau, self.evalset.tau)

    def sample(self, tokens, queries, num_samples, key, **_):
        self._check(tokens)
        e = self.evalset
        now = jnp.take_along_axis(e.slot_boxes, e.slot_now[..., None, None], axis=2)
        return jnp.repeat(now, num_samples, axis=2)

    def log_prob(self, tokens, queries, x, **_):
        self._check(tokens)
        e = self.evalset
        return ev.gt_mixture_log_prob(x, e.slot_probs, e.slot_boxes, e.slot_mask)


def test_samples_and_likelihoods_reach_the_right_metrics(evalset):
    row = ev.evaluate_predictor(_LastSeenSampler(evalset), evalset, jax.random.PRNGKey(0),
                                sample_counts=COUNTS, chunk_envs=NUM_ENVS, progress=False)
    np.testing.assert_allclose(row.kl, 0.0, atol=1e-5)
    last_seen = ev.reference_rows(evalset, COUNTS)[3]
    for n in COUNTS:
        for metric in ("p_hat", *ev.SLOT_METRICS):
            np.testing.assert_allclose(row.slots[n][metric], last_seen.slots[n][metric],
                                       atol=1e-6, err_msg=metric)
    assert row.samples.shape == (NUM_ENVS, SIM.num_objects, COUNTS[-1], 4)


# --------------------------------------------------------------------------- model rows, report


def test_model_rows_do_not_depend_on_the_chunking(evalset, predictors, report):
    """An environment's samples and KL are the same whichever chunk (and position) it is in."""
    _, _, rows, _ = report
    order = np.array([4, 5, 0, 1])  # other chunk neighbours and positions than in the report
    again = ev.evaluate_predictor(predictors[1], evalset.take(order), jax.random.PRNGKey(0),
                                  COUNTS, chunk_envs=4, progress=False)
    first = next(r for r in rows if r.name == "FlowMaps")
    np.testing.assert_allclose(again.samples, first.samples[order], atol=1e-5)
    np.testing.assert_allclose(again.kl, first.kl[order], rtol=1e-4, atol=1e-4)


def test_report_files_and_contents(report):
    out, _, rows, evalset = report
    assert [r.name for r in rows] == ["oracle", "oracle samples", "smoothed-q samples",
                                      "last-seen", "uniform", "MLP (mean)", "FlowMaps"]
    data = json.loads((out / "results.json").read_text())
    assert data["protocol"]["num_queries"] == NUM_ENVS * SIM.num_objects
    assert data["protocol"]["samples"] == list(COUNTS)
    assert list(data["rows"]) == [r.name for r in rows]
    flow = data["rows"]["FlowMaps"]
    assert set(flow["kl"]) == {"overall", "by_category", "by_horizon"}
    assert list(flow["kl"]["by_category"]) == ["fork", "bottle", "remote"]
    horizons = sorted({int(h) for h in np.asarray(evalset.horizon).ravel()})
    assert sorted(int(h) for h in flow["kl"]["by_horizon"]) == horizons
    assert flow["kl"]["overall"]["count"] == NUM_ENVS * SIM.num_objects
    assert set(flow["slots"]) == {str(n) for n in COUNTS}
    assert set(flow["slots"]["8"]) == set(ev.SLOT_METRICS)
    assert data["rows"]["oracle"]["kl"]["overall"]["mean"] == pytest.approx(0.0, abs=1e-5)
    np.testing.assert_allclose(flow["kl"]["overall"]["mean"], np.mean(rows[-1].kl), rtol=1e-5)
    text = (out / "results.md").read_text()
    for name in data["rows"]:
        assert f"| {name} |" in text
    assert "by horizon" in text and "by category" in text
    for figure in ("kl.png", "by_horizon.png", "samples.png", "slots.png"):
        assert figure in data["figures"]
        assert (out / figure).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert (out / figure).stat().st_size > 10_000


def test_route_offset_table_matches_the_one_step_queries(report):
    """The routine table: the oracle row is exactly 0.2 / 0.7 / 0.1 one step ahead and last-seen
    puts everything at offset 0, over the protocol's Δτ = 1 queries."""
    out, _, _, evalset = report
    data = json.loads((out / "results.json").read_text())
    one_step = int(np.sum(np.asarray(evalset.horizon) == 1))
    oracle = data["rows"]["oracle"]["route_offsets_one_step"]
    assert one_step > 0  # environment 3 of the fixture is queried one step ahead
    assert oracle["labels"] == list(ev.ROUTE_OFFSET_LABELS) and oracle["count"] == one_step
    np.testing.assert_allclose(oracle["mean"], [0.2, 0.7, 0.1, 0, 0, 0], atol=1e-5)
    np.testing.assert_allclose(data["rows"]["last-seen"]["route_offsets_one_step"]["mean"],
                               [1, 0, 0, 0, 0, 0], atol=1e-6)
    assert "route offsets one step ahead" in (out / "results.md").read_text()


def test_summarise_overall_and_by_group():
    values = np.array([1.0, 3.0, 2.0, 4.0, 10.0])
    out = ev.summarise(values, np.array([1, 1, 2, 2, 3]))
    assert out["overall"]["mean"] == pytest.approx(4.0)
    assert out["overall"]["stderr"] == pytest.approx(np.std(values, ddof=1) / math.sqrt(5))
    assert out["overall"]["count"] == 5
    assert out["by_group"][1] == {"mean": 2.0, "stderr": pytest.approx(1.0), "count": 2}
    assert out["by_group"][2]["mean"] == pytest.approx(3.0)
    assert math.isnan(out["by_group"][3]["stderr"])
    assert set(ev.summarise(values, np.array(list("aabbc")))["by_group"]) == {"a", "b", "c"}
    assert "by_group" not in ev.summarise(values)
    with pytest.raises(ValueError, match="groups"):
        ev.summarise(np.zeros(3), np.zeros(2))


def test_picked_queries_are_fork_remote_bottle_in_the_future(evalset):
    picks = ev.pick_queries(evalset, SIM)
    names = [SIM.categories[m].name for _, m in picks]
    assert names == ["fork", "remote", "bottle"]
    horizon = np.asarray(evalset.horizon)
    for e, m in picks:
        if np.any((horizon[:, m] >= 2) & (horizon[:, m] <= 4)):
            assert 2 <= horizon[e, m] <= 4  # a few steps ahead: multimodal, not yet uniform


def test_bad_arguments(scenes, evalset, predictors):
    with pytest.raises(ValueError, match="kl_draws"):
        ev.build_eval_queries(scenes, SIM, jax.random.PRNGKey(0), kl_draws=1)
    with pytest.raises(ValueError, match="sample_counts"):
        ev.evaluate_predictor(predictors[1], evalset, jax.random.PRNGKey(0), sample_counts=())
    with pytest.raises(ValueError, match="predictors"):
        ev.run_evaluation([], scenes, SIM)
    other = dataclasses.replace(SIM, map_size=300)
    with pytest.raises(ValueError, match="different FlowSim config"):
        ev.run_evaluation([predictors[1]], scenes, other)


# --------------------------------------------------------------------------- CLI


def test_cli_reports_bad_input_without_a_traceback(tmp_path, capsys):
    assert main(["--checkpoint", str(tmp_path / "nowhere"), "--no-progress"]) == 2
    assert "does not exist" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--checkpoint", str(tmp_path), "--samples", "0,x"])
    assert main(["--checkpoint", "pretrained:flowmap", "--out", str(tmp_path)]) == 2
    assert "mlp-learned" in capsys.readouterr().err  # the error lists the shipped names
    assert main(["--checkpoint", "pretrained:flowmaps", "--no-progress"]) == 2
    assert "--out is required" in capsys.readouterr().err


def test_cli_refuses_an_out_that_is_a_file_before_loading_anything(tmp_path, capsys):
    taken = tmp_path / "results"
    taken.write_text("not a directory")
    assert main(["--checkpoint", str(tmp_path / "nowhere"), "--out", str(taken)]) == 2
    err = capsys.readouterr().err
    assert "--out" in err and "is a file" in err and "nowhere" not in err


def test_non_finite_samples_are_refused_not_scored(evalset, predictors):
    """A diverged model (NaN parameters) is an error naming the row, not a table of NaN."""
    _, flow = predictors
    diverged = Predictor.from_params(jax.tree.map(lambda a: a * jnp.nan, flow.params), CFG)
    with pytest.raises(ValueError, match=r"FlowMaps.*non-finite"):
        ev.evaluate_predictor(diverged, evalset, jax.random.key(0), COUNTS, chunk_envs=4,
                              progress=False)


@pytest.mark.slow  # end to end: pytest -m slow (tests/conftest.py)
def test_evaluate_cli_on_saved_checkpoints(tmp_path, capsys):
    """``python -m flowmaps_jax.evaluate`` on a FlowMaps and an MLP checkpoint as training saves
    them (training through the CLI is tests/test_training.py's; here the states are fresh)."""
    from flowmaps_jax.store.checkpoint_store import CheckpointStore
    from flowmaps_jax.training import state as train_state
    from flowmaps_jax.training.config import get_preset

    run = tmp_path / "flow"
    for kind, where, step in (("flowmaps", run / "checkpoints", 4), ("mlp", tmp_path / "mlp", 0)):
        cfg = dataclasses.replace(get_preset("smoke"), model=CFG, family=kind)
        state = train_state.init_state(cfg).replace(step=jnp.asarray(step, jnp.int32))
        with CheckpointStore(where, keep_last=1) as store:
            store.save(state, cfg.to_dict())
    out = tmp_path / "eval"
    code = main(["--checkpoint", str(run), "--baseline", str(tmp_path / "mlp"),
                    "--out", str(out), "--num-envs", str(NUM_ENVS), "--samples", "4,8",
                    "--kl-draws", str(KL_DRAWS), "--chunk-envs", "4", "--no-progress",
                    "--no-figures"])
    assert code == 0, capsys.readouterr().err
    data = json.loads((out / "results.json").read_text())
    assert list(data["rows"]) == ["oracle", "oracle samples", "smoothed-q samples", "last-seen",
                                  "uniform", "MLP (mean)", "FlowMaps"]
    assert data["rows"]["FlowMaps"]["info"]["step"] == 4
    assert data["rows"]["FlowMaps"]["info"]["source"] == str(run / "checkpoints")
    assert data["protocol"]["num_queries"] == NUM_ENVS * SIM.num_objects
    assert "FlowMaps" in capsys.readouterr().out
