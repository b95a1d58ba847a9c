"""``python -m flowmaps_jax.data import-log`` (issue 56, item 2): a table of sightings (CSV or
parquet) as a recorded world, the in-hour rule, negative evidence, the clock checks and the
one-line refusals (docs/data.md, "Importing a log of sightings")."""

from __future__ import annotations

import csv
import datetime
import json

import numpy as np
import pytest

from flowmaps_jax.data.__main__ import main as data_main
from flowmaps_jax.recorded.format import Environment, Recorded, load_recorded
from flowmaps_jax.recorded.import_log import import_log

HEADER = ("environment", "timestamp", "object", "object_class", "receptacle",
          "receptacle_class", "room", "found")


def _csv(path, rows, header=HEADER):
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows([header, *rows])
    return path


def _parquet(path, rows, header=HEADER):
    import pyarrow as pa
    import pyarrow.parquet as pq

    columns = {h: [r[i] for r in rows] for i, h in enumerate(header)}
    pq.write_table(pa.table(columns), path)
    return path


# A day in one home (ISO times; Monday 2026-03-02 is hour 0 of the week): hour 8 the mug is seen
# twice (the sink, later, wins) and a search of the sink before that sighting is dropped; hour 9
# nothing; hour 10 the kitchen is searched for the mug, and the shelf is searched for everything.
ROWS = [
    ("home1", "2026-03-04T08:50:00", "mug_1", "mug", "sink_1", "sink", "kitchen", "true"),
    ("home1", "2026-03-04T08:10:00", "mug_1", "mug", "table_1", "table", "kitchen", "true"),
    ("home1", "2026-03-04T08:20:00", "mug_1", "mug", "sink_1", "sink", "kitchen", "false"),
    ("home1", "2026-03-04T08:30:00", "book_1", "book", "shelf_1", "shelf", "living", ""),
    ("home1", "2026-03-04T10:05:00", "mug_1", "mug", "", "", "kitchen", "false"),
    ("home1", "2026-03-04T10:30:00", "", "", "shelf_1", "shelf", "living", "0"),
    ("home1", "2026-03-04T10:40:00", "book_1", "book", "shelf_1", "shelf", "living", "1"),
]


def _expected_rows():
    hours = np.arange(56, 59)  # Wednesday 08:00 .. 10:00
    location = np.array([[0, 2], [-1, -1], [-1, 2]])  # (T, M): mug_1, book_1
    not_at = np.zeros((3, 2, 3), bool)  # receptacles sink_1, table_1, shelf_1 (first named)
    not_at[2, 0, [0, 1]] = True  # the kitchen searched for the mug
    not_at[2, 0, 2] = True  # the shelf searched: the mug is not there, the book is
    return hours, location, not_at


@pytest.mark.parametrize("kind", ["csv", "parquet"])
def test_a_table_round_trips_through_the_command(tmp_path, kind, capsys):
    parquet = [(r[0], datetime.datetime.fromisoformat(r[1]), *r[2:7],
                {"true": 1.0, "1": 1.0, "": float("nan")}.get(r[7], 0.0)) for r in ROWS]
    rows = parquet if kind == "parquet" else ROWS  # parquet: native times, found 0/1/NaN
    table = (_csv if kind == "csv" else _parquet)(tmp_path / f"log.{kind}", rows)
    assert data_main(["import-log", str(table), "--out", str(tmp_path / "d"),
                      "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "1 environment, 3 hours, 2 objects, 3 receptacles" in out
    assert "50.0 % of the object-hours observed" in out  # 3 of 3 hours x 2 objects
    assert "16.7 % with negative evidence" in out  # the mug at hour 10
    (env,) = load_recorded(tmp_path / "d").environments
    hours, location, not_at = _expected_rows()
    np.testing.assert_array_equal(env.hours, hours)
    np.testing.assert_array_equal(env.location, location)
    np.testing.assert_array_equal(env.not_at, not_at)
    assert env.object_ids == ("mug_1", "book_1")
    assert env.receptacle_ids == ("sink_1", "table_1", "shelf_1")
    assert env.room_classes == ("kitchen", "living") and env.receptacle_corners is None
    assert list(env.receptacle_room) == [0, 0, 1]
    assert env.source["time"] == "hours from Monday 2026-03-02 00:00"
    assert data_main(["validate", str(tmp_path / "d")]) == 0


def test_the_latest_sighting_in_an_hour_wins_and_searches_never_contradict_it(tmp_path):
    rows = [("h", "3.9", "m", "", "b", "", "", "1"), ("h", "3.2", "m", "", "a", "", "", "1"),
            ("h", "3.5", "m", "", "b", "", "", "0"),  # dropped: m is on b at hour 3
            ("h", "3.95", "m", "", "a", "", "", "0"),  # kept: a is not the hour's location
            ("h", "4.5", "m", "", "c", "", "", "1"), ("h", "4.5", "m", "", "a", "", "", "1")]
    (env,) = import_log(_csv(tmp_path / "t.csv", rows)).environments
    assert env.receptacle_ids == ("b", "a", "c")
    np.testing.assert_array_equal(env.location[:, 0], [0, 1])  # hour 4: equal times, later row
    np.testing.assert_array_equal(env.not_at[:, 0], [[False, True, False], [False] * 3])


def test_negative_rows_by_receptacle_by_room_and_for_every_object(tmp_path):
    rows = [("h", "0", "cup", "", "t1", "", "k", ""), ("h", "0", "pen", "", "t2", "", "k", ""),
            ("h", "0", "key", "", "d1", "", "o", ""),
            ("h", "1", "cup", "", "t2", "", "", "false"),  # one receptacle
            ("h", "2", "pen", "", "", "", "k", "false"),  # every receptacle of the room
            ("h", "3", "key", "", "t1", "", "", "1"),
            ("h", "3", "", "", "t1", "", "", "false"),  # everything not seen on t1 at hour 3
            ("h", "3", "hat", "", "d1", "", "", "false")]  # never seen: may stand anywhere
    (env,) = import_log(_csv(tmp_path / "t.csv", rows)).environments
    assert env.object_ids == ("cup", "pen", "key", "hat")
    assert env.receptacle_ids == ("t1", "t2", "d1")
    expected = np.zeros((4, 4, 3), bool)
    expected[1, 0, 1] = True
    expected[2, 1, [0, 1]] = True
    expected[3, [0, 1, 3], 0] = True  # the key is on t1 at hour 3
    expected[3, 3, 2] = True
    np.testing.assert_array_equal(env.not_at, expected)
    assert env.location[3].tolist() == [-1, -1, 0, -1]
    assert env.allowed.tolist() == [[True, False, False], [False, True, False],
                                    [True, False, True], [True] * 3]  # classes seen: the ids


def _table_of(recorded: Recorded, path):
    """A recorded world without geometry as a table of sightings and searches (hours)."""
    rows = []
    for env in recorded.environments:
        for t, m, r in zip(*np.nonzero(env.not_at), strict=True):
            rows.append((env.name, int(env.hours[t]), env.object_ids[m], env.object_classes[m],
                         env.receptacle_ids[r], env.receptacle_classes[r],
                         env.room_classes[env.receptacle_room[r]], "false"))
        for t, m in zip(*np.nonzero(env.location >= 0), strict=True):
            r = env.location[t, m]
            rows.append((env.name, int(env.hours[t]), env.object_ids[m], env.object_classes[m],
                         env.receptacle_ids[r], env.receptacle_classes[r],
                         env.room_classes[env.receptacle_room[r]], "true"))
    return _csv(path, rows[::-1])


def _facts(env: Environment) -> dict:
    """What an environment says, by ids (independent of the order of its lists)."""
    o, r = env.object_ids, env.receptacle_ids
    return {"hours": env.hours.tolist(), "rooms": {r[i]: env.room_classes[k]
                                                   for i, k in enumerate(env.receptacle_room)},
            "seen": {(int(env.hours[t]), o[m], r[env.location[t, m]])
                     for t, m in zip(*np.nonzero(env.location >= 0), strict=True)},
            "not": {(int(env.hours[t]), o[m], r[k]) for t, m, k in zip(*np.nonzero(env.not_at),
                                                                       strict=True)},
            "allowed": {(o[m], r[k]) for m, k in zip(*np.nonzero(env.allowed), strict=True)},
            "classes": (dict(zip(o, env.object_classes, strict=True)),
                        dict(zip(r, env.receptacle_classes, strict=True)))}


def test_a_dataset_from_arrays_exported_to_a_table_imports_equal(tmp_path):
    rng = np.random.default_rng(0)
    envs = []
    for e, hours in enumerate((30, 50)):
        location = rng.integers(0, 4, (hours, 3)).astype(np.int32)
        location[4:-1][rng.random((hours - 5, 3)) < 0.4] = -1  # the first 4 and last seen
        location[:4] = [[0, 1, 2], [1, 2, 3], [2, 3, 0], [3, 0, 1]]  # every class on every one
        not_at = (rng.random((hours, 3, 4)) < 0.1) & (location[..., None] != np.arange(4))
        envs.append(Environment(
            name=f"home{e}", receptacle_ids=("a", "b", "c", "d"),
            receptacle_classes=("table", "sink", "shelf", "table"),
            receptacle_texts=("table", "sink", "shelf", "table"),
            receptacle_room=np.array([0, 0, 1, 1], np.int32), receptacle_corners=None,
            object_ids=("x", "y", "z"), object_classes=("mug", "mug", "book"),
            object_texts=("mug", "mug", "book"), allowed=np.ones((3, 4), bool),
            hours=np.arange(10 + e, 10 + e + hours), location=location, not_at=not_at,
            room_classes=("kitchen", "living")))
    recorded = Recorded(tuple(envs))
    again = import_log(_table_of(recorded, tmp_path / "t.csv"))
    assert again.names() == recorded.names()
    for a, b in zip(recorded.environments, again.environments, strict=True):
        assert _facts(a) == _facts(b)


def _clock(tmp_path, times, name="t.csv"):
    rows = [("h", t, "m", "", "r", "", "", "") for t in times]
    lines = []
    recorded = import_log(_csv(tmp_path / name, rows), warn=lines.append)
    return recorded, lines


@pytest.mark.parametrize(("times", "says"), [
    (range(1, 49), "subtract 1"),  # hours counted from 1
    (range(0, 2 * 24 * 60, 15), "mostly 15 apart"),  # minutes, every 15
    (range(0, 3600, 60), "mostly 60 apart"),  # seconds, every minute, for an hour
])
def test_a_suspicious_clock_gets_one_warning_line_naming_the_file_and_the_fix(tmp_path, times,
                                                                              says):
    _, lines = _clock(tmp_path, times)
    assert len(lines) == 1 and "\n" not in lines[0]
    assert lines[0].startswith(f"{tmp_path / 't.csv'}: timestamp: a suspicious clock")
    assert says in lines[0]


def test_a_seconds_column_beyond_the_formats_hours_is_refused(tmp_path):
    with pytest.raises(ValueError, match=r"t\.csv: timestamp: reaches hour 169200, beyond the "
                                         r"format's 65536 hours .* seconds / 3600"):
        _clock(tmp_path, range(0, 2 * 86400, 3600))


def test_the_command_prints_the_warning_once(tmp_path, capsys):
    table = _csv(tmp_path / "t.csv", [("h", t, "m", "", "r", "", "", "") for t in range(1, 49)])
    assert data_main(["import-log", str(table), "--out", str(tmp_path / "d"),
                      "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert err.count("warning:") == 1 and str(table) in err and "subtract 1" in err


def test_iso_times_with_days_between_and_a_good_clock_say_nothing(tmp_path):
    recorded, lines = _clock(tmp_path, ["2026-03-02T08:15", "2026-03-02T09:00+02:00",
                                        "2026-03-05T10:59:59", "2026-03-05T11:00Z"])
    (env,) = recorded.environments
    assert lines == [] and env.hours[0] == 8 and env.hours[-1] == 3 * 24 + 11
    assert env.location[[0, 1, -2, -1], 0].tolist() == [0] * 4
    assert (env.location[2:-2] == -1).all()  # the days between: not observed
    _, lines = _clock(tmp_path, ["2024-01-01T00:00", "2026-06-01T00:00"])
    assert len(lines) == 1 and "span 2.4 years" in lines[0]
    with pytest.raises(ValueError, match=r"t\.csv: timestamp: reaches hour 70128, beyond the "
                                         r"format's 65536 hours \(7\.5 years\): check the dates"):
        _clock(tmp_path, ["2024-01-01T00:00", "2032-01-01T00:00"])


@pytest.mark.parametrize(("row", "says"), [
    (("h", "1", "m", "", "r", "", "", "maybe"), "row 2: found: 'maybe' is not"),
    (("h", "yesterday", "m", "", "r", "", "", ""), "row 2: timestamp: 'yesterday'"),
    (("h", "2026-03-02T10:00", "m", "", "r", "", "", ""), "row 2: timestamp: mixes"),
    (("h", "1", "m", "", "r", "", "k2", ""), "row 2: room: 'r' is 'k2' here and 'k' in row 1"),
    (("h", "1", "m", "", "", "", "k", "true"), "row 2: receptacle: is empty"),
    (("h", "-2", "m", "", "r", "", "", ""), "row 2: timestamp: -2.0 is not an hour"),
    (("../h", "1", "m", "", "r", "", "", ""), "row 2: environment '../h' must be"),
    (("h", "1", "m", "book", "r", "", "", ""), "row 2: object_class: 'm' is 'book' here"),
    (("h", "1", "m", "", "r", "", ""), "row 2: (all): has 7 cells; the header has 8"),
    (None, "(header): misses the column 'object'"),
    ("typo", "(header): 'recepatcle_class' is not a column of the schema"),
])
def test_bad_input_is_one_line_naming_the_file_row_and_column(tmp_path, capsys, row, says):
    first = ("h", "0", "m", "mug", "r", "", "k", "")
    header = (*HEADER[:5], "recepatcle_class", *HEADER[6:]) if row == "typo" else HEADER
    table = (_csv(tmp_path / "t.csv", [first, row], header) if isinstance(row, tuple) else
             _csv(tmp_path / "t.csv", [first[:2] + first[3:]], HEADER[:2] + HEADER[3:]) if not row
             else _csv(tmp_path / "t.csv", [first], header))
    assert data_main(["import-log", str(table), "--out", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{table}: {says}" in err, err
    assert not (tmp_path / "d").exists()


def test_a_layout_gives_geometry_and_must_name_every_receptacle(tmp_path):
    table = _csv(tmp_path / "t.csv", [("h", "0", "m", "", "a", "", "k", ""),
                                      ("h", "1", "m", "", "b", "", "l", "")])
    layout = {"h": {"receptacles": {"a": [0.5, 0.5, 0.4, 1, 1, 0.8],
                                    "b": [[x, y, z] for x in (3, 4) for y in (0, 1)
                                          for z in (0, 1)]},
                    "rooms": {"k": [0, 0, 2, 2], "l": [2, 0, 5, 2]},
                    "doors": [{"rooms": ["k", "l"], "position": [2, 1]}]}}
    (tmp_path / "layout.json").write_text(json.dumps(layout))
    (env,) = import_log(table, tmp_path / "layout.json").environments
    np.testing.assert_allclose(env.receptacle_boxes()[0], [0.5, 0.5, 0.4, 1, 1, 0.8])
    assert env.door_rooms.tolist() == [[0, 1]] and env.room_boxes.shape == (2, 4)
    assert env.walking_distance()[0, 1] == pytest.approx(2 * np.hypot(1.5, 0.5))
    del layout["h"]["receptacles"]["b"]
    (tmp_path / "layout.json").write_text(json.dumps(layout))
    with pytest.raises(ValueError, match=r"layout.json: h: receptacles: misses 'b' \(give every "
                                         r"receptacle a box, or none\)"):
        import_log(table, tmp_path / "layout.json")
    layout["h"] = {"receptacles": {"a": [0, 0, 0, 1, 1, 1], "b": [3, 0, 0, 1, 1, 1]}}
    (tmp_path / "layout.json").write_text(json.dumps(layout))
    with pytest.raises(ValueError, match=r"layout.json: h: rooms: misses 'k' \(give every room"):
        import_log(table, tmp_path / "layout.json")


@pytest.mark.parametrize(("layout", "says"), [
    ({"h": {"receptacles": []}}, "h: must be an environment of the table, with an object"),
    ({"g": {}}, "g: must be an environment of the table"),
    ({"h": {"receptacles": {"a": [1, 2, 3]}}}, "h: receptacles.a: must be 8 corners"),
    ({"h": {"doors": [{"rooms": ["k", "x"]}]}}, "h: doors[0]: must be"),
    ([1], "(top level): must be an object"),
    (None, "--layout: '"),
])
def test_a_bad_layout_is_one_line_naming_it(tmp_path, capsys, layout, says):
    table = _csv(tmp_path / "t.csv", [("h", "0", "m", "", "a", "", "", "")])
    if layout is not None:
        (tmp_path / "layout.json").write_text(json.dumps(layout))
    assert data_main(["import-log", str(table), "--layout", str(tmp_path / "layout.json"),
                      "--out", str(tmp_path / "d"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and says in err and "layout.json" in err, err
    assert not (tmp_path / "d").exists()
