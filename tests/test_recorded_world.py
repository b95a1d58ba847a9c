"""The recorded world (issue 47): a recorded dataset as the homes network's input, partial
observation in its inputs, train / evaluate / search with ``--data``."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support import run_python_in_process

from flowmaps_jax.flowsim.homes import HomesConfig, generate_homes
from flowmaps_jax.flowsim.homes.queries import HomesQueries
from flowmaps_jax.model import homes_inputs
from flowmaps_jax.recorded.format import Recorded, content_digest, load_recorded, save_recorded
from flowmaps_jax.recorded.from_homes import from_homes
from flowmaps_jax.training.config import (
    RecordedTrainConfig,
    config_from_stored,
    recorded_config,
)
from flowmaps_jax.worlds import WORLDS, world_of_files
from flowmaps_jax.worlds import recorded as rw

CONFIG = HomesConfig(regime="mixed", num_hours=72,
                     rooms=("kitchen", "living_room", "bedroom", "bathroom"),
                     objects_per_home=(4, 6))


@pytest.fixture(scope="module")
def data_dir(recorded_data):
    """3 FlowSim homes x 72 hours (``CONFIG``) as a recorded dataset, 30 % of the object-hours
    masked (the session's, tests/conftest.py)."""
    return recorded_data


@pytest.fixture(scope="module")
def recorded(data_dir):
    return load_recorded(data_dir)


@pytest.fixture(scope="module")
def cfg(data_dir):
    return recorded_config("smoke", str(data_dir))


def test_the_world_is_registered_and_reads_files():
    assert WORLDS["recorded"] is rw.WORLD and world_of_files() is rw.WORLD
    assert not WORLDS["homes"].reads_files


def test_the_config_comes_from_the_data_and_is_stored_with_the_run(cfg, recorded):
    homes = cfg.homes
    voc = recorded.vocabulary()
    assert [c.text for c in homes.object_classes][:len(voc["objects"])] == voc["objects"]
    assert homes.max_receptacles >= max(e.num_receptacles for e in recorded.environments)
    assert homes.max_objects == max(e.num_objects for e in recorded.environments)
    assert homes.num_hours == 72 and cfg.model.history_observed
    assert cfg.model.history + cfg.max_horizon <= 72
    stored = json.loads(json.dumps(cfg.to_dict()))
    assert stored["world"] == "recorded"
    assert config_from_stored(stored) == cfg  # resume rebuilds it
    assert stored["data_digest"] == content_digest(recorded)
    with pytest.raises(ValueError, match="--preset cpu"):
        recorded_config("cpu", cfg.data)
    with pytest.raises(ValueError, match="val_fraction"):
        dataclasses.replace(cfg, val_fraction=0.5, test_fraction=0.5)


def test_environments_become_valid_homes_with_their_observations(cfg, recorded):
    data = rw.recorded_homes(recorded, cfg.homes)  # validate_homes inside
    observed = np.asarray(data.observed)
    receptacle = np.asarray(data.homes.receptacle)
    for e, env in enumerate(recorded.environments):
        m = env.num_objects
        np.testing.assert_array_equal(observed[e, env.hours, :m], env.observed)
        seen = env.location >= 0
        np.testing.assert_array_equal(receptacle[e, env.hours, :m][seen], env.location[seen])
        # where an object is unseen, it stands where it was last seen
        t, i = np.argwhere(~seen & np.cumsum(seen, 0).astype(bool))[0]
        last = np.flatnonzero(seen[:t, i])[-1]
        assert receptacle[e, t, i] == env.location[last, i]
    assert 0.3 < observed[:, :, :4].mean() < 0.99  # masked, not empty


def test_environments_without_rooms_or_distances_read_as_homes(cfg, recorded):
    """The authors' layout has no rooms: the receptacles stand in a room spanning the home,
    distances Euclidean."""
    envs = tuple(dataclasses.replace(
        e, room_classes=(), room_boxes=None, door_rooms=None, door_positions=None,
        receptacle_room=np.full(e.num_receptacles, -1, np.int32), distance=None)
        for e in recorded.environments)
    bare = Recorded(environments=envs)
    config = rw.homes_config_of(bare)
    assert config.num_rooms >= 1 and [t.name for t in config.room_types] == ["none"]
    data = rw.recorded_homes(bare, config)
    size = np.asarray(data.homes.home_size)[0]
    np.testing.assert_allclose(np.asarray(data.homes.room_box)[0, 0], [0, 0, *size])
    data = rw.recorded_homes(bare, cfg.homes)  # a config with rooms reads it too
    assert np.all(np.asarray(data.homes.receptacle_room)[:, :8] == 0)


def test_a_vocabulary_that_does_not_cover_the_data_is_refused(cfg, recorded):
    env = recorded.environments[0]
    alien = dataclasses.replace(env, object_classes=("Alien", *env.object_classes[1:]))
    with pytest.raises(ValueError, match="no object class 'Alien'"):
        rw.recorded_homes(Recorded(environments=(alien,)), cfg.homes)


def test_the_split_is_seeded_by_environment_and_by_time(recorded):
    names = [f"env{i}" for i in range(10)]
    a = rw.split_environments(names, 0.2, 0.2, seed=1)
    assert a == rw.split_environments(names, 0.2, 0.2, seed=1)
    assert a != rw.split_environments(names, 0.2, 0.2, seed=2)
    assert sorted(a["train"] + a["val"] + a["test"]) == list(range(10))
    assert len(a["test"]) == len(a["val"]) == 2
    three = rw.split_environments(recorded.names(), 0.2, 0.2, seed=0)
    assert [len(three[p]) for p in rw.SPLITS] == [1, 1, 1]
    cut = rw.time_cut(recorded, [0], 0.25)
    assert cut[0] == 54  # the last quarter of 72 hours held out
    cfg = rw.homes_config_of(recorded)
    test = rw.part_of(recorded, cfg, rw.split(recorded, (0.2, 0.2, 0.25, 0)), "test")  # + train
    assert test.num_homes == 2 and list(np.asarray(test.start)) == [0, 54]


def test_training_batches_query_only_observed_targets(cfg, recorded):
    data = rw.part_of(recorded, cfg.homes, rw.split(recorded, (0.0, 0.0, 0.25, 0)), "train")
    batch = jax.jit(lambda k: rw.draw_batch(k, data, cfg))(jax.random.key(3))
    queries = rw.draw_queries(jax.random.key(3), jax.tree.map(lambda a: a[:3], data), 50,
                              cfg.max_horizon, cfg.default_horizon_frac)
    ok = np.asarray(rw.target_hours(data))
    e = np.arange(3)[:, None]
    assert ok[e, np.asarray(queries.tau_q), np.asarray(queries.object_index)].all()
    assert np.all(np.asarray(queries.tau_q) < 54)  # before the time cut
    horizon = np.asarray(queries.horizon)
    assert horizon.min() >= 1 and horizon.max() <= cfg.max_horizon
    assert batch.rows.shape[-1] == len(homes_inputs.ROW_FEATURES)
    assert batch.events.shape[-1] == cfg.model.history


def test_unseen_objects_carry_where_and_how_long_ago_they_were_seen(cfg, recorded):
    data = rw.recorded_homes(recorded, cfg.homes)
    observed = np.asarray(data.observed)
    e, t, i = (int(v) for v in np.argwhere(~observed[:, 10:60, :1])[0])
    t += 10
    last = np.flatnonzero(observed[e, :t + 1, i])
    queries = HomesQueries(object_index=np.full((3, 1), i, np.int32),
                           tau=np.full((3, 1), t, np.int32), tau_q=np.full((3, 1), t + 1, np.int32))

    @jax.jit  # one program for both masks
    def features(observed):
        events = homes_inputs.history_events(data.homes, queries, 24, observed)
        return homes_inputs.row_features(data.homes, queries, cfg.homes, events, observed)

    def rows(observed):
        return np.asarray(features(observed))

    f = rows(data.observed)[e, 0]
    names = homes_inputs.ROW_FEATURES
    allowed = f[:, names.index("allowed")] > 0
    unseen = f[allowed][:, [names.index(n) for n in names[-3:]]]
    ago = t - last[-1] if len(last) else t + 1
    np.testing.assert_allclose(unseen[0], [1.0, np.log1p(ago) / np.log1p(72),
                                           float(not len(last))], atol=1e-6)
    # every hour observed: the features of FlowSim homes, the last three 0
    full, none = rows(np.ones(data.observed.shape, bool)), rows(None)
    np.testing.assert_array_equal(full, none)
    assert np.all(none[..., -3:] == 0)


def test_realised_scores_break_ties_fairly():
    from flowmaps_jax.evaluation.realised import realised_scores, reliability

    allowed = np.array([[[True, True, True, False]]])
    uniform = allowed / 3.0
    s = realised_scores(uniform, np.array([[1]]), allowed)
    np.testing.assert_allclose([s["top1"][0, 0], s["rank"][0, 0], s["log_score"][0, 0]],
                               [1 / 3, 2.0, np.log(1 / 3)])
    sharp = np.array([[[0.7, 0.2, 0.1, 0.0]]])
    s = realised_scores(sharp, np.array([[2]]), allowed)
    assert s["top1"][0, 0] == 0 and s["rank"][0, 0] == 3 and s["top5"][0, 0] == 1
    table = reliability(sharp, np.array([[0]]), allowed, np.array([[True]]))
    assert sum(b["count"] for b in table["bins"]) == 3
    assert table["bins"][7]["realised"] == 1.0 and table["bins"][1]["realised"] == 0.0


@pytest.mark.slow  # end to end: pytest -m slow (tests/conftest.py)
def test_train_evaluate_and_search_with_data(data_dir, recorded_runs, tmp_path):
    run, out = recorded_runs.straight, recorded_runs.printed  # --preset smoke --data, 4 steps
    assert "train (1): " in out and "test (1): " in out  # the split, printed
    config = json.loads((run / "config.json").read_text())
    assert config["world"] == "recorded" and config["data"] == str(data_dir)
    assert isinstance(config_from_stored(config), RecordedTrainConfig)
    code, out = run_python_in_process(
        ["-m", "flowmaps_jax.evaluate", "--checkpoint", str(run), "--out",
         str(tmp_path / "eval"), "--queries", "8", "--no-progress"], tmp_path)
    assert code == 0, out
    results = json.loads((tmp_path / "eval" / "results.json").read_text())
    rows = results["posterior"]
    assert {"FlowMaps", "uniform over allowed", "last seen", "frequency prior"} <= set(rows)
    assert results["protocol"]["queries"] == 8 and "held-out test part" in results["part"]
    assert (tmp_path / "eval" / "reliability.png").exists()
    for row in rows.values():
        assert row["metrics"]["log_score"]["overall"]["mean"] <= 0
    code, out = run_python_in_process(
        ["-m", "flowmaps_jax.search", "--checkpoint", str(run), "--data", str(data_dir),
         "--out", str(tmp_path / "search"), "--queries", "4", "--no-progress"], tmp_path)
    assert code == 0, out
    nav = json.loads((tmp_path / "search" / "search.json").read_text())["navigation"]
    assert "FlowMaps, most-probable" in nav and "nearest first" in nav
    # the documented Python call (docs/data.md) answers as evaluate's own path does
    from flowmaps_jax.evaluation import realised
    from flowmaps_jax.predictor import load_model

    predictor, recorded = load_model(str(run)), load_recorded(data_dir)
    data = rw.recorded_homes(recorded, predictor.homes)
    queries, _ = realised.realised_queries(jax.random.key(5), data, 2, 24)
    rows = realised.row_probabilities(predictor, data, queries)[realised.MODEL_ROW]
    for e, env in enumerate(recorded.environments):
        for j in range(2):
            obj, tau, tau_q = (int(a[e, j]) for a in (queries.object_index, queries.tau,
                                                      queries.tau_q))
            got = rw.answer(predictor, str(data_dir), env.name, env.object_ids[obj], tau, tau_q)
            want = {env.receptacle_ids[r]: rows[e, j, r] for r in range(env.num_receptacles)
                    if rows[e, j, r] > 0}
            assert got.keys() == want.keys()
            np.testing.assert_allclose([got[k] for k in want], list(want.values()), atol=1e-6)
    with pytest.raises(ValueError, match="object_id"):
        rw.answer(predictor, recorded, recorded.environments[0].name, "no such", 30, 31)
    with pytest.raises(ValueError, match="observed is required"):
        predictor.probabilities(data.homes, queries, predictor.homes)


@pytest.mark.parametrize("args, message", [
    (["-m", "flowmaps_jax.train", "--data", "{missing}", "--preset", "smoke"], "--data"),
    (["-m", "flowmaps_jax.evaluate", "--checkpoint", "pretrained:flowmaps", "--data",
      "{data}", "--out", "{tmp}/e"], "--data needs a model of"),
    (["-m", "flowmaps_jax.search", "--checkpoint", "pretrained:flowmaps-homes", "--data",
      "{missing}", "--out", "{tmp}/s"], "--data"),
    (["-m", "flowmaps_jax.evaluate", "--checkpoint", "pretrained:flowmaps-homes", "--data",
      "{data}", "--out", "{tmp}/e", "--kl-draws", "7"], "--kl-draws does not apply"),
    (["-m", "flowmaps_jax.evaluate", "--checkpoint", "pretrained:flowmaps-homes", "--data",
      "{data}", "--out", "{tmp}/e", "--num-envs", "-1"], "--num-envs"),
    (["-m", "flowmaps_jax.search", "--checkpoint", "pretrained:flowmaps-homes", "--data",
      "{data}", "--out", "{tmp}/s", "--num-envs", "0"], "--num-envs"),
])
def test_bad_data_exits_2_with_one_line(args, message, data_dir, tmp_path):
    fill = {"missing": str(tmp_path / "nothing"), "data": str(data_dir), "tmp": str(tmp_path)}
    code, out = run_python_in_process([a.format(**fill) for a in args], tmp_path)
    assert code == 2, out
    assert message in out.strip().splitlines()[-1]


def test_the_shipped_homes_model_reads_homes_through_recorded_files_as_it_reads_them(
        tmp_path):
    """FlowSim homes -> recorded files -> homes again (0 % masked): the shipped homes model's
    probabilities are those on the original homes (receptacles and objects renumbered)."""
    from flowmaps_jax.predictor import load_pretrained

    model = load_pretrained("flowmaps-homes")
    homes = generate_homes(jax.random.key(5), model.homes, 2)
    save_recorded(from_homes(homes, model.homes), tmp_path / "data")
    data = rw.recorded_homes(load_recorded(tmp_path / "data"), model.homes)
    valid_o, valid_r = np.asarray(homes.object_valid), np.asarray(homes.receptacle_valid)
    tau = jnp.full((2, 3), 300, jnp.int32)
    tau_q = tau + jnp.asarray([1, 24, 168], jnp.int32)
    objects = np.stack([np.flatnonzero(v)[:3] for v in valid_o])
    p = np.asarray(model.probabilities(homes, HomesQueries(
        object_index=jnp.asarray(objects, jnp.int32), tau=tau, tau_q=tau_q)))
    q = np.asarray(model.probabilities(data.homes, HomesQueries(
        object_index=jnp.broadcast_to(jnp.arange(3, dtype=jnp.int32), (2, 3)), tau=tau,
        tau_q=tau_q)))
    for e in range(2):
        slots = np.flatnonzero(valid_r[e])
        np.testing.assert_allclose(q[e][:, :len(slots)], p[e][:, slots], atol=1e-5)


def test_a_checkpoint_whose_vocabulary_does_not_cover_the_data_exits_2(recorded, tmp_path):
    env = recorded.environments[0]
    alien = dataclasses.replace(env, object_classes=("Alien", *env.object_classes[1:]))
    save_recorded(Recorded(environments=(alien,)), tmp_path / "alien")
    code, out = run_python_in_process(
        ["-m", "flowmaps_jax.evaluate", "--checkpoint", "pretrained:flowmaps-homes", "--data",
         str(tmp_path / "alien"), "--out", str(tmp_path / "e")], tmp_path)
    assert code == 2, out
    last = out.strip().splitlines()[-1]
    assert last.startswith("error: --data: ") and "no object class 'Alien'" in last


def test_realised_figure_is_not_written_through_a_link(tmp_path):
    from flowmaps_jax.evaluation.realised import write_figure

    victim = tmp_path / "victim.png"
    victim.write_bytes(b"keep")
    out = tmp_path / "out"
    out.mkdir()
    (out / "reliability.png").symlink_to(victim)
    bins = [{"low": 0.0, "high": 1.0, "count": 1, "predicted": 0.5, "realised": 1.0}]
    results = {"posterior": {"FlowMaps": {"reliability": {"bins": bins, "ece": 0.5}}}}
    with pytest.raises(ValueError, match="symbolic link"):
        write_figure(results, out, "posterior")
    assert victim.read_bytes() == b"keep"


def test_an_environment_with_no_drawable_hour_is_refused(recorded, tmp_path):
    # seen once, at hour 0: no map hour has a target after it, so its queries would target
    # hours never observed (trained on silently before)
    envs = []
    for env in recorded.environments:
        location = np.full_like(env.location, -1)
        location[0] = env.location[0]
        envs.append(dataclasses.replace(env, location=location))
    path = tmp_path / "once"
    save_recorded(Recorded(tuple(envs)), path)
    cfg = recorded_config("smoke", str(path))
    with pytest.raises(ValueError, match=r"^data: training environment 'home.*max_horizon"):
        rw.splits(cfg, log=lambda line: None)


def test_a_copy_of_the_training_data_is_scored_on_its_test_part_and_changed_data_is_refused(
        cfg, recorded, data_dir, tmp_path):
    from flowmaps_jax.evaluation.realised import evaluation_part

    copy = tmp_path / "copy"
    save_recorded(recorded, copy)
    stored = cfg.to_dict()
    _, what, envs, _ = evaluation_part(load_recorded(copy), cfg.homes, stored, str(copy))
    assert "held-out test part" in what and len(envs) == 1  # not the training environments
    other = dict(stored, data_digest="0" * 64)
    _, what, envs, _ = evaluation_part(load_recorded(copy), cfg.homes, other, str(copy))
    assert what.startswith("all 3 environments (home0, home1, home2); ") and len(envs) == 3
    # a resume whose data changed under it is refused, naming the digest
    changed = dataclasses.replace(cfg, data_digest="0" * 64)
    with pytest.raises(ValueError, match=r"changed since the run began.*data_digest"):
        rw.splits(changed, log=lambda _: None)
    assert content_digest(load_recorded(copy)) == content_digest(recorded)
    moved = Recorded(environments=(dataclasses.replace(
        recorded.environments[0], location=np.roll(recorded.environments[0].location, 1, 0)),
        *recorded.environments[1:]))
    assert content_digest(moved) != content_digest(recorded)


def test_last_seen_is_uniform_for_an_object_not_yet_seen(cfg, recorded):
    from flowmaps_jax.evaluation.realised import LAST_SEEN, UNIFORM, reference_rows

    data = rw.recorded_homes(recorded, cfg.homes)
    observed = np.asarray(data.observed)
    never = np.cumsum(observed, axis=1) == 0  # (E, T, M) not yet seen up to t
    choice = np.asarray(data.homes.object_allowed).sum(-1) >= 2  # (E, M) uniform ≠ one place
    e, t, i = (int(v) for v in np.argwhere(never[:, :-1] & choice[:, None, :])[0])
    seen_e, seen_t, seen_i = (int(v) for v in np.argwhere(observed[:, :-1])[0])
    queries = HomesQueries(object_index=jnp.asarray([[i, seen_i]] * 3, jnp.int32),
                           tau=jnp.asarray([[t, seen_t]] * 3, jnp.int32),
                           tau_q=jnp.asarray([[t + 1, seen_t + 1]] * 3, jnp.int32))
    rows = reference_rows(data, queries, 24)
    np.testing.assert_array_equal(rows[LAST_SEEN][e, 0], rows[UNIFORM][e, 0])
    where = int(np.asarray(data.homes.receptacle)[seen_e, seen_t, seen_i])
    assert rows[LAST_SEEN][seen_e, 1, where] > 0.9  # seen: its receptacle at τ
