"""Recorded format v2 (issue 56): negative evidence (``not_at``) and scene graphs without
geometry load, train, evaluate and search; v1 datasets load unchanged. One load per run (issue
55): that training reads, digests and splits its dataset once, and its evaluation reads the run's
stored config once and the data once."""

from __future__ import annotations

import collections
import dataclasses
import functools
import json
import zipfile

import jax
import numpy as np
import pytest
from support import run_python_in_process

from flowmaps_jax.flowsim.homes import HomesConfig, generate_homes
from flowmaps_jax.flowsim.homes.queries import HomesQueries
from flowmaps_jax.model import homes_inputs
from flowmaps_jax.recorded import format as fmt
from flowmaps_jax.recorded.format import Environment, Recorded, load_recorded, save_recorded
from flowmaps_jax.recorded.from_homes import from_homes
from flowmaps_jax.store import checkpoints
from flowmaps_jax.training.config import recorded_config
from flowmaps_jax.worlds import recorded as rw

CONFIG = HomesConfig(regime="mixed", num_hours=72,
                     rooms=("kitchen", "living_room", "bedroom", "bathroom"),
                     objects_per_home=(4, 6))


def _graph(full: Environment, masked: Environment, rng) -> Environment:
    """``masked`` as a scene graph (no boxes, no positions) with looks: at half the unseen
    object-hours, half the allowed receptacles other than the true one ruled out."""
    truth = np.asarray(full.location)
    unseen = (np.asarray(masked.location) < 0)[..., None] & (rng.random(truth.shape) < 0.5)[
        ..., None]
    not_at = unseen & np.asarray(full.allowed)[None] & (rng.random((*truth.shape,
                                                                     full.num_receptacles)) < 0.5)
    not_at &= np.arange(full.num_receptacles) != truth[..., None]
    return dataclasses.replace(masked, receptacle_corners=None, room_boxes=None,
                               door_positions=None, distance=None, object_corners=None,
                               object_rotation=None, not_at=not_at)


@pytest.fixture(scope="module")
def homes():
    return generate_homes(jax.random.key(0), CONFIG, 3)


@pytest.fixture(scope="module")
def v2_dir(homes, tmp_path_factory):
    full = from_homes(homes, CONFIG, mask_fraction=0.0, seed=0)
    masked = from_homes(homes, CONFIG, mask_fraction=0.4, seed=0)
    rng = np.random.default_rng(0)
    envs = tuple(_graph(f, m, rng) for f, m in zip(full.environments, masked.environments,
                                                    strict=True))
    path = tmp_path_factory.mktemp("v2") / "data"
    save_recorded(Recorded(envs), path)
    return path


def _tiny(**changes) -> Environment:
    """3 receptacles in 2 rooms (joined by a door), 2 objects, 6 hours, no geometry."""
    location = np.full((6, 2), -1, np.int32)
    location[0], location[3] = [0, 1], [2, 1]
    not_at = np.zeros((6, 2, 3), bool)
    not_at[2, 0, 0] = not_at[4, 1, 0] = True
    env = Environment(
        name="home", receptacle_ids=("a", "b", "c"), receptacle_classes=("table", "shelf", "table"),
        receptacle_texts=("table", "shelf", "table"),
        receptacle_room=np.array([0, 0, 1], np.int32), receptacle_corners=None,
        object_ids=("mug", "book"), object_classes=("mug", "book"), object_texts=("mug", "book"),
        allowed=np.ones((2, 3), bool), hours=np.arange(6), location=location,
        room_classes=("kitchen", "hall"), door_rooms=np.array([[0, 1]], np.int32),
        not_at=not_at)
    return dataclasses.replace(env, **changes)


def test_a_v1_dataset_loads_and_is_written_unchanged(homes, tmp_path):
    v1 = from_homes(homes, CONFIG, mask_fraction=0.3, seed=0)
    save_recorded(v1, tmp_path / "v1")
    assert json.loads((tmp_path / "v1" / fmt.INDEX_FILE).read_text())["version"] == 1
    back = load_recorded(tmp_path / "v1")
    assert fmt.content_digest(back) == fmt.content_digest(v1)
    env = back.environments[0]
    assert env.not_at is None and env.receptacle_corners.shape == (env.num_receptacles, 8, 3)
    with zipfile.ZipFile(tmp_path / "v1" / env.name / fmt.ARRAYS_FILE) as f:
        assert "receptacle_corners.npy" in f.namelist() and "not_at_bits.npy" not in f.namelist()


def test_a_v2_scene_graph_with_looks_round_trips(tmp_path):
    env = _tiny()
    save_recorded(Recorded((env,)), tmp_path / "d")
    assert json.loads((tmp_path / "d" / fmt.INDEX_FILE).read_text())["version"] == 2
    data = json.loads((tmp_path / "d" / "home" / fmt.ENVIRONMENT_FILE).read_text())
    assert data["rooms"][0]["box"] is None and data["doors"][0]["position"] is None
    with zipfile.ZipFile(tmp_path / "d" / "home" / fmt.ARRAYS_FILE) as f:
        assert sorted(f.namelist()) == ["hours.npy", "location.npy", "not_at_bits.npy"]
    back = load_recorded(tmp_path / "d").environments[0]
    assert back.receptacle_corners is None and back.room_boxes is None
    np.testing.assert_array_equal(back.not_at, env.not_at)
    assert fmt.content_digest(Recorded((back,))) == fmt.content_digest(Recorded((env,)))


def test_walking_costs_without_positions_count_room_changes_and_looks():
    e, c = fmt.EXAMINE_COST, fmt.EXAMINE_COST + fmt.ROOM_CHANGE_COST
    np.testing.assert_array_equal(_tiny().walking_distance(), [[e, e, c], [e, e, c], [c, c, e]])
    three = _tiny(room_classes=("kitchen", "hall", "bed"), door_rooms=np.array([[0, 1], [1, 2]],
                                                                              np.int32),
                  receptacle_room=np.array([0, 1, 2], np.int32))
    assert three.walking_distance()[0, 2] == e + 2 * fmt.ROOM_CHANGE_COST  # through the hall
    no_doors = _tiny(room_classes=("kitchen", "hall", "bed"), door_rooms=None,
                     receptacle_room=np.array([0, 1, 2], np.int32))
    assert no_doors.walking_distance()[0, 2] == c  # every pair of rooms one change apart


@pytest.mark.parametrize("case, message", [
    ("seen where ruled out", r"arrays.npz: not_at: object 0 \('mug'\) was seen on receptacle 0"),
    ("bits shape", r"arrays.npz: not_at_bits: has shape \(6, 2, 2\)"),
    ("padding bits", r"arrays.npz: not_at_bits: sets padding bits"),
    ("v1 without boxes", r"arrays.npz is missing arrays \['receptacle_corners'\]"),
])
def test_bad_looks_are_refused_naming_file_and_field(tmp_path, case, message):
    root = tmp_path / "d"
    save_recorded(Recorded((_tiny(),)), root)
    npz = root / "home" / fmt.ARRAYS_FILE
    arrays = dict(np.load(npz))
    if case == "seen where ruled out":
        bits = np.unpackbits(arrays["not_at_bits"], axis=-1, count=3)
        bits[0, 0, 0] = 1
        arrays["not_at_bits"] = np.packbits(bits, axis=-1)
    elif case == "bits shape":
        arrays["not_at_bits"] = np.zeros((6, 2, 2), np.uint8)
    elif case == "padding bits":
        arrays["not_at_bits"] = arrays["not_at_bits"] | np.uint8(1)
    else:
        index = json.loads((root / fmt.INDEX_FILE).read_text())
        (root / fmt.INDEX_FILE).write_text(json.dumps({**index, "version": 1}))
    np.savez(npz, **arrays)
    with pytest.raises(ValueError, match=message):
        load_recorded(root)


def test_bad_looks_in_memory_are_refused_naming_the_field(tmp_path):
    with pytest.raises(ValueError, match=r"'home': not_at: has shape \(6, 2, 2\)"):
        save_recorded(Recorded((_tiny(not_at=np.zeros((6, 2, 2), bool)),)), tmp_path / "d")
    bad = _tiny().not_at.copy()
    bad[3, 0, 2] = True
    with pytest.raises(ValueError, match=r"'home': not_at: object 0 .* receptacle 2 at hour 3"):
        save_recorded(Recorded((_tiny(not_at=bad),)), tmp_path / "d")
    assert not (tmp_path / "d").exists()


@functools.partial(jax.jit, static_argnums=(2, 3))
def _with_and_without_looks(homes, queries, config, history, observed, not_at):
    """The training batch with the negative features, and without (one compiled program)."""
    return (homes_inputs.shared_tau_batch(homes, queries, config, history, observed, not_at,
                                          True),
            homes_inputs.shared_tau_batch(homes, queries, config, history, observed))


def test_looks_reach_the_rows_of_the_network_as_computed_by_hand(v2_dir):
    recorded = load_recorded(v2_dir)
    cfg = recorded_config("smoke", str(v2_dir))
    assert cfg.model.negative_evidence and not cfg.model.geometry
    data = rw.recorded_homes(recorded, cfg.homes)
    not_at, observed = np.asarray(data.not_at), np.asarray(data.observed)
    picks = [np.argwhere(not_at[e, 5:-1].any(-1))[:4] for e in range(data.num_homes)]
    obj = np.stack([p[:, 1] for p in picks])  # (E, 4) objects looked for at hours tau
    tau = np.stack([p[:, 0] + 5 for p in picks])
    queries = HomesQueries(*(np.asarray(a, np.int32) for a in (obj, tau, tau + 1)))
    h = cfg.model.history
    batch, plain = _with_and_without_looks(data.homes, queries, cfg.homes, h, data.observed,
                                           data.not_at)
    rows, k = np.asarray(batch.rows), len(homes_inputs.ROW_FEATURES)
    assert rows.shape[-1] == k + len(homes_inputs.NEGATIVE_FEATURES)
    np.testing.assert_array_equal(rows[..., :k], plain.rows)
    for ee, j in np.ndindex(obj.shape):
        o, tq = int(obj[ee, j]), int(tau[ee, j])
        allowed = np.asarray(data.homes.object_allowed)[ee, o]
        seen = [s for s in range(tq + 1) if observed[ee, s, o]]
        last = seen[-1] if seen else -1
        for r in range(cfg.homes.max_receptacles):
            looks = [s for s in range(max(0, tq - h + 1), tq + 1) if not_at[ee, s, o, r]]
            since = float(bool(looks) and looks[-1] > last)
            recency = 1 - np.log1p(tq - looks[-1]) / np.log1p(h) if looks else 0.0
            np.testing.assert_allclose(rows[ee, j, r, k:],
                                       np.array([since, recency]) * allowed[r], atol=1e-6)
    assert rows[..., k:].any()


@pytest.fixture
def counted(monkeypatch):
    """Calls of the data's read, digest and split and of the stored config's read, counted,
    with nothing read before (as in a fresh process)."""
    calls = collections.Counter()

    def counting(module, name):
        real = getattr(module, name)

        def wrapper(*args, **kwargs):
            calls[name] += 1
            return real(*args, **kwargs)

        monkeypatch.setattr(module, name, wrapper)

    for name in ("load_recorded", "content_digest", "split_environments"):
        counting(rw, name)
    counting(checkpoints, "stored_config")
    rw._LOADED.clear()
    return calls


@pytest.mark.slow  # end to end: pytest -m slow (tests/conftest.py)
def test_a_v2_scene_graph_with_looks_trains_evaluates_and_searches(v2_dir, tmp_path, counted):
    """Also one load per run: the training and the evaluation (each as in a process of its own)
    read, digest and split the data once; the evaluation reads the stored config once."""
    run = tmp_path / "run"
    code, out = run_python_in_process(
        ["-m", "flowmaps_jax.train", "--preset", "smoke", "--data", str(v2_dir),
         "--run-dir", str(run), "--no-progress", "--steps", "4", "--set", "val_every=2",
         "--set", "ckpt_every=2", "--set", "log_every=1"], tmp_path)
    assert code == 0, out
    assert counted == {"load_recorded": 1, "content_digest": 1, "split_environments": 1}
    model = json.loads((run / "config.json").read_text())["model"]
    assert model["negative_evidence"] and not model["geometry"]
    counted.clear()
    rw._LOADED.clear()  # evaluate in a process of its own
    code, out = run_python_in_process(
        ["-m", "flowmaps_jax.evaluate", "--checkpoint", str(run), "--out",
         str(tmp_path / "eval"), "--queries", "8", "--no-progress"], tmp_path)
    assert code == 0, out
    assert counted == {"load_recorded": 1, "content_digest": 1, "split_environments": 1,
                       "stored_config": 1}
    results = json.loads((tmp_path / "eval" / "results.json").read_text())
    ruled = results["ruled_out"]
    assert {"FlowMaps", "uniform over allowed", "last seen"} <= set(ruled)
    assert all(v["count"] > 0 and v["mean"] <= 0 for v in ruled.values())
    assert "Negative evidence" in (tmp_path / "eval" / "results.md").read_text()
    code, out = run_python_in_process(
        ["-m", "flowmaps_jax.search", "--checkpoint", str(run), "--data", str(v2_dir),
         "--out", str(tmp_path / "search"), "--queries", "4", "--no-progress"], tmp_path)
    assert code == 0, out
    nav = json.loads((tmp_path / "search" / "search.json").read_text())["navigation"]
    steps = nav["nearest first"]["metrics"]["steps"]["overall"]["mean"]
    assert steps >= fmt.EXAMINE_COST  # at least one look, in room-graph costs


def test_validate_summarises_geometry_and_looks(v2_dir, tmp_path):
    code, out = run_python_in_process(["-m", "flowmaps_jax.data", "validate", str(v2_dir)],
                                      tmp_path)
    assert code == 0, out
    recorded = load_recorded(v2_dir)
    looked = sum(int(e.not_at.any(-1).sum()) for e in recorded.environments)
    total = sum(e.num_hours * e.num_objects for e in recorded.environments)
    assert "receptacle boxes in 0 of 3" in out and "walking costs come from the room graph" in out
    assert f"not_at) in all: {100 * looked / total:.1f} % of the object-hours" in out


def test_a_scene_graph_is_not_exported_to_the_authors_layout(tmp_path):
    from flowmaps_jax.recorded.flowmaps2026 import export_flowmaps2026

    with pytest.raises(ValueError, match="'home' has no receptacle boxes"):
        export_flowmaps2026(Recorded((_tiny(),)), tmp_path / "authors")
    assert not (tmp_path / "authors").exists()
