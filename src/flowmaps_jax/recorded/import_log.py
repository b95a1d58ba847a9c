"""A log of sightings (a CSV or parquet table: one row per sighting or search) as a recorded world:
``import_log(table, layout=None) -> Recorded``. The columns, the clock, the in-hour rule and the
layout file: docs/data.md, "Importing a log of sightings". Bad input is one ``ValueError`` line
naming the file, the row (1: the first after the header) and the column.
"""

from __future__ import annotations

import csv
import datetime
import itertools
import math
import os
import sys
from collections.abc import Callable

import numpy as np

from flowmaps_jax.flowsim.homes.config import MAX_HOURS
from flowmaps_jax.recorded.flowmaps2026 import Progress, _natural, _pyarrow, class_text
from flowmaps_jax.recorded.format import Environment, Recorded, check_environment_name
from flowmaps_jax.resources import check_request_size
from flowmaps_jax.untrusted_files import read_json

REQUIRED = ("environment", "timestamp", "object", "receptacle")
OPTIONAL = ("object_class", "receptacle_class", "room", "room_class", "object_text",
            "receptacle_text", "found")
FOUND = {"true": True, "1": True, "false": False, "0": False, "": True}
YEAR = 24 * 366
KEYS = {"receptacles": dict, "rooms": dict, "doors": list}
"""A layout file's keys per environment (each optional)."""


def read_table(file: str) -> dict[str, list]:
    """The columns of a CSV or ``.parquet`` table, as lists of cells (None: empty)."""
    if not os.path.isfile(file):
        raise ValueError(f"{file}: (file): missing, or not a regular file")
    check_request_size(file, 40 * os.path.getsize(file))
    if file.endswith(".parquet"):
        pa, pq = _pyarrow()
        try:
            table = pq.read_table(file)
        except (OSError, pa.ArrowException) as err:
            raise ValueError(f"{file}: (file): not a readable parquet file ({err})"[:300]) from None
        header = table.column_names
        columns = [table.column(name).to_pylist() for name in header]
    else:
        try:
            with open(file, newline="", encoding="utf-8-sig") as f:
                rows = list(csv.reader(f))
        except (UnicodeDecodeError, csv.Error) as err:
            raise ValueError(f"{file}: (file): not a readable UTF-8 CSV ({err})"[:300]) from None
        header, rows = (rows[0], rows[1:]) if rows else ([], [])
        bad = [i for i, row in enumerate(rows, 1) if len(row) != len(header)]
        if bad:
            raise ValueError(f"{file}: row {bad[0]}: (all): has {len(rows[bad[0] - 1])} cells; "
                             f"the header has {len(header)}")
        columns = [list(c) for c in zip(*rows, strict=True)] if rows else [[] for _ in header]
    twice = sorted({h for h in header if header.count(h) > 1})
    missing = [c for c in REQUIRED if c not in header]
    other = [h for h in header if h not in REQUIRED + OPTIONAL and not h.startswith("__index")]
    if twice or missing or other:
        raise ValueError(f"{file}: (header): " + (
            f"names {twice[0]!r} twice" if twice else f"misses the column {missing[0]!r} "
            f"(required: {', '.join(REQUIRED)})" if missing else f"{other[0]!r} is not a column "
            f"of the schema (optional: {', '.join(OPTIONAL)}); rename or drop it")[:300])
    if not columns[0]:
        raise ValueError(f"{file}: (all): the table has no rows")
    return {h: [None if v == "" else v for v in c] for h, c in zip(header, columns, strict=True)
            if h in REQUIRED + OPTIONAL}


def _text(file: str, row: int, column: str, value) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    if isinstance(value, bool | float):
        raise ValueError(f"{file}: row {row}: {column}: must be an id or name; got {value!r}")
    return str(value).strip()


def parse_times(file: str, values: list) -> tuple[np.ndarray, str]:
    """float64 (N,) hours on the recorded clock (ISO 8601: from Monday 00:00 of the earliest
    timestamp's week, the wall-clock time as written; numbers: hours), and that origin in words."""
    numbers, dates = {}, {}
    for row, v in enumerate(values, 1):
        for parse in (float, datetime.datetime.fromisoformat) if isinstance(v, str) else ():
            try:
                v = parse(v.strip())
                break
            except ValueError:
                pass
        if isinstance(v, datetime.date) and not isinstance(v, datetime.datetime):
            v = datetime.datetime(v.year, v.month, v.day)
        if isinstance(v, datetime.datetime):
            dates[row] = v.replace(tzinfo=None)
        elif isinstance(v, int | float) and not isinstance(v, bool):
            numbers[row] = float(v)
        else:
            raise ValueError(f"{file}: row {row}: timestamp: {values[row - 1]!r} is neither an "
                             f"ISO 8601 time nor a number of hours"[:300])
    if numbers and dates:
        row = min(numbers if len(numbers) < len(dates) else dates)
        raise ValueError(f"{file}: row {row}: timestamp: mixes numbers of hours and ISO 8601 "
                         f"times in one column")
    if numbers:
        bad = [r for r, v in numbers.items() if not (math.isfinite(v) and v >= 0)]
        if bad:
            raise ValueError(f"{file}: row {bad[0]}: timestamp: {numbers[bad[0]]} is not an hour "
                             f">= 0")
        return np.array(list(numbers.values())), "the table's numbers of hours"
    first = min(dates.values())
    monday = datetime.datetime(first.year, first.month, first.day) - datetime.timedelta(
        days=first.weekday())
    hours = [(d - monday).total_seconds() / 3600 for d in dates.values()]
    return np.array(hours), f"hours from Monday {monday.date().isoformat()} 00:00"


def check_clock(file: str, hours: np.ndarray, env: np.ndarray, numeric: bool,
                warn: Callable[[str], None]) -> None:
    """Refuse a clock beyond the format's hours; warn (one line) of a suspicious one."""
    order = np.lexsort((hours, env))
    h, same = hours[order], env[order][1:] == env[order][:-1]
    starts, ends = h[np.r_[True, ~same]], h[np.r_[~same, True]]
    gaps = np.diff(h)[same & (np.diff(h) > 0)]
    gap = float(np.median(gaps)) if gaps.size else 1.0
    fix = ("give hours (minutes / 60, seconds / 3600) or ISO 8601 times" if numeric else
           "check the dates")
    if hours.max() >= MAX_HOURS:
        raise ValueError(f"{file}: timestamp: reaches hour {int(hours.max())}, beyond the "
                         f"format's {MAX_HOURS} hours (7.5 years): " + "if the column holds "
                         "minutes or seconds, " * numeric + fix)
    notes = []
    if numeric and gap >= 2:
        notes.append(f"timestamps are mostly {gap:g} apart, not 1 hour: if they count minutes "
                     f"or seconds, {fix}")
    if np.max(ends - starts) > YEAR:
        notes.append(f"the timestamps span {np.max(ends - starts) / 8766:.1f} years: {fix}")
    if numeric and np.all(starts == 1):
        notes.append("hour 0 never occurs and every environment starts at hour 1: if the hours "
                     "count from 1, subtract 1 (hour 0 is Monday 00:00)")
    if notes:
        warn(f"{file}: timestamp: a suspicious clock: " + "; ".join(notes))


class _Env:
    """What the rows say of one environment: ids in order of first appearance, their classes,
    texts and rooms (checked for contradictions), and the events."""

    def __init__(self, file: str):
        self.file, self.ids, self.facts, self.events = file, {"o": {}, "r": {}, "k": {}}, {}, []

    def index(self, kind: str, key: str) -> int:
        return self.ids[kind].setdefault(key, len(self.ids[kind])) if key else -1

    def cls(self, kind: str) -> list[str]:
        column = {"o": "object_class", "r": "receptacle_class", "k": "room_class"}[kind]
        return [self.facts.get((column, i), (i,))[0] for i in self.ids[kind]]

    def put(self, row: int, column: str, key: str, value: str) -> None:
        if value:
            old = self.facts.setdefault((column, key), (value, row))
            if old[0] != value:
                raise ValueError(f"{self.file}: row {row}: {column}: {key!r} is {value!r} here "
                                 f"and {old[0]!r} in row {old[1]}"[:300])


def import_log(table, layout=None, progress: Progress = None,
               warn: Callable[[str], None] | None = None) -> Recorded:
    """The recorded world of the table ``table`` (CSV or parquet) and the optional layout JSON;
    ``warn`` gets the one line about a suspicious clock (default: printed to stderr)."""
    file = os.fspath(table)
    if layout is not None and not os.path.isfile(layout):
        raise ValueError(f"--layout: {os.fspath(layout)!r} is missing, or not a regular file")
    warn = warn or (lambda line: print(f"warning: {line}", file=sys.stderr))
    cols = read_table(file)
    n = len(cols["environment"])
    get = {c: cols.get(c, [None] * n) for c in REQUIRED + OPTIONAL}
    hours, origin = parse_times(file, get["timestamp"])
    names = [_text(file, i, "environment", v) for i, v in enumerate(get["environment"], 1)]
    first: dict[str, int] = {}  # each name's first row
    for row, name in enumerate(names, 1):
        first.setdefault(name, row)
    for name, row in first.items():
        try:
            check_environment_name(name, "environment")
        except ValueError as err:
            raise ValueError(f"{file}: row {row}: {err}") from None
    codes = np.unique(np.array(names), return_inverse=True)[1]
    check_clock(file, hours, codes, origin.startswith("the table"), warn)
    envs: dict[str, _Env] = {}
    for i in progress(range(n)) if progress else range(n):
        row = i + 1
        obj, rec, room = (_text(file, row, c, get[c][i]) for c in ("object", "receptacle", "room"))
        found = get["found"][i]  # text, a boolean, or a number (0/1; NaN: empty) from parquet
        found = "" if found is None or found != found else str(
            int(found) if isinstance(found, float) and found in (0, 1) else found)
        found = FOUND.get(found.strip().lower())
        if found is None:
            raise ValueError(f"{file}: row {row}: found: {get['found'][i]!r} is not true/false "
                             f"or 1/0"[:300])
        if not (rec or room) or (found and not (obj and rec)):
            raise ValueError(f"{file}: row {row}: {'receptacle' if obj else 'object'}: is empty; "
                             f"a sighting names the object and its receptacle, a not-found row "
                             f"a receptacle or a room")
        e = envs.setdefault(names[i], _Env(file))
        for column, key in (("object_class", obj), ("object_text", obj), ("receptacle_class", rec),
                            ("receptacle_text", rec), ("room_class", room)):
            if key:
                e.put(row, column, key, _text(file, row, column, get[column][i]))
        if rec:
            e.put(row, "room", rec, room)
        e.events.append((hours[i], row, e.index("o", obj), e.index("r", rec),
                         e.index("k", room), found))
    pairs = set()  # (object class, receptacle class) of every sighting: allowed
    for e in envs.values():
        oc, rc = e.cls("o"), e.cls("r")
        pairs |= {(oc[m], rc[r]) for _, _, m, r, _, found in e.events if found}
    geometry = _layout(os.fspath(layout), envs) if layout is not None else {}
    return Recorded(tuple(_environment(name, envs[name], pairs, origin, geometry.get(name))
                          for name in sorted(envs, key=_natural)))


def _environment(name: str, e: _Env, pairs: set, origin: str, geometry) -> Environment:
    """One environment from its rows: the latest sighting in an hour is the object's location;
    a not-found row marks ``not_at`` except where the hour's location is that receptacle."""
    obj, rec = list(e.ids["o"]), list(e.ids["r"])
    cls = {k: e.cls(k) for k in "ork"}
    room_of = np.array([e.ids["k"].get(e.facts.get(("room", r), ("",))[0], -1) for r in rec],
                       np.int32)
    first = int(min(ev[0] for ev in e.events) // 1)
    t, m, r = int(max(ev[0] for ev in e.events) // 1) - first + 1, len(obj), len(rec)
    check_request_size(f"{e.file}: environment {name!r}: {t} hours x {m} objects x {r} "
                       f"receptacles", t * m * r)
    location, not_at = np.full((t, m), -1, np.int32), np.zeros((t, m, r), bool)
    for time, _, mo, re_, ro, found in sorted(e.events, key=lambda ev: ev[:2]):
        h = int(time // 1) - first
        if found:
            location[h, mo] = re_
        else:
            not_at[h, slice(None) if mo < 0 else mo, [re_] if re_ >= 0 else room_of == ro] = True
    not_at &= location[..., None] != np.arange(r)
    allowed = np.array([[(a, b) in pairs for b in cls["r"]] for a in cls["o"]]).reshape(m, r)
    allowed[~allowed.any(axis=1)] = True
    corners, boxes, doors = geometry or (None, None, None)
    return Environment(
        name=name, receptacle_ids=tuple(rec), receptacle_classes=tuple(cls["r"]),
        receptacle_texts=tuple(e.facts.get(("receptacle_text", i), (class_text(c),))[0]
                               for i, c in zip(rec, cls["r"], strict=True)),
        receptacle_room=room_of, receptacle_corners=corners, object_ids=tuple(obj),
        object_classes=tuple(cls["o"]),
        object_texts=tuple(e.facts.get(("object_text", i), (class_text(c),))[0]
                           for i, c in zip(obj, cls["o"], strict=True)),
        allowed=allowed, hours=np.arange(first, first + t, dtype=np.int64), location=location,
        not_at=not_at, room_classes=tuple(cls["k"]), room_boxes=boxes,
        door_rooms=None if doors is None else doors[0],
        door_positions=None if doors is None else doors[1],
        source={"from": "import-log", "table": os.path.basename(e.file), "time": origin})


def _numbers(where: str, value, sizes: tuple, what: str) -> np.ndarray:
    try:
        array = np.array(value, np.float64)
    except (TypeError, ValueError):
        array = np.zeros(0)
    if array.shape not in sizes or not np.all(np.isfinite(array)):
        raise ValueError(f"{where}: must be {what}; got {value!r}"[:300])
    return array


def _corners(where: str, value) -> np.ndarray:
    """float32 (8, 3): 8 corners as given, or those of an axis-aligned box (cx, cy, cz, w, d, h)."""
    a = _numbers(where, value, ((8, 3), (6,)), "8 corners [x, y, z] or a box [cx, cy, cz, w, d, h]")
    signs = np.array(list(itertools.product((-0.5, 0.5), repeat=3)))
    return (a if a.shape == (8, 3) else a[:3] + signs * a[3:]).astype(np.float32)


def _layout(file: str, envs: dict[str, _Env]) -> dict:
    """Per environment the layout file names: (receptacle corners (R, 8, 3) or None, room boxes
    (K, 4) or None, (door rooms (D, 2), door positions (D, 2)) or None); rooms only the layout
    names are added to the environment."""
    data = read_json("--layout", file)
    if not isinstance(data, dict):
        raise ValueError(f"{file}: (top level): must be an object of environment -> layout")
    out = {}
    for name, spec in data.items():
        where = f"{file}: {name}"
        spec = spec if isinstance(spec, dict) else {"": spec}
        recs, rooms, doors = (spec.get(k, t()) for k, t in KEYS.items())
        if name not in envs or set(spec) - set(KEYS) or not all(
                isinstance(v, t) for v, t in zip((recs, rooms, doors), KEYS.values(), strict=True)):
            raise ValueError(f"{where}: must be an environment of the table, with an object of "
                             f"receptacles {{id: box}}, rooms {{id: box}} and a list of doors")
        e = envs[name]
        for key in rooms:
            e.index("k", key)
        for kind, ids, given in (("receptacles", e.ids["r"], recs), ("rooms", e.ids["k"], rooms)):
            extra = sorted(set(given) - set(ids))
            missing = sorted(set(ids) - set(given)) if given or recs else []  # boxes need rooms
            if extra or missing:
                raise ValueError(f"{where}: {kind}: " + (
                    f"names {extra[0]!r}, not a {kind[:-1]} of the table" if extra else
                    f"misses {missing[0]!r} (give every {kind[:-1]} a box, or none)"))
        corners = None if not recs else np.stack([
            _corners(f"{where}: receptacles.{r}", recs[r]) for r in e.ids["r"]])
        boxes = None if not rooms else np.stack([_numbers(
            f"{where}: rooms.{k}", rooms[k], ((4,),), "a box [x0, y0, x1, y1]")
            for k in e.ids["k"]]).astype(np.float32)
        pairs = []
        for i, door in enumerate(doors):
            ok = isinstance(door, dict) and set(door) - {"position"} == {"rooms"} and isinstance(
                door["rooms"], list) and len(door["rooms"]) == 2
            if not ok or any(not isinstance(k, str) or k not in e.ids["k"] for k in door["rooms"]):
                raise ValueError(f"{where}: doors[{i}]: must be {{\"rooms\": [two room ids], "
                                 f"\"position\": [x, y] (optional)}}; got {door!r}"[:300])
            pairs.append(([e.ids["k"][k] for k in door["rooms"]], None if "position" not in door
                          else _numbers(f"{where}: doors[{i}].position", door["position"],
                                        ((2,),), "[x, y]")))
        at = [b for _, b in pairs if b is not None]
        if at and len(at) < len(pairs):
            raise ValueError(f"{where}: doors: give every door a position, or none")
        out[name] = (corners, boxes, None if not pairs else (
            np.array([a for a, _ in pairs], np.int32), np.array(at, np.float32) if at else None))
    return out
