"""Recorded worlds on disk: plain JSON and ``.npz`` files, the in-memory ``Recorded`` and a loader
that refuses bad files (the format: docs/data.md).

``PATH/recorded.json`` (the index), ``PATH/<name>/environment.json`` and
``PATH/<name>/arrays.npz`` (hours (T,) int64, location (T, M) int32, −1 not observed;
receptacle_corners (R, 8, 3) float32, absent in version 2 = no geometry; optional distance
(R, R), object_corners (T, M, 8, 3), object_rotation (T, M), and in version 2 not_at_bits
(T, M, ⌈R / 8⌉) uint8 = ``numpy.packbits(not_at, axis=-1)``). Names are relative POSIX paths;
metres and hours, z up. A dataset is written as version 1 unless it uses a version-2 field.
``load_recorded(path)`` raises one-line ``ValueError`` ``"<file>: <field>: what is wrong"`` for
anything ``save_recorded`` could not have written; ``save_recorded`` writes every file aside and
renames them together, never through a symbolic link; ``validate_environment`` applies the
loader's checks to an in-memory ``Environment``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import itertools
import json
import os
import pathlib
import re
import shlex
from typing import Any

import numpy as np

from flowmaps_jax.atomic_files import make_output_dir, write_files
from flowmaps_jax.resources import (
    SEQUENTIAL_FLOPS,
    check_request_size,
    check_resources,
    memory_limit,
)
from flowmaps_jax.untrusted_files import read_json, read_npz
from flowmaps_jax.validation import check_dir, check_output_dir

FORMAT = "flowmaps-recorded"
VERSION = 2
VERSIONS = (1, 2)
INDEX_FILE = "recorded.json"
ENVIRONMENT_FILE = "environment.json"
ARRAYS_FILE = "arrays.npz"
UNITS = {"length": "metres", "time": "hours"}
TIME = "hour t counts from Monday 00:00 of the first week"

REQUIRED_ARRAYS = ("hours", "location")
OPTIONAL_ARRAYS = ("receptacle_corners", "distance", "object_corners", "object_rotation")
ARRAYS = (*REQUIRED_ARRAYS, *OPTIONAL_ARRAYS, "not_at")
ROOM_CHANGE_COST = 5.0
EXAMINE_COST = 4.0
"""Without geometry a walk costs ``ROOM_CHANGE_COST`` per room change and ``EXAMINE_COST`` per
receptacle examined, as SGM's find-object task counts them (5 to travel to another room; 1 up
to the room, 1 down to the furniture and 2 to examine it)."""
_JSON_NAMES = {"receptacle_ids": ("receptacles", "id"),
               "receptacle_classes": ("receptacles", "class"),
               "receptacle_texts": ("receptacles", "text"),
               "receptacle_room": ("receptacles", "room"),
               "object_ids": ("objects", "id"), "object_classes": ("objects", "class"),
               "object_texts": ("objects", "text"), "allowed": ("objects", "allowed"),
               "room_classes": ("rooms", "class"), "room_boxes": ("rooms", "box"),
               "door_rooms": ("doors", "rooms"), "door_positions": ("doors", "position")}
"""Where each ``Environment`` field lives in ``environment.json`` (for load's messages)."""
_ENV_KEYS = ("receptacles", "objects", "rooms", "doors", "source")
_ENTRY_KEYS = {"receptacles": ("id", "class", "text", "room"),
               "objects": ("id", "class", "text", "allowed"),
               "rooms": ("class", "box"), "doors": ("rooms", "position")}
_INDEX_KEYS = ("format", "version", "environments", "units", "time")
_PART = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.+-]{0,63}")
MAX_NAME = 255
MAX_TEXT = 256
SYMMETRY_ATOL = 1e-3
AUTHORS_SCAN = re.compile(r"scan_(merged|[0-9]+)\.parquet")
"""The authors' scan files: a folder holding one needs ``import-flowmaps2026`` (named on load)."""
"""How far apart (metres) ``distance[i, j]`` and ``distance[j, i]`` may be (float round-off of
a shortest-path computation)."""


# ------------------------------------------------------------------------------ the API


@dataclasses.dataclass(frozen=True, eq=False)
class Environment:
    """One recorded environment: R receptacles, M objects, T timestamps (hours).

    receptacle_room: int32 (R,), index into ``room_classes`` (-1: unknown);
    receptacle_corners: float32 (R, 8, 3), the receptacle's oriented box (x, y, z up), metres,
    or None (no geometry: a scene graph of rooms, receptacles and objects);
    allowed: bool (M, R), the receptacles each object may stand on;
    hours: int64 (T,), strictly increasing, >= 0; location: int32 (T, M), the receptacle each
    object was seen on at each hour, -1 = not observed;
    room_boxes: float32 (K, 4) (x0, y0, x1, y1); door_rooms: int32 (D, 2); door_positions:
    float32 (D, 2) (None when there are no rooms / doors; boxes and positions may be None
    without geometry);
    distance: float32 (R, R) walking distances as stored (None: derived, see
    ``walking_distance``); object_corners: float32 (T, M, 8, 3) and object_rotation: float32
    (T, M), optional per-hour object boxes (the authors' ``aabb_cornerPoints`` and
    ``rotation``); source: free-form provenance (JSON); not_at: bool (T, M, R) or None,
    object m was looked for on receptacle r at hour index t and was not there (False where
    it was seen).
    """

    name: str
    receptacle_ids: tuple[str, ...]
    receptacle_classes: tuple[str, ...]
    receptacle_texts: tuple[str, ...]
    receptacle_room: np.ndarray
    receptacle_corners: np.ndarray | None
    object_ids: tuple[str, ...]
    object_classes: tuple[str, ...]
    object_texts: tuple[str, ...]
    allowed: np.ndarray
    hours: np.ndarray
    location: np.ndarray
    room_classes: tuple[str, ...] = ()
    room_boxes: np.ndarray | None = None
    door_rooms: np.ndarray | None = None
    door_positions: np.ndarray | None = None
    distance: np.ndarray | None = None
    object_corners: np.ndarray | None = None
    object_rotation: np.ndarray | None = None
    source: dict = dataclasses.field(default_factory=dict)
    not_at: np.ndarray | None = None

    @property
    def num_hours(self) -> int:
        """T."""
        return int(np.shape(self.hours)[0])

    @property
    def num_objects(self) -> int:
        """M."""
        return len(self.object_ids)

    @property
    def num_receptacles(self) -> int:
        """R."""
        return len(self.receptacle_ids)

    @property
    def observed(self) -> np.ndarray:
        """bool (T, M): whether each object was seen at each hour."""
        return np.asarray(self.location) >= 0

    @property
    def version(self) -> int:
        """The format version the environment needs: 2 without geometry or with ``not_at``."""
        return 2 if self.receptacle_corners is None or self.not_at is not None else 1

    def receptacle_boxes(self) -> np.ndarray:
        """float32 (R, 6): the axis-aligned box (cx, cy, cz, w, d, h) around each receptacle's
        corners, metres (zeros without geometry)."""
        if self.receptacle_corners is None:
            return np.zeros((self.num_receptacles, 6), np.float32)
        corners = np.asarray(self.receptacle_corners, np.float32)
        low, high = corners.min(axis=1), corners.max(axis=1)
        return np.concatenate([(low + high) / 2, high - low], axis=-1).astype(np.float32)

    def walking_distance(self) -> np.ndarray:
        """float32 (R, R) walking distances, metres: the stored ``distance``, else derived.

        Derived: geodesic through doors (straight lines within a room, between box centres on
        the floor, through door positions) when rooms, doors and every receptacle's room are
        known; otherwise, and for pairs that no door path joins, the straight-line distance
        between the box centres on the floor (x, y). Without geometry: :meth:`room_costs`."""
        if self.distance is not None:
            return np.asarray(self.distance, np.float32)
        if self.receptacle_corners is None:
            return self.room_costs()
        centre = self.receptacle_boxes()[:, :2].astype(np.float64)
        straight = np.linalg.norm(centre[:, None] - centre[None], axis=-1)
        room = np.asarray(self.receptacle_room)
        if self.room_boxes is None or self.door_rooms is None or np.any(room < 0):
            return straight.astype(np.float32)
        check_walk(f"environment {self.name!r}", len(room), len(self.door_rooms))
        geodesic = _geodesic(centre, room, np.asarray(self.door_positions, np.float64),
                             np.asarray(self.door_rooms), len(self.room_classes))
        return np.where(np.isfinite(geodesic), geodesic, straight).astype(np.float32)

    def room_costs(self) -> np.ndarray:
        """float32 (R, R): the cost of going from receptacle i to examine j, ``EXAMINE_COST`` +
        ``ROOM_CHANGE_COST`` × the room changes (fewest doors between their rooms; every pair
        of rooms one change apart without doors; a receptacle of unknown room one change from
        every other; K changes where no door path joins them). The diagonal is
        ``EXAMINE_COST`` (examining where one stands)."""
        room, k = np.asarray(self.receptacle_room), len(self.room_classes)
        hops = np.where(np.eye(k, dtype=bool), 0.0, 1.0 if self.door_rooms is None else np.inf)
        for a, b in ([] if self.door_rooms is None else np.asarray(self.door_rooms)):
            hops[a, b] = hops[b, a] = min(hops[a, b], 1.0)
        for via in range(k):  # Floyd-Warshall over K rooms
            hops = np.minimum(hops, hops[:, via:via + 1] + hops[via:via + 1])
        known = (room[:, None] >= 0) & (room[None] >= 0)
        changes = np.where(known, hops[np.maximum(room, 0)][:, np.maximum(room, 0)] if k else 0,
                           1.0)
        changes = np.where(np.eye(len(room), dtype=bool), 0.0,
                           np.where(np.isfinite(changes), changes, k))
        return (EXAMINE_COST + ROOM_CHANGE_COST * changes).astype(np.float32)


@dataclasses.dataclass(frozen=True, eq=False)
class Recorded:
    """A recorded world: one or more environments (of any sizes), in order."""

    environments: tuple[Environment, ...]

    def names(self) -> tuple[str, ...]:
        """The environments' names, in order."""
        return tuple(env.name for env in self.environments)

    def vocabulary(self) -> dict[str, list[str]]:
        """The sorted class names over every environment: {"rooms", "receptacles", "objects"}."""
        return {"rooms": sorted({c for e in self.environments for c in e.room_classes}),
                "receptacles": sorted({c for e in self.environments
                                       for c in e.receptacle_classes}),
                "objects": sorted({c for e in self.environments for c in e.object_classes})}


def check_walk(where: str, points: int, doors: int) -> None:
    """The memory and work of :func:`_geodesic` through the shared budget: its (P + D)²
    matrices, and D passes over (P, P + D), each million entries counted as one sequential
    step (:data:`~flowmaps_jax.resources.SEQUENTIAL_FLOPS`)."""
    v = points + doors
    check_resources(f"{where}: walking distances between {points} receptacles through {doors} "
                    f"doors", num_bytes=8 * (5 * v * v + 4 * points * v),
                    flops=doors * -(-points * v // 2**20) * SEQUENTIAL_FLOPS)


def _geodesic(points, point_room, door_positions, door_rooms, num_rooms: int) -> np.ndarray:
    """(P, P) float64 shortest walks between points (P, 2) through doors (inf: not joined):
    Dijkstra from every point at once, settling the doors only (a point is never worth passing
    through: its room's nodes are joined directly)."""
    nodes = np.concatenate([points, door_positions.reshape(-1, 2)], axis=0)
    rooms = np.arange(num_rooms)
    member = np.concatenate([point_room[:, None] == rooms[None],
                             (door_rooms.reshape(-1, 2)[:, :1] == rooms[None])
                             | (door_rooms.reshape(-1, 2)[:, 1:] == rooms[None])], axis=0)
    share = (member.astype(np.int64) @ member.T.astype(np.int64)) > 0
    dist = np.where(share, np.linalg.norm(nodes[:, None] - nodes[None], axis=-1), np.inf)
    np.fill_diagonal(dist, 0.0)
    p, rows = len(points), np.arange(len(points))
    best, done = dist[:p].copy(), np.zeros((p, len(nodes) - p), bool)
    for _ in range(len(nodes) - p):
        u = np.argmin(np.where(done, np.inf, best[:, p:]), axis=1)
        done[rows, u] = True
        np.minimum(best, best[rows, p + u][:, None] + dist[p + u], out=best)
    return best[:, :p]


# ------------------------------------------------------------------------------ checks


class _Where:
    """Names where a field comes from in an error message: its file (when loading) or the
    environment (in memory)."""

    def __init__(self, env_name: str, files: dict[str, str] | None = None):
        self.env_name, self.files = env_name, files

    def fail(self, field: str, what: str) -> ValueError:
        if self.files is None:
            return ValueError(f"environment {self.env_name!r}: {field}: {what}")
        base, _, index = field.partition("[")
        if base in ARRAYS:
            return ValueError(f"{self.files['arrays']}: {field}: {what}")
        if base in _JSON_NAMES:  # the dataclass field as the JSON path it was read from
            entry, key = _JSON_NAMES[base]
            field = f"{entry}[{index}.{key}" if index else f"{entry}[*].{key}"
        return ValueError(f"{self.files['json']}: {field}: {what}")


def check_environment_name(name: Any, what: str = "environment name") -> str:
    """``name`` if it is a relative POSIX path of plain parts (``train/env0``): parts of letters,
    digits, ``_ . + -`` starting with a letter or digit (no ``..``, no leading ``/``)."""
    if not isinstance(name, str) or not name or len(name) > MAX_NAME:
        raise ValueError(f"{what} must be a non-empty relative path (str); got {name!r}"[:300])
    if not all(_PART.fullmatch(part) and ".." not in part for part in name.split("/")):
        raise ValueError(f"{what} {name!r} must be a relative POSIX path of plain parts "
                         f"(letters, digits, '_', '.', '+', '-'; no '..', no leading '/')"[:300])
    return name


def _check_strings(where: _Where, field: str, value: Any, count: int | None,
                   distinct: bool = False) -> None:
    if not isinstance(value, tuple) or (count is not None and len(value) != count):
        size = "" if count is None else f" of {count}"
        length = len(value) if hasattr(value, "__len__") else "?"
        raise where.fail(field, f"must be a tuple{size or ' of'} strings; got a "
                                f"{type(value).__name__} of {length}")
    for i, text in enumerate(value):
        if not isinstance(text, str) or not text or len(text) > MAX_TEXT or not text.isprintable():
            raise where.fail(f"{field}[{i}]", f"must be a non-empty printable string of at most "
                                              f"{MAX_TEXT} characters; got {text!r}"[:300])
    if distinct and len(set(value)) != len(value):
        twice = sorted(t for t in set(value) if value.count(t) > 1)[0]
        raise where.fail(field, f"names {twice!r} twice; ids must be distinct")


def _check_array(where: _Where, field: str, value: Any, dtype, shape: tuple,
                 symbols: str) -> np.ndarray:
    """``value`` must be a numpy array of exactly ``dtype`` and ``shape`` (None: any size)."""
    expected = "(" + ", ".join("*" if s is None else str(s) for s in shape) + (
        ",)" if len(shape) == 1 else ")")
    if not isinstance(value, np.ndarray):
        raise where.fail(field, f"is a {type(value).__name__}, expected a {np.dtype(dtype)} "
                                f"array of shape {symbols} = {expected}")
    if value.dtype != np.dtype(dtype) or value.ndim != len(shape) or any(
            s is not None and a != s for a, s in zip(value.shape, shape, strict=True)):
        raise where.fail(field, f"has shape {value.shape} and dtype {value.dtype}; expected "
                                f"{symbols} = {expected} and {np.dtype(dtype)}")
    return value


def _check_integers(where: _Where, field: str, value: Any, dtype, shape: tuple,
                    symbols: str) -> np.ndarray:
    """As :func:`_check_array`, for an array of any integer dtype whose values fit ``dtype``
    (returned as ``dtype``; numpy's default int64 for ``location``, say)."""
    if isinstance(value, np.ndarray) and value.dtype.kind in "iu" and value.dtype != dtype:
        info = np.iinfo(dtype)
        if value.size and (value.min() < info.min or value.max() > info.max):
            bad = value.min() if value.min() < info.min else value.max()
            raise where.fail(field, f"holds {bad}, outside the range of {np.dtype(dtype)}")
        value = value.astype(dtype)
    return _check_array(where, field, value, dtype, shape, symbols)


def _check_finite(where: _Where, field: str, value: np.ndarray) -> None:
    if not np.all(np.isfinite(value)):
        raise where.fail(field, "holds NaN or inf")


def _check_range(where: _Where, field: str, value: np.ndarray, low: int, high: int,
                 meaning: str) -> None:
    if value.size and (value.min() < low or value.max() > high):
        at = tuple(int(i) for i in np.argwhere((value < low) | (value > high))[0])
        bad = value[at]
        if value.ndim == 1 or field in _JSON_NAMES:  # one entry of environment.json
            raise where.fail(f"{field}[{at[0]}]", f"holds {bad}, outside {low}..{high} "
                                                  f"({meaning})")
        raise where.fail(field, f"holds {bad} at {list(at)}, outside {low}..{high} ({meaning})")


def validate_environment(env: Any, *, _files: dict[str, str] | None = None) -> Environment:
    """``env`` if it is a well-formed ``Environment`` (the checks ``load_recorded`` applies;
    ``hours`` and ``location`` of another integer dtype whose values fit come back as int64 and
    int32); else ``ValueError`` ``"environment '<name>': <field>: what is wrong"``.

    Types, shapes and dtypes as documented; T, M, R >= 1; ids distinct; hours >= 0 and
    strictly increasing; location, allowed, room and door indices in range; every object allowed
    somewhere and observed only on receptacles it may stand on; finite boxes, corners and
    distances (distance symmetric, >= 0, 0 on the diagonal); room boxes with x1 > x0, y1 > y0;
    a JSON-able ``source`` dict."""
    if not isinstance(env, Environment):
        raise ValueError(f"environment must be an Environment; got {type(env).__name__}")
    name = check_environment_name(env.name)
    where = _Where(name, _files)
    hours = _check_integers(where, "hours", env.hours, np.int64, (None,), "(T,)")
    t = hours.shape[0]
    _check_strings(where, "receptacle_ids", env.receptacle_ids, None, distinct=True)
    r = len(env.receptacle_ids)
    _check_strings(where, "object_ids", env.object_ids, None, distinct=True)
    m = len(env.object_ids)
    for field, size in (("hours", t), ("objects", m), ("receptacles", r)):
        if size == 0:
            raise where.fail(field, "is empty: an environment needs at least one hour, one "
                                    "object and one receptacle")
    for field, size in (("receptacle_classes", r), ("receptacle_texts", r),
                        ("object_classes", m), ("object_texts", m)):
        _check_strings(where, field, getattr(env, field), size)
    _check_strings(where, "room_classes", env.room_classes, None)
    k = len(env.room_classes)
    # arrays: shapes and dtypes
    location = _check_integers(where, "location", env.location, np.int32, (t, m), "(T, M)")
    corners = None if env.receptacle_corners is None else _check_array(
        where, "receptacle_corners", env.receptacle_corners, np.float32, (r, 8, 3), "(R, 8, 3)")
    allowed = _check_array(where, "allowed", env.allowed, np.bool_, (m, r), "(M, R)")
    room = _check_array(where, "receptacle_room", env.receptacle_room, np.int32, (r,), "(R,)")
    # time
    if hours.min() < 0:
        raise where.fail("hours", f"holds {hours.min()}; hours count from 0")
    back = np.flatnonzero(np.diff(hours) <= 0)
    if back.size:
        i = int(back[0])
        raise where.fail("hours", f"must be strictly increasing; hour {hours[i + 1]} at "
                                  f"index {i + 1} follows {hours[i]} (time goes backwards)")
    # indices and geometry
    _check_range(where, "location", location, -1, r - 1, "a receptacle index, or -1 = not "
                                                          "observed")
    if corners is not None:
        _check_finite(where, "receptacle_corners", corners)
    _check_range(where, "receptacle_room", room, -1, k - 1, "a room index, or -1 = unknown")
    none = np.flatnonzero(~allowed.any(axis=1))
    if none.size:
        raise where.fail(f"allowed[{none[0]}]", f"object {env.object_ids[none[0]]!r} may "
                                                f"stand on no receptacle")
    seen_t, seen_m = np.nonzero(location >= 0)
    off = ~allowed[seen_m, location[seen_t, seen_m]]
    if np.any(off):
        i = int(np.flatnonzero(off)[0])
        tt, mm = int(seen_t[i]), int(seen_m[i])
        rr = int(location[tt, mm])
        raise where.fail("location", f"object {mm} ({env.object_ids[mm]!r}) is on receptacle "
                                     f"{rr} ({env.receptacle_ids[rr]!r}) at hour {hours[tt]}, "
                                     f"where it may not stand (allowed[{mm}, {rr}] is False)")
    # rooms and doors
    if k == 0:
        for field in ("room_boxes", "door_rooms", "door_positions"):
            if getattr(env, field) is not None and np.size(getattr(env, field)):
                raise where.fail(field, "is given but room_classes is empty (no rooms)")
    else:
        graph = corners is None  # a scene graph: room boxes and door positions optional
        if not (graph and env.room_boxes is None):
            boxes = _check_array(where, "room_boxes", env.room_boxes, np.float32, (k, 4),
                                 "(K, 4)")
            _check_finite(where, "room_boxes", boxes)
            if np.any(boxes[:, 2:] <= boxes[:, :2]):
                raise where.fail("room_boxes", "must have x1 > x0 and y1 > y0")
        if (env.door_rooms is None) != (env.door_positions is None) and not (
                graph and env.door_positions is None):
            raise where.fail("door_rooms", "and door_positions must be given together (door "
                                           "positions may be left out only without geometry)")
        if env.door_rooms is not None:
            doors = _check_array(where, "door_rooms", env.door_rooms, np.int32, (None, 2),
                                 "(D, 2)")
            _check_range(where, "door_rooms", doors, 0, k - 1, "room indices")
            if env.door_positions is not None:
                _check_finite(where, "door_positions", _check_array(
                    where, "door_positions", env.door_positions, np.float32,
                    (doors.shape[0], 2), "(D, 2)"))
    # optional arrays
    if env.distance is not None:
        distance = _check_array(where, "distance", env.distance, np.float32, (r, r), "(R, R)")
        _check_finite(where, "distance", distance)
        if distance.min() < 0:
            raise where.fail("distance", f"holds {distance.min()}; distances are >= 0")
        if np.any(np.abs(np.diag(distance)) > 0):
            raise where.fail("distance", "must be 0 on the diagonal")
        if np.any(np.abs(distance - distance.T) > SYMMETRY_ATOL):
            raise where.fail("distance", f"must be symmetric (within {SYMMETRY_ATOL} m)")
    if env.object_corners is not None:
        _check_finite(where, "object_corners", _check_array(
            where, "object_corners", env.object_corners, np.float32, (t, m, 8, 3),
            "(T, M, 8, 3)"))
    if env.object_rotation is not None:
        _check_finite(where, "object_rotation", _check_array(
            where, "object_rotation", env.object_rotation, np.float32, (t, m), "(T, M)"))
    if env.not_at is not None:
        not_at = _check_array(where, "not_at", env.not_at, np.bool_, (t, m, r), "(T, M, R)")
        clash = np.flatnonzero(not_at[seen_t, seen_m, location[seen_t, seen_m]])
        if clash.size:
            tt, mm = int(seen_t[clash[0]]), int(seen_m[clash[0]])
            raise where.fail("not_at", f"object {mm} ({env.object_ids[mm]!r}) was seen on "
                                       f"receptacle {location[tt, mm]} at hour {hours[tt]}, "
                                       f"where not_at says it was not")
    if not isinstance(env.source, dict):
        raise where.fail("source", f"must be a dict; got {type(env.source).__name__}")
    try:
        json.dumps(env.source, allow_nan=False)
    except (TypeError, ValueError) as err:
        raise where.fail("source", f"must be JSON-able ({err})") from None
    if hours is not env.hours or location is not env.location:  # another integer dtype
        env = dataclasses.replace(env, hours=hours, location=location)
    return env


def validate_recorded(recorded: Any) -> Recorded:
    """``recorded`` if it is a ``Recorded`` of at least one valid environment with distinct
    names; else ``ValueError`` naming the environment and the field."""
    if not isinstance(recorded, Recorded):
        raise ValueError(f"recorded must be a Recorded; got {type(recorded).__name__}")
    if not isinstance(recorded.environments, tuple) or not recorded.environments:
        raise ValueError("recorded.environments must be a non-empty tuple of Environment")
    recorded = Recorded(tuple(validate_environment(env) for env in recorded.environments))
    _check_distinct_names(recorded.names(), "recorded.environments")
    return recorded


def _check_distinct_names(names, what: str) -> None:
    seen = set()
    for name in names:
        folded = name.casefold()  # one folder per name, also on case-insensitive disks
        if folded in seen:
            raise ValueError(f"{what}: the environment name {name!r} appears twice")
        seen.add(folded)
    for name in names:  # a folder inside another environment's folder
        parts = name.split("/")
        for i in range(1, len(parts)):
            if "/".join(parts[:i]).casefold() in seen:
                raise ValueError(f"{what}: the environment {name!r} lies inside the "
                                 f"environment {'/'.join(parts[:i])!r}")


# ------------------------------------------------------------------------------ save


def environment_json(env: Environment) -> dict:
    """The ``environment.json`` of ``env`` (a dict)."""
    room = np.asarray(env.receptacle_room)
    allowed = np.asarray(env.allowed)
    boxes = [None] * len(env.room_classes) if env.room_boxes is None else env.room_boxes
    rooms = [{"class": c, "box": None if box is None else [float(v) for v in box]}
             for c, box in zip(env.room_classes, boxes, strict=True)]
    pairs = [] if env.door_rooms is None else np.asarray(env.door_rooms)
    at = [None] * len(pairs) if env.door_positions is None else env.door_positions
    doors = [{"rooms": [int(a), int(b)], "position": None if p is None else [float(v) for v in p]}
             for (a, b), p in zip(pairs, at, strict=True)]
    return {
        "receptacles": [{"id": i, "class": c, "text": t, "room": int(r) if r >= 0 else None}
                        for i, c, t, r in zip(env.receptacle_ids, env.receptacle_classes,
                                              env.receptacle_texts, room, strict=True)],
        "objects": [{"id": i, "class": c, "text": t,
                     "allowed": [int(j) for j in np.flatnonzero(a)]}
                    for i, c, t, a in zip(env.object_ids, env.object_classes, env.object_texts,
                                          allowed, strict=True)],
        "rooms": rooms, "doors": doors, "source": env.source}


def dumps_entries(data: dict) -> str:
    """``data`` (a dict) as JSON text with one line per top-level key, and one line per entry
    of a top-level list: readable, and diffable, by hand."""
    lines = []
    for key, value in data.items():
        head = f" {json.dumps(key)}: "
        if isinstance(value, list) and value:
            body = ",\n".join(f"  {json.dumps(v, allow_nan=False)}" for v in value)
            lines.append(f"{head}[\n{body}\n ]")
        else:
            lines.append(head + json.dumps(value, allow_nan=False))
    return "{\n" + ",\n".join(lines) + "\n}\n"


def _npz_bytes(env: Environment) -> bytes:
    arrays = {name: getattr(env, name) for name in (*REQUIRED_ARRAYS, *OPTIONAL_ARRAYS)
              if getattr(env, name) is not None}
    if env.not_at is not None:
        arrays["not_at_bits"] = np.packbits(env.not_at, axis=-1)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **{k: np.asarray(v) for k, v in arrays.items()})
    return buffer.getvalue()


def content_digest(recorded: Recorded) -> str:
    """A SHA-256 (hex) of what ``recorded`` holds, in order: each environment's name, its
    ``environment.json`` entries and its hours, locations, receptacle boxes and ``not_at``
    (those given). Copies of one dataset share it wherever they sit; a run stores it to
    recognise its own data."""
    digest = hashlib.sha256()
    for env in recorded.environments:
        digest.update(json.dumps([env.name, environment_json(env)], sort_keys=True).encode())
        for array in (env.hours, env.location, env.receptacle_corners, env.not_at):
            if array is None:
                continue
            array = np.ascontiguousarray(array)
            digest.update(f"{array.dtype.str}{array.shape}".encode())
            digest.update(array.tobytes())
    return digest.hexdigest()


def check_no_link_below(path: pathlib.Path, name: str, what: str = "path") -> None:
    """``ValueError`` (naming the argument ``what``) if a component of ``path / name`` below
    ``path`` is a symbolic link."""
    here = path
    for part in name.split("/"):
        here = here / part
        if here.is_symlink():
            raise ValueError(f"{what}: {os.fspath(here)!r} is a symbolic link; refusing to "
                             f"write through it")


def index_json(recorded: Recorded) -> dict:
    """The ``recorded.json`` of ``recorded`` (a dict)."""
    return {"format": FORMAT, "version": max(e.version for e in recorded.environments),
            "environments": list(recorded.names()),
            "units": dict(UNITS), "time": TIME}


def save_recorded(recorded: Recorded, path) -> pathlib.Path:
    """Write ``recorded`` (checked first) into the folder ``path`` (created if needed): its
    ``recorded.json`` and one ``<name>/environment.json`` + ``<name>/arrays.npz`` per
    environment, all written aside and renamed into place together; a symbolic link at any
    name written, or at a folder under ``path``, is refused. Returns the ``recorded.json``
    path."""
    recorded = validate_recorded(recorded)
    root = pathlib.Path(check_output_dir("path", path))
    files: dict[pathlib.Path, str | bytes] = {}
    for env in recorded.environments:
        check_no_link_below(root, env.name)
        folder = root / env.name
        if folder.exists() and not folder.is_dir():
            raise ValueError(f"path: {os.fspath(folder)!r} is a file, where the environment "
                             f"{env.name!r} needs a folder")
        files[folder / ENVIRONMENT_FILE] = dumps_entries(environment_json(env))
        files[folder / ARRAYS_FILE] = _npz_bytes(env)
    root = make_output_dir("path", root, [INDEX_FILE])
    for env in recorded.environments:
        make_output_dir("path", root / env.name, [ENVIRONMENT_FILE, ARRAYS_FILE])
    files[root / INDEX_FILE] = dumps_entries(index_json(recorded))
    write_files(files, name="path")
    return root / INDEX_FILE


# ------------------------------------------------------------------------------ load


def _keys(file: str, field: str, value: Any, keys: tuple[str, ...]) -> dict:
    if not isinstance(value, dict):
        raise ValueError(f"{file}: {field}: must be a JSON object; got "
                         f"{type(value).__name__}")
    missing = [k for k in keys if k not in value]
    extra = sorted(k for k in value if k not in keys)
    if missing or extra:
        raise ValueError(f"{file}: {field}: " + "; ".join(
            ([f"missing {missing}"] if missing else [])
            + ([f"unexpected {extra}"] if extra else [])) + f" (expected keys {list(keys)})")
    return value


def _list(file: str, field: str, value: Any) -> list:
    if not isinstance(value, list):
        raise ValueError(f"{file}: {field}: must be a JSON list; got {type(value).__name__}")
    return value


def _number_list(file: str, field: str, value: Any, length: int, integer: bool) -> list:
    kinds = (int,) if integer else (int, float)
    if (not isinstance(value, list) or len(value) != length
            or not all(isinstance(v, kinds) and not isinstance(v, bool) for v in value)):
        what = "integers" if integer else "numbers"
        raise ValueError(f"{file}: {field}: must be a list of {length} {what}; got "
                         f"{value!r}"[:300])
    return value


def _string(file: str, field: str, value: Any) -> str:
    if not isinstance(value, str):
        raise ValueError(f"{file}: {field}: must be a string; got {value!r}"[:300])
    return value


def _json_bytes(file: str, data: Any, limit: int) -> int:
    """Bytes that the sizes ``environment.json`` gives cost (the objects x receptacles matrix,
    the walking distances), checked against ``limit`` before anything is allocated."""
    data = _keys(file, "(top level)", data, _ENV_KEYS)
    m, r, d = (len(_list(file, key, data[key])) for key in ("objects", "receptacles", "doors"))
    size = check_request_size(f"{file}: {m} objects x {r} receptacles", m * r, limit)
    if d:
        check_walk(file, r, d)
    return size


def _environment_from_json(name: str, data: Any, arrays: dict[str, np.ndarray],
                           files: dict[str, str]) -> Environment:
    """An Environment from a parsed ``environment.json`` and its arrays (structure checked
    here, values by ``validate_environment``)."""
    file = files["json"]
    data = _keys(file, "(top level)", data, _ENV_KEYS)
    entries = {}
    for key in ("receptacles", "objects", "rooms", "doors"):
        entries[key] = _list(file, key, data[key])
        for i, entry in enumerate(entries[key]):
            _keys(file, f"{key}[{i}]", entry, _ENTRY_KEYS[key])
    rec, obj, rooms, doors = (entries[k] for k in ("receptacles", "objects", "rooms", "doors"))
    r = len(rec)
    room = []
    for i, e in enumerate(rec):
        value = e["room"]
        if value is not None and (not isinstance(value, int) or isinstance(value, bool)):
            raise ValueError(f"{file}: receptacles[{i}].room: must be a room index or null; "
                             f"got {value!r}"[:300])
        room.append(-1 if value is None else value)
    if any(v < -1 or v > np.iinfo(np.int32).max for v in room):
        raise ValueError(f"{file}: receptacles: a room index is out of range (null = unknown)")
    allowed = np.zeros((len(obj), r), bool)
    for i, e in enumerate(obj):
        listed = _list(file, f"objects[{i}].allowed", e["allowed"])
        if not all(isinstance(j, int) and not isinstance(j, bool) for j in listed):
            raise ValueError(f"{file}: objects[{i}].allowed: must list receptacle indices; got "
                             f"{listed!r}"[:300])
        bad = [j for j in listed if not 0 <= j < r]
        if bad:
            raise ValueError(f"{file}: objects[{i}].allowed: holds {bad[0]}, outside "
                             f"0..{r - 1} (receptacle indices)")
        if len(set(listed)) != len(listed):
            raise ValueError(f"{file}: objects[{i}].allowed: lists a receptacle twice")
        allowed[i, listed] = True
    boxes, door_positions = ([None if e[key] is None and all(f[key] is None for f in listed)
                              else _number_list(file, f"{name}[{i}].{key}", e[key], size, False)
                              for i, e in enumerate(listed)]
                             for name, listed, key, size in (("rooms", rooms, "box", 4),
                                                             ("doors", doors, "position", 2)))
    door_rooms = [_number_list(file, f"doors[{i}].rooms", e["rooms"], 2, True)
                  for i, e in enumerate(doors)]
    if doors and not rooms:
        raise ValueError(f"{file}: doors: doors are given but rooms is empty")
    if any(not -2**31 <= v < 2**31 for pair in door_rooms for v in pair):
        raise ValueError(f"{file}: doors: a room index is out of range")
    with np.errstate(over="ignore"):
        room_boxes = (np.asarray(boxes, np.float32).reshape(-1, 4)
                      if rooms and boxes[0] is not None else None)
        positions = (np.asarray(door_positions, np.float32).reshape(-1, 2)
                     if doors and door_positions[0] is not None else None)
    strings = {}
    for key, entries_, fields in (("receptacles", rec, ("id", "class", "text")),
                                  ("objects", obj, ("id", "class", "text")),
                                  ("rooms", rooms, ("class",))):
        for f in fields:
            strings[key, f] = tuple(_string(file, f"{key}[{i}].{f}", e[f])
                                    for i, e in enumerate(entries_))
    source = data["source"]
    if not isinstance(source, dict):
        raise ValueError(f"{file}: source: must be a JSON object; got {type(source).__name__}")
    env = Environment(
        name=name,
        receptacle_ids=strings["receptacles", "id"],
        receptacle_classes=strings["receptacles", "class"],
        receptacle_texts=strings["receptacles", "text"],
        receptacle_room=np.asarray(room, np.int32).reshape(r),
        receptacle_corners=arrays.get("receptacle_corners"),
        object_ids=strings["objects", "id"],
        object_classes=strings["objects", "class"],
        object_texts=strings["objects", "text"],
        allowed=allowed,
        hours=arrays["hours"],
        location=arrays["location"],
        room_classes=strings["rooms", "class"],
        room_boxes=room_boxes,
        door_rooms=np.asarray(door_rooms, np.int32).reshape(-1, 2) if doors else None,
        door_positions=positions,
        distance=arrays.get("distance"),
        object_corners=arrays.get("object_corners"),
        object_rotation=arrays.get("object_rotation"),
        source=source, not_at=_not_at(files["arrays"], arrays, len(strings["objects", "id"]), r))
    return validate_environment(env, _files=files)


def _not_at(file: str, arrays: dict, m: int, r: int) -> np.ndarray | None:
    """``not_at`` (T, M, R) bool unpacked from ``not_at_bits`` (T, M, ⌈R / 8⌉) uint8."""
    bits = arrays.get("not_at_bits")
    if bits is None:
        return None
    shape = (np.shape(arrays["hours"])[0], m, -(-r // 8))
    if bits.dtype != np.uint8 or bits.shape != shape:
        raise ValueError(f"{file}: not_at_bits: has shape {bits.shape} and dtype {bits.dtype}; "
                         f"expected (T, M, ⌈R / 8⌉) = {shape} and uint8")
    not_at = np.unpackbits(bits, axis=-1, count=r).astype(bool)
    if not np.array_equal(np.packbits(not_at, axis=-1), bits):
        raise ValueError(f"{file}: not_at_bits: sets padding bits past receptacle {r - 1}")
    return not_at


def load_environment(root, name: str, budget: int | None = None,
                     version: int = VERSION) -> Environment:
    """The environment ``name`` of the recorded world in the folder ``root`` (checked as
    ``load_recorded`` checks it); the sizes its files give must fit in ``budget`` bytes
    (default :func:`~flowmaps_jax.resources.memory_limit`) before anything is allocated;
    ``version``: the index's (version 1 needs ``receptacle_corners``)."""
    folder = pathlib.Path(root) / name
    files = {"json": os.fspath(folder / ENVIRONMENT_FILE),
             "arrays": os.fspath(folder / ARRAYS_FILE)}
    for file in files.values():
        if not os.path.isfile(file):
            raise ValueError(f"{file}: (file): missing; the environment {name!r} listed in "
                             f"{INDEX_FILE} has no such file")
    budget = memory_limit() if budget is None else budget
    data = read_json("", files["json"])
    arrays = read_npz(files["arrays"], files["arrays"],
                      allowed=(*REQUIRED_ARRAYS, *OPTIONAL_ARRAYS, "not_at_bits"),
                      required=REQUIRED_ARRAYS + ("receptacle_corners",) * (version == 1),
                      max_bytes=max(budget - _json_bytes(files["json"], data, budget), 0))
    return _environment_from_json(name, data, arrays, files)


def _authors_layout(root: pathlib.Path, folders: int = 1000) -> bool:
    """Whether a scan file of the authors' 2026 layout (``flowmaps2026``) lies under ``root``
    (among its first ``folders`` folders)."""
    walk = itertools.islice(os.walk(root), folders)
    return any(AUTHORS_SCAN.fullmatch(f) for _, _, files in walk for f in files)


def load_recorded(path) -> Recorded:
    """Read the recorded world in the folder ``path`` (see the module's docstring);
    ``ValueError`` ``"<file>: <field>: what is wrong"`` for a bad file. The files are
    untrusted: JSON size and depth are bounded, ``.npz`` members whitelisted and their sizes
    checked before anything is decompressed."""
    root = pathlib.Path(check_dir("path", path))
    index_file = os.fspath(root / INDEX_FILE)
    if not os.path.isfile(index_file):
        hint = (f"; it is in the authors' 2026 layout: convert it first with python -m "
                f"flowmaps_jax.data import-flowmaps2026 {shlex.quote(os.fspath(root))} --out "
                f"OUT" if _authors_layout(root) else "")
        raise ValueError(f"{index_file}: (file): missing; {os.fspath(root)!r} is not a "
                         f"recorded world (no {INDEX_FILE}){hint}")
    index = _keys(index_file, "(top level)", read_json("", index_file), _INDEX_KEYS)
    if index["format"] != FORMAT:
        raise ValueError(f"{index_file}: format: is {index['format']!r}, not {FORMAT!r}"[:300])
    if index["version"] not in VERSIONS or isinstance(index["version"], bool):
        raise ValueError(f"{index_file}: version: is {index['version']!r}; this code reads "
                         f"versions {list(VERSIONS)}"[:300])
    if index["units"] != UNITS:
        raise ValueError(f"{index_file}: units: must be {UNITS}; got {index['units']!r}"[:300])
    _string(index_file, "time", index["time"])
    names = _list(index_file, "environments", index["environments"])
    if not names:
        raise ValueError(f"{index_file}: environments: is empty; a recorded world holds at "
                         f"least one environment")
    for i, name in enumerate(names):
        try:
            check_environment_name(name, f"entry {i}")
        except ValueError as err:
            raise ValueError(f"{index_file}: environments: {err}") from None
    try:
        _check_distinct_names(names, "environments")
    except ValueError as err:
        raise ValueError(f"{index_file}: {err}") from None
    environments, left = [], memory_limit()  # one budget for all the environments
    for name in names:
        environments.append(load_environment(root, name, left, index["version"]))
        env = environments[-1]
        left -= env.num_objects * env.num_receptacles + sum(
            getattr(env, f).nbytes for f in ARRAYS if getattr(env, f) is not None)
        if env.version > index["version"]:
            raise ValueError(f"{index_file}: version: is 1, but the environment {name!r} uses "
                             f"a version-2 field (no receptacle_corners, or not_at_bits)")
    return Recorded(tuple(environments))

