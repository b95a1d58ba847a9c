"""experiments/peers/sgm.py (issue 56, item 5) without SGM or torch: the adapter on a log in the
shape sgm_driver.py writes, through import-log; SGM's accuracy and the scores on hand-checked
examples; the refusal of a checkout that is not SGM; the driver's fix for all-zero weights."""

from __future__ import annotations

import importlib.util
import math
import pathlib
import random
import types

import numpy as np
import pytest

from flowmaps_jax.recorded.import_log import import_log

PEERS = pathlib.Path(__file__).parents[1] / "experiments" / "peers"


def _module(name):
    spec = importlib.util.spec_from_file_location(f"peers_{name}", PEERS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


sgm, driver = _module("sgm"), _module("sgm_driver")


def _look(hour, receptacle, room, seen=()):
    """The rows the driver writes for one look: the look, then each object seen there."""
    where = {"environment": "small-s0-scene0000", "timestamp": hour, "receptacle": receptacle,
             "receptacle_class": receptacle.split("|")[0], "room": room}
    return [{**where, "object": "", "object_class": "", "found": "false"},
            *({**where, "object": o, "object_class": o.split("|")[0], "found": "true"}
              for o in seen)]


# One scene: the table (kitchen) and the shelf (living room); hour 0 the table holds the mug and
# the cup, hour 1 the shelf the book, hour 2 the table the mug alone (the cup moved away).
LOG = [*_look(0, "table|1", "kitchen", ("mug|5", "cup|6")), *_look(1, "shelf|2", "living_room",
       ("book|7",)), *_look(2, "table|1", "kitchen", ("mug|5",))]


def test_a_driver_log_splits_into_parts_and_imports_with_its_looks(tmp_path):
    rows, part = sgm.split_log(LOG, max_objects=2)
    env = "small-s0-scene0000"
    # sorted ids book|7, cup|6, mug|5 in two parts: the first two, then the mug
    assert part == {(env, "book|7"): f"{env}/part0", (env, "cup|6"): f"{env}/part0",
                    (env, "mug|5"): f"{env}/part1"}
    looks = [r for r in rows if not r["object"]]
    assert len(looks) == 6  # 3 looks, each in both parts
    path = tmp_path / "log.csv"
    sgm.write_csv(path, rows, driver.TRACE_COLUMNS)
    recorded = import_log(str(path), warn=lambda line: None)
    envs = {e.name: e for e in recorded.environments}
    assert sorted(envs) == [f"{env}/part0", f"{env}/part1"]
    first, second = envs[f"{env}/part0"], envs[f"{env}/part1"]
    assert set(first.object_ids) == {"book|7", "cup|6"} and second.object_ids == ("mug|5",)
    assert set(first.receptacle_ids) == set(second.receptacle_ids) == {"table|1", "shelf|2"}
    np.testing.assert_array_equal(first.hours, [0, 1, 2])
    table, shelf = (second.receptacle_ids.index(r) for r in ("table|1", "shelf|2"))
    np.testing.assert_array_equal(second.location[:, 0], [table, -1, table])
    assert second.not_at[1, 0, shelf]  # the shelf looked at in hour 1: the mug was not there
    cup = first.object_ids.index("cup|6")
    assert first.location[2, cup] == -1 and first.not_at[2, cup, table]  # the cup left


def test_the_model_reads_only_training_pairs_and_known_classes():
    recorded = import_log(_written(LOG), warn=lambda line: None)
    texts = lambda *names: [types.SimpleNamespace(text=n) for n in names]  # noqa: E731
    config = types.SimpleNamespace(object_classes=texts("mug", "book"),
                                   receptacle_classes=texts("table", "shelf"),
                                   room_types=texts("kitchen", "living_room"),
                                   max_receptacles=2, num_rooms=2, num_hours=3)
    envs, removed = sgm.readable(recorded, config, {("mug", "shelf")})
    assert removed == 1  # the cup: a class the training log never showed
    (env,) = envs
    assert env.object_ids == ("mug|5", "book|7") and env.location.shape == (3, 2)
    shelf = env.receptacle_ids.index("shelf|2")
    # the mug only where training saw mugs; the book (no pair) anywhere; not import-log's pairs
    assert env.allowed[0].tolist() == [r == shelf for r in range(2)]
    assert env.allowed[1].all()
    assert (env.location[:, 0] == -1).all()  # the mug seen on the table only: read as unseen
    small = types.SimpleNamespace(**{**vars(config), "max_receptacles": 1})
    assert sgm.readable(recorded, small, set()) == ([], 3)  # larger than the model's homes
    (env,), _ = sgm.readable(recorded, config)  # no pairs: every receptacle, every sighting
    assert env.allowed.all() and (env.location[[0, 2], 0] == env.receptacle_ids.index("table|1")
                                  ).all()


def _written(rows):
    import tempfile

    path = pathlib.Path(tempfile.mkdtemp()) / "log.csv"
    sgm.write_csv(path, rows, driver.TRACE_COLUMNS)
    return str(path)


def test_sgm_accuracy_and_the_rows_scores_by_hand():
    accuracy = sgm.sgm_accuracy(["a|1", "b|2", "c|3"], ["a|1;x|9", "c|3", "c|3"])
    assert accuracy == pytest.approx(2 / 3)
    queries = [{"environment": "s", "object": "o|1", "receptacle": "a|1", "receptacles": "a|1"},
               {"environment": "s", "object": "o|1", "receptacle": "b|2", "receptacles": "b|2"},
               {"environment": "s", "object": "o|2", "receptacle": "b|2", "receptacles": "b|2"}]
    answers = [{"a|1": 0.7, "b|2": 0.3}, {"a|1": 0.5, "b|2": 0.5}, None]
    fallback = [None, None, {"a|1": 0.25, "b|2": 0.75}]
    scores = sgm.score_row(answers, queries, fallback)
    # a hit; a tie read as the first (a miss); the fallback's guess (a hit)
    assert scores["accuracy"] == pytest.approx(2 / 3)
    assert scores["log_score"] == pytest.approx((math.log(0.7) + math.log(0.5)
                                                 + math.log(0.75)) / 3)
    assert scores["fallback"] == 1


def test_the_log_fallback_is_the_last_place_seen_then_the_class_frequency():
    # training: the mug on the table twice, then the shelf (one stay in two), the book once
    train = [*_look(0, "table|1", "kitchen", ("mug|5",)), *_look(1, "table|1", "kitchen",
             ("mug|5",)), *_look(2, "shelf|2", "living_room", ("mug|5", "book|7"))]
    queries = [{"environment": "small-s0-scene0000", "timestamp": t, "object": o,
                "object_class": o.split("|")[0]} for t, o in
               [(0, "mug|5"), (1, "mug|5"), (3, "mug|5"), (1, "cup|6"), (1, "vase|8")]]
    never, seen_table, seen_again, cup, vase = sgm.log_fallback(queries, LOG, train)
    # mugs: 2 on tables, 1 on shelves, add-one: 3/5 and 2/5; never seen before hour 0
    assert never == pytest.approx({"table|1": 3 / 5, "shelf|2": 2 / 5})
    # seen on the table at hour 0: stay 1/2 there, else the class frequency
    assert seen_table == pytest.approx({"table|1": 0.5 + 0.5 * 3 / 5, "shelf|2": 0.5 * 2 / 5})
    assert seen_again == seen_table  # last seen at hour 2, on the table again
    # the cup was seen on the table at hour 0; no cup in training: every class pooled, 2+1 on
    # tables and 2+1 on shelves
    assert cup == pytest.approx({"table|1": 0.5 + 0.5 / 2, "shelf|2": 0.5 / 2})
    assert vase == pytest.approx({"table|1": 1 / 2, "shelf|2": 1 / 2})  # never seen


def test_a_dataset_allowed_everywhere_keeps_everything_else(tmp_path):
    from flowmaps_jax.recorded.format import load_recorded, save_recorded

    save_recorded(import_log(_written(LOG), warn=lambda line: None), tmp_path / "a")
    sgm.allow_everywhere(tmp_path / "a", tmp_path / "b", True)
    sgm.allow_everywhere(tmp_path / "a", tmp_path / "c", False)
    (a,), (b,), (c,) = (load_recorded(tmp_path / n).environments for n in "abc")
    assert not a.allowed.all() and b.allowed.all() and (c.allowed == a.allowed).all()
    np.testing.assert_array_equal(b.location, a.location)
    np.testing.assert_array_equal(b.not_at, a.not_at)


def test_a_path_that_is_not_sgm_is_refused_naming_sgm(tmp_path, capsys):
    with pytest.raises(ValueError, match=r"--sgm: .* is not a folder"):
        sgm.check_sgm(tmp_path / "missing")
    with pytest.raises(ValueError, match=r"--sgm: .* not a checkout of SGM .*memsearch/scene\.py"):
        sgm.check_sgm(tmp_path)
    with pytest.raises(SystemExit) as err:
        sgm.main(["--sgm", str(tmp_path), "--out", str(tmp_path / "out")])
    assert err.value.code == 2 and "--sgm" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_the_driver_draws_uniformly_from_all_zero_weights():
    stream = driver.Stream(0)
    assert stream.Random is random.Random  # SGM calls random.Random() on the module
    pick = driver.choose(stream)
    with pytest.raises(ValueError):
        random.choices(["a", "b"], weights=[0.0, 0.0])  # what SGM hits on Python >= 3.9
    assert {pick({"a": 0.0, "b": 0.0}) for _ in range(50)} == {"a", "b"}
    assert {pick({"a": 0.0, "b": 2.0}) for _ in range(50)} == {"b"}


def test_a_scene_larger_than_the_default_token_and_class_budgets_gets_a_config():
    from flowmaps_jax.worlds.recorded import homes_config_of

    rows = [r for k in range(60) for r in _look(k, f"shelf{k}|{k}", f"room{k % 3}",
                                                (f"thing{k}|{100 + k}",) if k < 15 else ())]
    config = homes_config_of(import_log(_written(rows), warn=lambda line: None))
    assert config.max_receptacles >= 60 and config.max_tokens > 48  # the defaults: 48, 128
    assert config.max_vocabulary == config.vocabulary_size > 60
