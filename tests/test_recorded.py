"""Recorded worlds (docs/data.md): the files and their loader's refusals, FlowSim homes as a
recorded world (masking by whole rooms), the authors' 2026 format both ways, and the
``python -m flowmaps_jax.data`` commands.

Tiny sizes: 4 homes over 48 hours, and a hand-made environment of 3 receptacles, 2 objects
and 4 hours."""

from __future__ import annotations

import dataclasses
import json
import pathlib
import re
import zipfile

import jax
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from flowmaps_jax.flowsim.homes import HomesConfig, generate_homes
from flowmaps_jax.recorded import (
    Environment,
    Recorded,
    from_homes,
    load_recorded,
    save_recorded,
    validate_environment,
)
from flowmaps_jax.recorded.format import ARRAYS_FILE, ENVIRONMENT_FILE, INDEX_FILE

CONFIG = HomesConfig(regime="mixed", num_hours=48)
NUM_HOMES = 4


@pytest.fixture(scope="module")
def homes():
    return generate_homes(jax.random.key(0), CONFIG, NUM_HOMES)


def tiny_environment(name: str = "train/env0", **changes) -> Environment:
    """3 receptacles (no rooms), 2 objects, 4 hours; object 1 unseen at hour 2."""
    corners = np.zeros((3, 8, 3), np.float32)
    for r in range(3):
        corners[r] = np.asarray([[x, y, z] for z in (0.0, 0.5) for x, y in
                                 ((r, 0), (r + 1, 0), (r + 1, 1), (r, 1))], np.float32)
    fields = dict(
        name=name, receptacle_ids=("Sofa|1", "Table|2", "Shelf|3"),
        receptacle_classes=("Sofa", "Table", "Shelf"),
        receptacle_texts=("sofa", "table", "shelf"),
        receptacle_room=np.full(3, -1, np.int32), receptacle_corners=corners,
        object_ids=("Book|1", "Mug|2"), object_classes=("Book", "Mug"),
        object_texts=("book", "mug"),
        allowed=np.asarray([[True, True, False], [False, True, True]]),
        hours=np.asarray([0, 1, 2, 5], np.int64),
        location=np.asarray([[0, 1], [1, 1], [1, -1], [0, 2]], np.int32),
        source={"from": "test"})
    fields.update(changes)
    return Environment(**fields)


def assert_same_environment(a: Environment, b: Environment) -> None:
    """Every field equal: arrays (value, dtype, shape) and everything else."""
    for field in dataclasses.fields(Environment):
        x, y = getattr(a, field.name), getattr(b, field.name)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            assert isinstance(x, np.ndarray) and isinstance(y, np.ndarray), field.name
            assert x.dtype == y.dtype and x.shape == y.shape, field.name
            np.testing.assert_array_equal(x, y, err_msg=field.name)
        else:
            assert x == y, field.name


def assert_same(a: Recorded, b: Recorded) -> None:
    assert a.names() == b.names()
    for x, y in zip(a.environments, b.environments, strict=True):
        assert_same_environment(x, y)


# ---------------------------------------------------------------------------- the files


def test_tiny_round_trip_and_derived_distances(tmp_path):
    world = Recorded((tiny_environment(), tiny_environment("val/env3")))
    index = save_recorded(world, tmp_path / "world")
    assert index == tmp_path / "world" / INDEX_FILE
    data = json.loads(index.read_text())
    assert data["format"] == "flowmaps-recorded" and data["version"] == 1
    assert data["environments"] == ["train/env0", "val/env3"]
    env_json = json.loads((tmp_path / "world/train/env0" / ENVIRONMENT_FILE).read_text())
    assert env_json["objects"][1] == {"id": "Mug|2", "class": "Mug", "text": "mug",
                                      "allowed": [1, 2]}
    assert env_json["receptacles"][0]["room"] is None
    with np.load(tmp_path / "world/train/env0" / ARRAYS_FILE) as f:  # numpy alone reads it
        assert sorted(f.files) == ["hours", "location", "receptacle_corners"]
    back = load_recorded(tmp_path / "world")
    assert_same(world, back)
    env = back.environments[0]
    assert (env.num_hours, env.num_objects, env.num_receptacles) == (4, 2, 3)
    np.testing.assert_array_equal(env.observed, env.location >= 0)
    np.testing.assert_allclose(env.receptacle_boxes()[0], [0.5, 0.5, 0.25, 1, 1, 0.5])
    # no rooms: straight lines between the box centres on the floor
    np.testing.assert_allclose(env.walking_distance(), np.abs(np.subtract.outer(
        np.arange(3), np.arange(3))), atol=1e-6)
    assert back.vocabulary() == {"rooms": [], "receptacles": ["Shelf", "Sofa", "Table"],
                                 "objects": ["Book", "Mug"]}


def test_walking_distance_through_a_door():
    # two rooms side by side, a door at (2, 0.5): from receptacle 0 to 2 the walk bends
    env = tiny_environment(
        receptacle_room=np.asarray([0, 0, 1], np.int32), room_classes=("a", "b"),
        room_boxes=np.asarray([[0, 0, 2, 1], [2, 0, 4, 1]], np.float32),
        door_rooms=np.asarray([[0, 1]], np.int32),
        door_positions=np.asarray([[2.0, -1.0]], np.float32))
    validate_environment(env)
    d = env.walking_distance()
    via = np.hypot(1.5, 1.5) + np.hypot(0.5, 1.5)
    assert d[0, 2] == pytest.approx(via, rel=1e-6) and d[2, 0] == pytest.approx(via, rel=1e-6)
    assert d[0, 1] == pytest.approx(1.0)


def _saved(tmp_path) -> pathlib.Path:
    root = tmp_path / "world"
    save_recorded(Recorded((tiny_environment(),)), root)
    return root


def _edit_json(path: pathlib.Path, edit) -> None:
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


def _edit_arrays(path: pathlib.Path, edit) -> None:
    with np.load(path) as f:
        arrays = {k: f[k] for k in f.files}
    edit(arrays)
    np.savez(path, **arrays)


def _set(key, value):
    return lambda d: d.__setitem__(key, value)


INDEX_CASES = {
    "format": (_set("format", "flowmaps-homes"), "format"),
    "version": (_set("version", 3), "version"),
    "missing": (lambda d: d.pop("units"), r"\(top level\): missing \['units'\]"),
    "unexpected": (_set("extra", 1), r"unexpected \['extra'\]"),
    "no environments": (_set("environments", []), "environments: is empty"),
    "twice": (_set("environments", ["train/env0", "train/env0"]), "environments: .*twice"),
    "escape": (_set("environments", ["../env0"]), "environments: .*relative POSIX path"),
}
ENV_CASES = {
    "allowed index": (lambda d: d["objects"][0].__setitem__("allowed", [0, 7]),
                      r"objects\[0\]\.allowed: holds 7, outside 0\.\.2"),
    "room index": (lambda d: d["receptacles"][1].__setitem__("room", 4),
                   r"receptacles\[1\]\.room: holds 4, outside -1\.\.-1"),
    "no objects": (_set("objects", []), "objects: is empty"),
    "not allowed": (lambda d: d["objects"][1].__setitem__("allowed", [2]),
                    "location: object 1 .* may not stand"),
    "missing key": (lambda d: d["receptacles"][0].pop("text"),
                    r"receptacles\[0\]: missing \['text'\]"),
    "door without rooms": (_set("doors", [{"rooms": [0, 1], "position": [0, 0]}]),
                           "doors: doors are given but rooms is empty"),
    "bad box": (_set("rooms", [{"class": "a", "box": [0, 0, -1, 1]}]),
                r"rooms\[\*\]\.box: must have x1 > x0"),
    "door index": (lambda d: (d.__setitem__("rooms", [{"class": "a", "box": [0, 0, 1, 1]}]),
                              d.__setitem__("doors", [{"rooms": [0, 5], "position": [1, 0]}])),
                   r"doors\[0\]\.rooms: holds 5, outside 0\.\.0"),
    "no receptacles": (lambda d: (d.__setitem__("receptacles", []),
                                  [o.__setitem__("allowed", []) for o in d["objects"]]),
                       "receptacles: is empty"),
    "nan room box": (_set("rooms", [{"class": "a", "box": [0, 0, float("nan"), 1]}]),
                     r"rooms\[\*\]\.box: holds NaN or inf"),
    "duplicate id": (lambda d: d["objects"][1].__setitem__("id", "Book|1"),
                     r"objects\[\*\]\.id: names 'Book\|1' twice"),
}


def _nan_corner(a):
    a["receptacle_corners"][1, 2, 0] = np.nan


ARRAY_CASES = {
    "shape": (lambda a: a.__setitem__("location", a["location"][:, :1]),
              r"location: has shape \(4, 1\) and dtype int32; expected \(T, M\) = \(4, 2\)"),
    "dtype": (lambda a: a.__setitem__("location", a["location"].astype(np.float32)),
              "location: has shape .* dtype float32"),  # any integer dtype that fits is read
    "out of range": (lambda a: a["location"].__setitem__((0, 0), 3),
                     r"location: holds 3 at \[0, 0\], outside -1\.\.2"),
    "below -1": (lambda a: a["location"].__setitem__((0, 0), -2), "location: holds -2"),
    "nan corner": (_nan_corner, "receptacle_corners: holds NaN or inf"),
    "backwards": (lambda a: a.__setitem__("hours", np.asarray([0, 3, 2, 5], np.int64)),
                  "hours: must be strictly increasing.*time goes backwards"),
    "empty": (lambda a: (a.__setitem__("hours", a["hours"][:0]),
                         a.__setitem__("location", a["location"][:0])), "hours: is empty"),
    "distance": (lambda a: a.__setitem__("distance", np.full((3, 3), np.inf, np.float32)),
                 "distance: holds NaN or inf"),
    "asymmetric": (lambda a: a.__setitem__("distance", np.triu(np.ones((3, 3), np.float32), 1)),
                   "distance: must be symmetric"),
    "unexpected": (lambda a: a.__setitem__("colour", np.zeros(3)), "unexpected member"),
    "missing": (lambda a: a.pop("hours"), r"missing arrays \['hours'\]"),
}


@pytest.mark.parametrize("case", sorted(INDEX_CASES))
def test_load_refuses_a_bad_index(tmp_path, case):
    root = _saved(tmp_path)
    edit, message = INDEX_CASES[case]
    _edit_json(root / INDEX_FILE, edit)
    with pytest.raises(ValueError, match=message) as info:
        load_recorded(root)
    assert str(info.value).startswith(str(root / INDEX_FILE)) and "\n" not in str(info.value)


@pytest.mark.parametrize("case", sorted(ENV_CASES))
def test_load_refuses_a_bad_environment_json(tmp_path, case):
    root = _saved(tmp_path)
    edit, message = ENV_CASES[case]
    _edit_json(root / "train/env0" / ENVIRONMENT_FILE, edit)
    with pytest.raises(ValueError, match=message) as info:
        load_recorded(root)
    file = ARRAYS_FILE if case == "not allowed" else ENVIRONMENT_FILE  # location is an array
    assert str(info.value).startswith(str(root / "train/env0" / file)), str(info.value)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("case", sorted(ARRAY_CASES))
def test_load_refuses_bad_arrays(tmp_path, case):
    root = _saved(tmp_path)
    edit, message = ARRAY_CASES[case]
    _edit_arrays(root / "train/env0" / ARRAYS_FILE, edit)
    with pytest.raises(ValueError, match=message) as info:
        load_recorded(root)
    assert str(root / "train/env0" / ARRAYS_FILE) in str(info.value)
    assert "\n" not in str(info.value)


def test_load_refuses_missing_and_broken_files(tmp_path):
    root = _saved(tmp_path)
    with pytest.raises(ValueError, match="does not exist"):
        load_recorded(tmp_path / "absent")
    (root / "train/env0" / ARRAYS_FILE).write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=r"arrays\.npz is not a readable \.npz"):
        load_recorded(root)
    (root / "train/env0" / ENVIRONMENT_FILE).write_text("{")
    with pytest.raises(ValueError, match=r"environment\.json' is not valid JSON"):
        load_recorded(root)
    (root / INDEX_FILE).unlink()
    with pytest.raises(ValueError, match=r"recorded\.json: \(file\): missing"):
        load_recorded(root)


def test_save_refuses_bad_worlds_and_links(tmp_path):
    with pytest.raises(ValueError, match=r"environment name 'a/\.\./b'"):
        save_recorded(Recorded((tiny_environment("a/../b"),)), tmp_path / "w")
    with pytest.raises(ValueError, match="appears twice"):
        save_recorded(Recorded((tiny_environment(), tiny_environment())), tmp_path / "w")
    with pytest.raises(ValueError, match="lies inside the environment 'train'"):
        save_recorded(Recorded((tiny_environment("train"), tiny_environment())), tmp_path / "w")
    with pytest.raises(ValueError, match="non-empty tuple"):
        save_recorded(Recorded(()), tmp_path / "w")
    bad = tiny_environment(location=np.asarray([[0, 0], [1, 1], [1, -1], [0, 2]], np.int32))
    with pytest.raises(ValueError, match=r"environment 'train/env0': location: object 1 "
                                         r"\('Mug\|2'\) is on receptacle 0"):
        save_recorded(Recorded((bad,)), tmp_path / "w")
    with pytest.raises(ValueError, match="source: must be JSON-able"):
        validate_environment(tiny_environment(source={"x": object()}))
    assert not (tmp_path / "w").exists()  # refused before anything was written
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "w").mkdir()
    (tmp_path / "w" / "train").symlink_to(tmp_path / "elsewhere")
    with pytest.raises(ValueError, match="symbolic link"):
        save_recorded(Recorded((tiny_environment(),)), tmp_path / "w")
    assert not list((tmp_path / "elsewhere").iterdir())


# ---------------------------------------------------------------------------- FlowSim homes


def test_homes_as_recorded_world(homes, tmp_path):
    world = from_homes(homes, CONFIG)
    assert world.names() == tuple(f"home{e}" for e in range(NUM_HOMES))
    for e, env in enumerate(world.environments):
        home = jax.tree.map(np.asarray, homes.home(e))
        slots = np.flatnonzero(home.receptacle_valid)
        objects = np.flatnonzero(home.object_valid)
        assert env.num_receptacles == slots.size and env.num_objects == objects.size
        np.testing.assert_array_equal(env.hours, np.arange(CONFIG.num_hours))
        np.testing.assert_array_equal(slots[env.location], home.receptacle[:, objects])
        np.testing.assert_array_equal(env.allowed, home.object_allowed[objects][:, slots])
        np.testing.assert_array_equal(env.distance,
                                      home.receptacle_distance[slots][:, slots])
        np.testing.assert_allclose(env.receptacle_boxes(), home.receptacle_box[slots],
                                   atol=1e-5)
        np.testing.assert_array_equal(env.receptacle_room, home.receptacle_room[slots])
        assert env.receptacle_classes == tuple(
            CONFIG.receptacle_classes[c].name for c in home.receptacle_class[slots])
        assert env.object_texts == tuple(
            CONFIG.object_classes[c].text for c in home.object_class[objects])
        assert all(i.split("|")[0] == c for i, c in zip(env.object_ids, env.object_classes,
                                                        strict=True))
        assert env.door_rooms.shape == (home.door_valid.sum(), 2)
        # the derived geodesic is the homes' own
        np.testing.assert_allclose(dataclasses.replace(env, distance=None).walking_distance(),
                                   env.distance, atol=1e-4)
        assert env.source["from"] == "flowsim-homes" and env.source["home"] == e
        assert HomesConfig.from_dict(env.source["config"]) == CONFIG
    save_recorded(world, tmp_path / "homes")
    assert_same(world, load_recorded(tmp_path / "homes"))


def test_masking_hides_whole_rooms_for_runs_of_hours(homes):
    world = from_homes(homes, CONFIG, mask_fraction=0.3, seed=3,
                       names=[f"train/h{e}" for e in range(NUM_HOMES)])
    truth = from_homes(homes, CONFIG)
    hidden, runs = [], []
    for env, full in zip(world.environments, truth.environments, strict=True):
        assert env.name.startswith("train/h")
        seen = env.observed
        np.testing.assert_array_equal(env.location[seen], full.location[seen])
        room = env.receptacle_room[full.location]  # (T, M): the room each object is in
        for t in range(env.num_hours):  # whole rooms: an hour hides all or none of a room
            for k in np.unique(room[t]):
                assert len(set(seen[t, room[t] == k])) == 1
        hidden.append(~seen)
        # runs: a room hidden at hour t is mostly hidden at t + 1 too
        per_room = np.zeros((env.num_hours, len(env.room_classes)), bool)
        per_room[np.nonzero(~seen)[0], room[~seen]] = True
        runs.append((per_room[1:] & per_room[:-1]).sum() / max(per_room[:-1].sum(), 1))
    fraction = np.mean(np.concatenate([h.ravel() for h in hidden]))
    assert 0.2 < fraction < 0.4, fraction
    assert np.mean(runs) > 0.6
    again = from_homes(homes, CONFIG, mask_fraction=0.3, seed=3)
    np.testing.assert_array_equal(again.environments[1].location, world.environments[1].location)
    other = from_homes(homes, CONFIG, mask_fraction=0.3, seed=4)
    assert not np.array_equal(other.environments[1].location, world.environments[1].location)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"mask_fraction": 1.0}, "mask_fraction must be in"),
    ({"mask_fraction": -0.1}, "mask_fraction must be in"),
    ({"seed": -1}, "seed must be an int"),
    ({"names": ["a", "b"]}, "names must be a sequence of 4"),
    ({"names": ["a", "b", "c", "/d"]}, r"names\[3\] '/d' must be a relative POSIX path"),
])
def test_from_homes_refuses_bad_arguments(homes, kwargs, message):
    with pytest.raises(ValueError, match=message):
        from_homes(homes, CONFIG, **kwargs)


def test_npz_members_are_plain_arrays(tmp_path):
    root = _saved(tmp_path)
    with zipfile.ZipFile(root / "train/env0" / ARRAYS_FILE) as archive:
        assert sorted(archive.namelist()) == ["hours.npy", "location.npy",
                                              "receptacle_corners.npy"]


# ---------------------------------------------------------------------------- the authors' format

OBJECTS = ["Book|surface|1|2", "Mug|3"]
RECEPTACLES = ["Sofa|1|0", "CounterTop|2|1", "Sink|5|1|0___0"]
ALLOWED = {"Book|surface|1|2": ["Sofa|1|0", "CounterTop|2|1"],
           "Mug|3": ["CounterTop|2|1", "Sink|5|1|0___0"]}
ASSIGNMENT = np.zeros((5, 2, 3), np.int64)  # hour, object, receptacle (one-hot)
for _t, (_book, _mug) in enumerate([(0, 1), (0, 2), (1, None), (1, 1), (0, 2)]):
    ASSIGNMENT[_t, 0, _book] = 1
    if _mug is not None:  # the mug is not seen at hour 2: an all-zero row
        ASSIGNMENT[_t, 1, _mug] = 1


def _y_up_box(x0, z0, x1, z1, top) -> list:
    """8 corner points [x, y up, z] of a box on the floor, in the authors' axes."""
    return [[x, y, z] for y in (0.0, top) for x, z in ((x0, z0), (x1, z0), (x1, z1), (x0, z1))]


def _nested(array: np.ndarray, fixed: bool):
    """A numpy array (rows first) as a pyarrow column of nested lists."""
    column = pa.array(array.reshape(-1))
    for size in reversed(array.shape[1:]):
        if fixed:
            column = pa.FixedSizeListArray.from_arrays(column, size)
        else:
            offsets = pa.array(np.arange(0, len(column) + 1, size, dtype=np.int32))
            column = pa.ListArray.from_arrays(offsets, column)
    return column


def write_authors_environment(folder: pathlib.Path, *, pieces: bool = False,
                              fixed: bool = True, assignment=ASSIGNMENT,
                              objects=OBJECTS) -> None:
    """One environment folder written from the documented columns and JSON layout."""
    folder.mkdir(parents=True)
    t, m = assignment.shape[:2]
    corners = np.zeros((t, m, 8, 3), np.float32)
    corners[..., 1] = np.arange(t, dtype=np.float32)[:, None, None]  # y up: the hour
    columns = {"assignment": assignment, "rotation": np.full((t, m), 0.5, np.float32),
               "aabb_cornerPoints": corners}
    splits = [(0, 3), (3, t)] if pieces else [(0, t)]
    for n, (a, b) in enumerate(splits):
        table = pa.table({k: _nested(v[a:b], fixed) for k, v in columns.items()})
        pq.write_table(table, folder / (f"scan_{n * 10}.parquet" if pieces
                                        else "scan_merged.parquet"))
    boxes = {r: {"cornerPoints": _y_up_box(i, 0.0, i + 1.0, 2.0, 0.5 + i)}
             for i, r in enumerate(RECEPTACLES)}
    for name, value in (("pickupable_names.json", objects),
                        ("receptacle_names.json", RECEPTACLES),
                        ("receptacles_oobb.json", boxes),
                        ("pickupable_to_receptacle.json", ALLOWED)):
        (folder / name).write_text(json.dumps(value, indent=4))


def write_lookup(folder: pathlib.Path) -> None:
    (folder / "lookup.json").write_text(json.dumps({
        "pickupable2id": {"Apple": 0, "Book": 1, "Mug": 2},
        "receptacle2id": {"CounterTop": 0, "Sofa": 1, "Sink": 2, "Bed": 3}}))


@pytest.fixture
def authors_root(tmp_path) -> pathlib.Path:
    """data/lookup.json above ROOT = data/habit1, holding train/env0 (scan_merged.parquet of
    fixed-size lists) and val/env1 (two scan_N.parquet pieces of variable-size lists)."""
    (tmp_path / "data").mkdir()
    write_lookup(tmp_path / "data")
    root = tmp_path / "data" / "habit1"
    write_authors_environment(root / "train" / "env0")
    write_authors_environment(root / "val" / "env1", pieces=True, fixed=False)
    return root


def test_an_authors_folder_imports(authors_root):
    from flowmaps_jax.recorded.flowmaps2026 import import_flowmaps2026

    world = import_flowmaps2026(authors_root)
    assert world.names() == ("train/env0", "val/env1")
    for env in world.environments:
        assert env.object_classes == ("Book", "Mug")
        assert env.receptacle_classes == ("Sofa", "CounterTop", "Sink")
        assert env.receptacle_texts == ("sofa", "counter top", "sink")
        np.testing.assert_array_equal(env.hours, np.arange(5))
        np.testing.assert_array_equal(env.location, [[0, 1], [0, 2], [1, -1], [1, 1], [0, 2]])
        np.testing.assert_array_equal(env.allowed, [[1, 1, 0], [0, 1, 1]])
        # their y is up: here z is
        np.testing.assert_allclose(env.receptacle_boxes()[2], [2.5, 1.0, 1.25, 1.0, 2.0, 2.5])
        np.testing.assert_array_equal(env.object_corners[:, 0, 0, 2], np.arange(5))
        np.testing.assert_array_equal(env.object_rotation, 0.5)
        assert env.room_classes == () and env.distance is None
    assert world.environments[1].source["scans"] == ["scan_0.parquet", "scan_10.parquet"]


def _remove(key):
    return lambda d: d.pop(key)


AUTHORS_CASES = {
    "names against counts": (
        lambda root: ((root / "pickupable_names.json").write_text(json.dumps([*OBJECTS, "Mug|9"])),
                      _edit_json(root / "pickupable_to_receptacle.json",
                                 _set("Mug|9", ["Sink|5|1|0___0"]))),
        "scan_merged.parquet: assignment: has 2 objects per row, but pickupable_names.json "
        "lists 3"),
    "id missing from oobb": (
        lambda root: _edit_json(root / "receptacles_oobb.json", _remove("Sink|5|1|0___0")),
        r"receptacles_oobb.json: Sink\|5\|1\|0___0: missing"),
    "class missing from lookup": (
        lambda root: _edit_json(root.parents[2] / "lookup.json",
                                lambda d: d["pickupable2id"].pop("Mug")),
        r"pickupable_names.json: Mug\|3: its class 'Mug' is missing from .*lookup.json"),
    "allowed unknown": (
        lambda root: _edit_json(root / "pickupable_to_receptacle.json",
                                lambda d: d["Mug|3"].append("Bed|1")),
        r"pickupable_to_receptacle.json: Mug\|3: 'Bed\|1' is not in receptacle_names.json"),
    "allowed missing": (
        lambda root: _edit_json(root / "pickupable_to_receptacle.json", _remove("Mug|3")),
        r"pickupable_to_receptacle.json: Mug\|3: missing"),
    "two receptacles": (
        lambda root: (root / "scan_merged.parquet").unlink() or write_authors_environment(
            root.parent / "env9", assignment=np.ones((2, 2, 3), np.int64)),
        "scan_merged.parquet: assignment: object 0 is on 3 receptacles at row 0"),
    "broken parquet": (
        lambda root: (root / "scan_merged.parquet").write_bytes(b"PAR1 not really"),
        r"scan_merged.parquet: \(file\): not a readable parquet file"),
}


@pytest.mark.parametrize("case", sorted(AUTHORS_CASES))
def test_import_refuses_a_folder_that_contradicts_itself(authors_root, case):
    from flowmaps_jax.recorded.flowmaps2026 import import_flowmaps2026

    edit, message = AUTHORS_CASES[case]
    edit(authors_root / "train" / "env0")
    with pytest.raises(ValueError, match=message) as info:
        import_flowmaps2026(authors_root)
    assert "\n" not in str(info.value)


def test_import_needs_a_lookup_and_an_environment(tmp_path):
    from flowmaps_jax.recorded.flowmaps2026 import import_flowmaps2026

    write_authors_environment(tmp_path / "root" / "env0")
    with pytest.raises(ValueError, match=r"lookup\.json: none in the folder or above it"):
        import_flowmaps2026(tmp_path / "root")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="holds no environment folder"):
        import_flowmaps2026(tmp_path / "empty")
    write_lookup(tmp_path / "root" / "env0")  # ROOT may be the environment folder itself
    assert import_flowmaps2026(tmp_path / "root" / "env0").names() == ("env0",)


def test_homes_through_the_authors_format_round_trip(homes, tmp_path):
    from flowmaps_jax.recorded.flowmaps2026 import export_flowmaps2026, import_flowmaps2026

    world = from_homes(homes, CONFIG, mask_fraction=0.3, seed=5)
    lookup = export_flowmaps2026(world, tmp_path / "authors")
    assert json.loads(lookup.read_text())["receptacle2id"]["sofa"] == \
        world.vocabulary()["receptacles"].index("sofa")
    table = pq.read_table(tmp_path / "authors/home0/scan_merged.parquet")
    env = world.environments[0]
    assert table.num_rows == CONFIG.num_hours
    assert str(table.schema.field("assignment").type).startswith("fixed_size_list")
    assignment = np.asarray(table.column("assignment").combine_chunks().flatten().flatten()
                            ).reshape(CONFIG.num_hours, env.num_objects, env.num_receptacles)
    # an unobserved hour is an all-zero row; an observed one is one-hot on its receptacle
    np.testing.assert_array_equal(assignment.sum(-1), env.observed)
    np.testing.assert_array_equal(np.where(env.observed, assignment.argmax(-1), -1),
                                  env.location)
    back = import_flowmaps2026(tmp_path / "authors")
    assert_same(world, back)  # identical arrays, ids, classes, texts, rooms, distances
    # without the extras file: the native columns alone give the same observations
    for name in world.names():
        (tmp_path / "authors" / name / "flowmaps_recorded.json").unlink()
    bare = import_flowmaps2026(tmp_path / "authors")
    for a, b in zip(world.environments, bare.environments, strict=True):
        for field in ("hours", "location", "allowed", "receptacle_corners"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
        assert (a.receptacle_ids, a.object_ids) == (b.receptacle_ids, b.object_ids)
        assert (a.receptacle_classes, a.object_classes) == (b.receptacle_classes,
                                                            b.object_classes)


def test_recorded_boxes_and_gaps_round_trip(tmp_path):
    from flowmaps_jax.recorded.flowmaps2026 import export_flowmaps2026, import_flowmaps2026

    rng = np.random.default_rng(0)
    env = tiny_environment("env0", object_corners=rng.normal(size=(4, 2, 8, 3)).astype(
        np.float32), object_rotation=rng.normal(size=(4, 2)).astype(np.float32))
    world = Recorded((env, tiny_environment("env1")))
    export_flowmaps2026(world, tmp_path / "a")
    table = pq.read_table(tmp_path / "a/env0/scan_merged.parquet")
    assert table.num_rows == 6  # hours 0, 1, 2, 5: rows 3 and 4 are all-zero assignments
    assert_same(world, import_flowmaps2026(tmp_path / "a"))


def test_export_writes_fixed_size_list_columns_as_their_loader_reads_them(tmp_path):
    """Their loader reads the columns as polars' fixed-size ``Array`` columns: nested
    fixed-size lists of [M, R] (assignment), [M] (rotation) and [M, 8, 3] (corner points)."""
    from flowmaps_jax.recorded.flowmaps2026 import export_flowmaps2026

    export_flowmaps2026(Recorded((tiny_environment("env0"),)), tmp_path)
    table = pq.read_table(tmp_path / "env0" / "scan_merged.parquet")
    assert table.num_rows == 6

    def sizes(kind):
        out = []
        while pa.types.is_fixed_size_list(kind):
            out.append(kind.list_size)
            kind = kind.value_type
        return out

    assert sizes(table.schema.field("assignment").type) == [2, 3]
    assert sizes(table.schema.field("rotation").type) == [2]
    assert sizes(table.schema.field("aabb_cornerPoints").type) == [2, 8, 3]
    assignment = np.asarray(table.column("assignment").to_pylist())
    assert assignment.shape == (6, 2, 3) and set(np.unique(assignment)) <= {0, 1}


# ---------------------------------------------------------------------------- the commands


def test_the_data_commands(homes, tmp_path, capsys):
    from support import error_line, run_cli

    from flowmaps_jax.data.__main__ import main

    code, out, _ = run_cli(main, ["from-homes", "--homes", "4", "--hours", "48", "--mask",
                                  "0.3", "--seed", "0", "--names", "train/env",
                                  "--no-progress", "--out", str(tmp_path / "w")], capsys)
    assert code == 0 and "wrote" in out and "4 environments, 48 hours" in out
    world = load_recorded(tmp_path / "w")
    assert world.names() == tuple(f"train/env{e}" for e in range(4))
    direct = from_homes(homes, CONFIG, mask_fraction=0.3, seed=0)
    for a, b in zip(direct.environments, world.environments, strict=True):
        np.testing.assert_array_equal(a.location, b.location)
        assert b.source["generator"]["num_homes"] == 4
    code, out, _ = run_cli(main, ["export-flowmaps2026", str(tmp_path / "w"), "--out",
                                  str(tmp_path / "a"), "--no-progress"], capsys)
    assert code == 0 and (tmp_path / "a/lookup.json").is_file()
    code, out, _ = run_cli(main, ["import-flowmaps2026", str(tmp_path / "a"), "--out",
                                  str(tmp_path / "w2"), "--no-progress"], capsys)
    assert code == 0
    assert_same(world, load_recorded(tmp_path / "w2"))
    (tmp_path / "a/train/env1/receptacles_oobb.json").write_text("{}")
    for argv, message in (
            (["import-flowmaps2026", str(tmp_path / "a"), "--out", str(tmp_path / "w3")],
             "receptacles_oobb.json: .*: missing"),
            (["export-flowmaps2026", str(tmp_path / "a"), "--out", str(tmp_path / "x")],
             r"recorded.json: \(file\): missing"),
            (["from-homes", "--homes", "2", "--mask", "1.5", "--out", str(tmp_path / "y")],
             "--mask must be in"),
            (["from-homes", "--homes", "0", "--out", str(tmp_path / "y")], "--homes must be")):
        code, _, err = run_cli(main, [*argv, "--no-progress"], capsys)
        assert code == 2, argv
        assert re.search(message, error_line(err)), err
    assert not (tmp_path / "w3").exists() and not (tmp_path / "y").exists()


def test_export_refuses_a_folder_holding_an_earlier_exports_environments(tmp_path):
    """An earlier export's env folders left beside a new one would be read with it (by their
    loader and by import); exporting the same names again (an update) is fine."""
    from flowmaps_jax.recorded.flowmaps2026 import export_flowmaps2026, import_flowmaps2026

    two = Recorded((tiny_environment("env0"), tiny_environment("env1")))
    export_flowmaps2026(two, tmp_path / "a")
    export_flowmaps2026(two, tmp_path / "a")  # the same environments again
    with pytest.raises(ValueError, match=r"^root: .*'env1' .*choose an empty folder"):
        export_flowmaps2026(Recorded((tiny_environment("env0"),)), tmp_path / "a")
    assert_same(two, import_flowmaps2026(tmp_path / "a"))  # nothing written


def test_export_refuses_a_linked_environment_folder(tmp_path):
    from flowmaps_jax.recorded.flowmaps2026 import export_flowmaps2026

    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "a" / "train").mkdir(parents=True)
    (tmp_path / "a" / "train" / "env0").symlink_to(tmp_path / "elsewhere")
    with pytest.raises(ValueError, match=r"^root: .*env0' is a symbolic link"):
        export_flowmaps2026(Recorded((tiny_environment("train/env0"),)), tmp_path / "a")
    assert not any((tmp_path / "elsewhere").iterdir())
