"""The authors' 2026 dataset layout (FlowMaps 2026, ``src/dataset/sim_dataset.py``), both ways:
``import_flowmaps2026(root) -> Recorded`` and ``export_flowmaps2026(recorded, root)``.

The layout, the axes (their y is up: (X, Y, Z) there is (X, Z, Y) here), unobserved hours
(all-zero ``assignment`` rows), derived object boxes (``DERIVED_OBJECT_SIZE``) and the side file
``flowmaps_recorded.json`` (what their layout cannot hold, so that recorded → theirs → recorded
is the identity) are docs/data.md, "The converters". Import refuses a folder that contradicts
itself with one ``ValueError`` line naming the file and the field.
"""

from __future__ import annotations

import itertools
import json
import os
import pathlib
import re
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from flowmaps_jax.atomic_files import make_output_dir, write_files
from flowmaps_jax.recorded.format import (
    FORMAT,
    MAX_TEXT,
    VERSION,
    Environment,
    Recorded,
    _environment_from_json,
    check_environment_name,
    check_no_link_below,
    environment_json,
    validate_environment,
    validate_recorded,
)
from flowmaps_jax.resources import check_request_size
from flowmaps_jax.untrusted_files import read_json
from flowmaps_jax.validation import check_dir, check_output_dir

SCAN_MERGED = "scan_merged.parquet"
SCAN_PIECE = re.compile(r"^scan_(\d+)\.parquet$")
OBJECT_NAMES = "pickupable_names.json"
RECEPTACLE_NAMES = "receptacle_names.json"
RECEPTACLE_BOXES = "receptacles_oobb.json"
OBJECT_ALLOWED = "pickupable_to_receptacle.json"
LOOKUP = "lookup.json"
EXTRAS = "flowmaps_recorded.json"
COLUMNS = ("assignment", "rotation", "aabb_cornerPoints")
DERIVED_OBJECT_SIZE = 0.2
"""Side (metres) of the cube export writes as an object's box when none was recorded."""
_SWAP = [0, 2, 1]  # (x, y, z up) <-> (X, Y up, Z): the same permutation both ways
_EXTRAS_KEYS = ("format", "version", "layout", "environment", "hours", "distance",
                "object_corners", "object_rotation")
_LAYOUT = "flowmaps2026"

Progress = Callable[[Iterable], Iterable] | None


def _pyarrow():
    """pyarrow and pyarrow.parquet, or a ValueError saying how to install them."""
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        raise ValueError("the authors' format is parquet, which needs pyarrow: "
                         "pip install pyarrow (a dependency of flowmaps-jax)") from None
    return pa, pq


def class_of(identifier: str) -> str:
    """The class of a ProcTHOR-style id: the text before the first ``|``."""
    return identifier.split("|", 1)[0]


def class_text(name: str) -> str:
    """A text descriptor from a class name: ``CellPhone`` -> "cell phone", ``TVStand`` -> "tv
    stand", ``coffee_table`` -> "coffee table"."""
    spaced = re.sub(r"(?<=[a-z0-9])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])", " ", name)
    return " ".join(spaced.replace("_", " ").split()).lower() or name


def _natural(name: str) -> list:
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


# ------------------------------------------------------------------------------ import


def environment_folders(root) -> list[tuple[str, pathlib.Path]]:
    """(name, folder) of every environment folder under ``root`` (one holding
    ``scan_merged.parquet`` or ``scan_N.parquet``), named by its path relative to ``root``, in
    natural order (env2 before env10). A linked folder is refused (links are not followed)."""
    root = pathlib.Path(root)
    found = []
    for here, dirs, files in os.walk(root, followlinks=False):
        dirs.sort()
        for name in dirs:
            if os.path.islink(os.path.join(here, name)):
                raise ValueError(f"{os.path.join(here, name)}: (folder): is a symbolic link; "
                                 f"import does not follow links: put the folder itself there")
        if SCAN_MERGED in files or any(SCAN_PIECE.match(f) for f in files):
            folder = pathlib.Path(here)
            name = folder.relative_to(root).as_posix()
            found.append((root.resolve().name if name == "." else name, folder))
    return sorted(found, key=lambda item: _natural(item[0]))


def _scan_files(folder: pathlib.Path) -> list[pathlib.Path]:
    merged = folder / SCAN_MERGED
    pieces = [(0, merged)] if os.path.lexists(merged) else sorted(
        (int(m.group(1)), folder / f) for f in os.listdir(folder) if (m := SCAN_PIECE.match(f)))
    for _, path in pieces:  # a FIFO or a folder there: named, not skipped
        if not path.is_file():
            raise ValueError(f"{os.fspath(path)}: (file): not a regular file")
    for (a, first), (b, second) in itertools.pairwise(pieces):
        if a == b:
            raise ValueError(f"{os.fspath(folder)}: (folder): {first.name} and {second.name} "
                             f"are both scan piece {a} (the same hours twice): keep one")
    return [path for _, path in pieces]


def _numbers(value: Any, depth: int) -> bool:
    """Whether ``value`` is ``depth`` levels of JSON lists of numbers (true/false is not one)."""
    if depth == 0:
        return type(value) in (int, float)
    return isinstance(value, list) and all(_numbers(v, depth - 1) for v in value)


def _column(table, name: str, file: str, rank: int) -> np.ndarray:
    """The column ``name`` of a pyarrow ``table`` as a numpy array of ``1 + rank`` dims (rows,
    then nested lists of equal lengths, fixed-size or not)."""
    pa, _ = _pyarrow()
    if name not in table.column_names:
        raise ValueError(f"{file}: {name}: no such column (columns: {table.column_names})")
    array = table.column(name).combine_chunks()
    shape = [len(array)]
    for depth in range(rank):
        kind = array.type
        if not (pa.types.is_list(kind) or pa.types.is_large_list(kind)
                or pa.types.is_fixed_size_list(kind)):
            raise ValueError(f"{file}: {name}: expected {rank} nested lists; level {depth} is "
                             f"{kind}")
        if array.null_count:
            raise ValueError(f"{file}: {name}: holds nulls")
        if pa.types.is_fixed_size_list(kind):
            size = kind.list_size
        else:
            lengths = np.asarray(array.value_lengths())
            size = int(lengths[0]) if lengths.size else 0
            if np.any(lengths != size):
                raise ValueError(f"{file}: {name}: its lists have different lengths "
                                 f"({lengths.min()}..{lengths.max()}) at level {depth}")
        shape.append(size)
        array = array.flatten()
    if array.null_count:
        raise ValueError(f"{file}: {name}: holds nulls")
    if not (pa.types.is_integer(array.type) or pa.types.is_floating(array.type)
            or (pa.types.is_boolean(array.type) and name == "assignment")):
        raise ValueError(f"{file}: {name}: holds {array.type}, not numbers")
    values = array.to_numpy(zero_copy_only=False)
    if values.size != int(np.prod(shape)):
        raise ValueError(f"{file}: {name}: holds {values.size} values for shape {shape}")
    return values.reshape(shape)


def read_scans(files: list[pathlib.Path]) -> dict[str, np.ndarray]:
    """assignment (T, M, R), rotation (T, M), aabb_cornerPoints (T, M, 8, 3) of the parquet
    ``files`` (pieces concatenated in order)."""
    pa, pq = _pyarrow()
    parts: dict[str, list[np.ndarray]] = {c: [] for c in COLUMNS}
    for path in files:
        file = os.fspath(path)
        size = "its values"
        try:
            meta = pq.ParquetFile(path).metadata
            chunks = [meta.row_group(i).column(j) for i in range(meta.num_row_groups)
                      for j in range(meta.num_columns)]
            values = sum(c.num_values for c in chunks if c.path_in_schema.split(".")[0]
                         in COLUMNS)  # decoded: 8 bytes each, a copy and the concatenation
            size = f"{meta.num_rows} rows of {values} values"
            check_request_size(f"{file}: {size}", 24 * values)
            table = pq.read_table(path, columns=list(COLUMNS))
        except MemoryError:  # pyarrow's too: more than the process may have (a ulimit)
            raise ValueError(f"{file}: (file): not enough memory to read {size}") from None
        except (pa.ArrowException, OSError) as err:  # a broken or foreign file
            raise ValueError(f"{file}: (file): not a readable parquet file with the columns "
                             f"{list(COLUMNS)} ({' '.join(str(err).split())[:200]})") from None
        for column, rank in zip(COLUMNS, (2, 1, 3), strict=True):
            parts[column].append(_column(table, column, file, rank))
    out = {}
    for column, arrays in parts.items():
        inner = {a.shape[1:] for a in arrays}
        if len(inner) > 1:
            raise ValueError(f"{os.fspath(files[0].parent)}: {column}: the scan pieces have "
                             f"different shapes {sorted(inner)}")
        out[column] = np.concatenate(arrays, axis=0)
    return out


def _json(folder: pathlib.Path, name: str) -> tuple[Any, str]:
    file = os.fspath(folder / name)
    if not os.path.isfile(file):
        raise ValueError(f"{file}: (file): missing; an environment folder holds {name}")
    return read_json("", file), file


def _id_list(folder: pathlib.Path, name: str) -> tuple[list[str], str]:
    ids, file = _json(folder, name)
    if not isinstance(ids, list):
        raise ValueError(f"{file}: (top level): must be a list of id strings")
    for k, i in enumerate(ids):  # here, not later as a field of another file
        if not isinstance(i, str) or not i or len(i) > MAX_TEXT or not i.isprintable():
            raise ValueError(f"{file}: [{k}]: must be a non-empty printable string of at most "
                             f"{MAX_TEXT} characters; got {i!r}"[:300])
    if len(set(ids)) != len(ids):
        twice = next(i for i in ids if ids.count(i) > 1)
        raise ValueError(f"{file}: {twice}: listed twice")
    return ids, file


def find_lookup(folder: pathlib.Path) -> pathlib.Path | None:
    """The nearest ``lookup.json`` in ``folder`` or a folder above it."""
    for here in (folder, *folder.resolve().parents):
        if (here / LOOKUP).is_file():
            return here / LOOKUP
    return None


def _lookup(path: pathlib.Path, cache: dict) -> dict[str, set]:
    if path not in cache:
        file = os.fspath(path)
        data = read_json("", file)
        if not isinstance(data, dict):
            raise ValueError(f"{file}: (top level): must be a JSON object")
        tables = {}
        for key in ("pickupable2id", "receptacle2id"):
            table = data.get(key)
            if not isinstance(table, dict) or not all(
                    isinstance(v, int) and not isinstance(v, bool) for v in table.values()):
                raise ValueError(f"{file}: {key}: must be an object of class -> integer id")
            tables[key] = set(table)
        cache[path] = tables
    return cache[path]


def _one_hot(assignment: np.ndarray, file: str) -> np.ndarray:
    """int32 (T, M) location from the one-hot (T, M, R) assignment (-1 where a row is zero)."""
    if assignment.dtype.kind == "f" and not np.all(np.isfinite(assignment)):
        raise ValueError(f"{file}: assignment: holds NaN or inf")
    if not np.all((assignment == 0) | (assignment == 1)):
        raise ValueError(f"{file}: assignment: must hold only 0 and 1 (one-hot rows)")
    total = (assignment == 1).sum(axis=-1)
    if np.any(total > 1):
        t, m = (int(i) for i in np.argwhere(total > 1)[0])
        raise ValueError(f"{file}: assignment: object {m} is on {total[t, m]} receptacles at "
                         f"row {t}; a row is one-hot (or all 0: not observed)")
    return np.where(total == 1, np.argmax(assignment, axis=-1), -1).astype(np.int32)


def import_environment(name: str, folder: pathlib.Path, lookups: dict | None = None,
                       lookup_root: pathlib.Path | None = None) -> Environment:
    """One environment folder of the authors' layout as an Environment (see the module's
    docstring for what is checked)."""
    lookups = {} if lookups is None else lookups
    objects, objects_file = _id_list(folder, OBJECT_NAMES)
    receptacles, receptacles_file = _id_list(folder, RECEPTACLE_NAMES)
    lookup_path = find_lookup(folder)
    if lookup_path is None:
        raise ValueError(f"{os.fspath(lookup_root or folder)}: {LOOKUP}: none in the folder "
                         f"or above it")
    tables = _lookup(lookup_path, lookups)
    for ids, file, key in ((objects, objects_file, "pickupable2id"),
                           (receptacles, receptacles_file, "receptacle2id")):
        for i in ids:
            if class_of(i) not in tables[key]:
                raise ValueError(f"{file}: {i}: its class {class_of(i)!r} is missing from "
                                 f"{os.fspath(lookup_path)} ({key})")
    check_request_size(f"{objects_file}: {len(objects)} objects x {len(receptacles)} "
                       f"receptacles", len(objects) * len(receptacles))
    boxes, boxes_file = _json(folder, RECEPTACLE_BOXES)
    if not isinstance(boxes, dict):
        raise ValueError(f"{boxes_file}: (top level): must be an object of id -> box")
    corners = np.zeros((len(receptacles), 8, 3), np.float32)
    for r, i in enumerate(receptacles):
        entry = boxes.get(i)
        if entry is None:
            raise ValueError(f"{boxes_file}: {i}: missing (listed in {RECEPTACLE_NAMES})")
        points = entry.get("cornerPoints") if isinstance(entry, dict) else None
        try:
            value = np.asarray(points, np.float64)
        except (TypeError, ValueError):
            value = np.zeros(0)
        if value.shape != (8, 3) or not _numbers(points, 2) or not np.all(np.isfinite(value)):
            raise ValueError(f"{boxes_file}: {i}.cornerPoints: must be 8 finite [x, y, z] "
                             f"points")
        corners[r] = value[:, _SWAP]
    allowed_lists, allowed_file = _json(folder, OBJECT_ALLOWED)
    if not isinstance(allowed_lists, dict):
        raise ValueError(f"{allowed_file}: (top level): must be an object of object id -> "
                         f"[receptacle id, ...]")
    index = {i: r for r, i in enumerate(receptacles)}
    allowed = np.zeros((len(objects), len(receptacles)), bool)
    for m, i in enumerate(objects):
        if i not in allowed_lists:
            raise ValueError(f"{allowed_file}: {i}: missing (listed in {OBJECT_NAMES})")
        listed = allowed_lists[i]
        if not isinstance(listed, list):
            raise ValueError(f"{allowed_file}: {i}: must be a list of receptacle ids")
        for r in listed:
            if not isinstance(r, str) or r not in index:
                raise ValueError(f"{allowed_file}: {i}: {r!r} is not in {RECEPTACLE_NAMES}"
                                 [:300])
            allowed[m, index[r]] = True
    extra = sorted(set(allowed_lists) - set(objects))
    if extra:
        raise ValueError(f"{allowed_file}: {extra[0]}: not in {OBJECT_NAMES}")
    files = _scan_files(folder)
    scan_file = os.fspath(files[0]) if len(files) == 1 else os.fspath(folder / "scan_N.parquet")
    scans = read_scans(files)
    assignment = scans["assignment"]
    for axis, ids, file in ((1, objects, OBJECT_NAMES), (2, receptacles, RECEPTACLE_NAMES)):
        if assignment.shape[axis] != len(ids):
            raise ValueError(f"{scan_file}: assignment: has {assignment.shape[axis]} "
                             f"{'objects' if axis == 1 else 'receptacles'} per row, but "
                             f"{file} lists {len(ids)}")
    t, m = assignment.shape[:2]
    for column, shape in (("rotation", (t, m)), ("aabb_cornerPoints", (t, m, 8, 3))):
        if scans[column].shape != shape:
            raise ValueError(f"{scan_file}: {column}: has shape {scans[column].shape}, "
                             f"expected {shape} (rows, objects as in assignment)")
    location = _one_hot(assignment, scan_file)
    object_corners = scans["aabb_cornerPoints"].astype(np.float32)[..., _SWAP]
    rotation = scans["rotation"].astype(np.float32)
    env = Environment(
        name=name, receptacle_ids=tuple(receptacles),
        receptacle_classes=tuple(class_of(i) for i in receptacles),
        receptacle_texts=tuple(class_text(class_of(i)) for i in receptacles),
        receptacle_room=np.full(len(receptacles), -1, np.int32), receptacle_corners=corners,
        object_ids=tuple(objects), object_classes=tuple(class_of(i) for i in objects),
        object_texts=tuple(class_text(class_of(i)) for i in objects), allowed=allowed,
        hours=np.arange(t, dtype=np.int64), location=location,
        object_corners=object_corners, object_rotation=rotation,
        source={"from": "flowmaps2026", "folder": name,
                "scans": [f.name for f in files]})
    files_named = {"json": os.fspath(folder / OBJECT_ALLOWED), "arrays": scan_file}
    if (folder / EXTRAS).is_file():
        return _with_extras(env, folder, assignment)
    return validate_environment(env, _files=files_named)


def _with_extras(env: Environment, folder: pathlib.Path, assignment: np.ndarray
                 ) -> Environment:
    """``env`` completed from its ``flowmaps_recorded.json`` (checked against the other
    files)."""
    data, file = _json(folder, EXTRAS)
    if not isinstance(data, dict) or sorted(data) != sorted(_EXTRAS_KEYS):
        raise ValueError(f"{file}: (top level): must hold exactly the keys "
                         f"{list(_EXTRAS_KEYS)}")
    if data["format"] != FORMAT or data["version"] != VERSION or data["layout"] != _LAYOUT:
        raise ValueError(f"{file}: format: is not {FORMAT} version {VERSION} ({_LAYOUT})")
    hours = data["hours"]
    rows = env.num_hours
    if (not isinstance(hours, list) or not hours or not all(
            isinstance(h, int) and not isinstance(h, bool) and 0 <= h < rows for h in hours)
            or any(b <= a for a, b in itertools.pairwise(hours))):
        raise ValueError(f"{file}: hours: must be strictly increasing row numbers in "
                         f"0..{rows - 1}")
    hours = np.asarray(hours, np.int64)
    others = np.setdiff1d(np.arange(rows), hours)
    if np.any(assignment[others] != 0):
        raise ValueError(f"{file}: hours: a row it does not list (hour {others[0]}) has an "
                         f"assignment; such rows must be all 0")
    arrays = {"hours": hours, "location": env.location[hours],
              "receptacle_corners": env.receptacle_corners}
    distance = data["distance"]
    if distance is not None:
        try:
            arrays["distance"] = np.asarray(distance, np.float32)
            if not _numbers(distance, 2):
                raise ValueError
        except (TypeError, ValueError):
            raise ValueError(f"{file}: distance: must be an R x R list of numbers") from None
    for key, value in (("object_corners", env.object_corners[hours]),
                       ("object_rotation", env.object_rotation[hours])):
        if data[key] not in ("recorded", "derived"):
            raise ValueError(f"{file}: {key}: must be 'recorded' or 'derived'")
        if data[key] == "recorded":
            arrays[key] = value
    names = {"json": file, "arrays": file}
    extended = _environment_from_json(env.name, data["environment"], arrays, names)
    for field in ("receptacle_ids", "receptacle_classes", "object_ids", "object_classes"):
        if getattr(extended, field) != getattr(env, field):
            raise ValueError(f"{file}: environment.{field}: differs from the folder's name "
                             f"files; remove {EXTRAS} if they were changed on purpose")
    if not np.array_equal(extended.allowed, env.allowed):
        raise ValueError(f"{file}: environment.objects[*].allowed: differs from "
                         f"{OBJECT_ALLOWED}")
    return extended


def import_flowmaps2026(root, *, progress: Progress = None) -> Recorded:
    """Every environment folder under ``root`` (at any depth; see the module's docstring) as
    one recorded world, each named by its path relative to ``root``. ``ValueError`` with one
    line naming the file and the field for a folder that contradicts itself."""
    root = pathlib.Path(check_dir("root", root))
    folders = environment_folders(root)
    if not folders:
        raise ValueError(f"{os.fspath(root)}: (folder): holds no environment folder (none with "
                         f"{SCAN_MERGED} or scan_N.parquet)")
    for name, folder in folders:
        try:
            check_environment_name(name)
        except ValueError as err:
            raise ValueError(f"{os.fspath(folder)}: (folder): {err}") from None
    lookups: dict = {}
    items = folders if progress is None else progress(folders)
    return validate_recorded(Recorded(tuple(
        import_environment(name, folder, lookups, root) for name, folder in items)))


# ------------------------------------------------------------------------------ export


def derived_object_corners(env: Environment) -> np.ndarray:
    """float32 (T, M, 8, 3) boxes (x, y, z up) for ``env``'s objects: a cube of side
    ``DERIVED_OBJECT_SIZE`` on the top face of the receptacle each was last seen on (the first
    one it is seen on before that; zeros for an object never seen)."""
    location = np.asarray(env.location)
    t, m = location.shape
    seen = location >= 0
    last = np.where(seen, np.arange(t)[:, None], -1)
    last = np.maximum.accumulate(last, axis=0)  # the row of the latest sighting so far
    first = np.argmax(seen, axis=0)  # the first sighting (0 if never)
    row = np.where(last >= 0, last, first[None, :])
    where = location[row, np.arange(m)[None, :]]  # (T, M), -1 if never seen
    boxes = env.receptacle_boxes()
    top = boxes[np.maximum(where, 0)]
    side = np.float32(DERIVED_OBJECT_SIZE)
    centre = np.stack([top[..., 0], top[..., 1], top[..., 2] + top[..., 5] / 2 + side / 2], -1)
    signs = np.asarray([[x, y, z] for z in (-1, 1) for x, y in
                        ((-1, -1), (1, -1), (1, 1), (-1, 1))], np.float32)
    corners = centre[..., None, :] + signs * (side / 2)
    return np.where((where >= 0)[..., None, None], corners, 0.0).astype(np.float32)


def check_export_size(env: Environment) -> int:
    """The hourly rows (0 .. hours[-1]) of exporting ``env``, its memory through the budget:
    per row and object the one-hot row and, at the peak, three copies of the float columns."""
    rows, m, r = int(env.hours[-1]) + 1, env.num_objects, env.num_receptacles
    check_request_size(f"exporting {env.name!r} ({rows} hourly rows x {m} objects)",
                       rows * m * (2 * r + 3 * 4 * 26))
    return rows


def _rows(env: Environment) -> dict[str, np.ndarray]:
    """The parquet columns of ``env``: one row per hour 0 .. hours[-1]."""
    hours = np.asarray(env.hours)
    rows, m, r = check_export_size(env), env.num_objects, env.num_receptacles
    assignment = np.zeros((rows, m, r), np.int8)
    t_seen, m_seen = np.nonzero(env.observed)
    assignment[hours[t_seen], m_seen, np.asarray(env.location)[t_seen, m_seen]] = 1
    corners = np.zeros((rows, m, 8, 3), np.float32)
    corners[hours] = (derived_object_corners(env) if env.object_corners is None
                      else np.asarray(env.object_corners, np.float32))
    rotation = np.zeros((rows, m), np.float32)
    if env.object_rotation is not None:
        rotation[hours] = env.object_rotation
    return {"assignment": assignment, "rotation": rotation,
            "aabb_cornerPoints": corners[..., _SWAP]}


def _parquet_bytes(columns: dict[str, np.ndarray]) -> bytes:
    """The columns (rows first) as a parquet file of fixed-size list columns."""
    pa, pq = _pyarrow()
    fields = {}
    for name, array in columns.items():
        nested = pa.array(np.ascontiguousarray(array).reshape(-1))
        for size in reversed(array.shape[1:]):
            nested = pa.FixedSizeListArray.from_arrays(nested, size)
        fields[name] = nested
    sink = pa.BufferOutputStream()
    pq.write_table(pa.table(fields), sink, compression="zstd")
    return sink.getvalue().to_pybytes()


def _dumps(value: Any) -> str:
    return json.dumps(value, indent=4, allow_nan=False) + "\n"


def export_files(env: Environment) -> dict[str, str | bytes]:
    """The authors'-layout files of one environment: {file name: contents}."""
    allowed = np.asarray(env.allowed)
    corners = np.asarray(env.receptacle_corners, np.float32)[..., _SWAP]
    extras = {
        "format": FORMAT, "version": VERSION, "layout": _LAYOUT,
        "environment": environment_json(env),
        "hours": [int(h) for h in env.hours],
        "distance": None if env.distance is None else np.asarray(env.distance).tolist(),
        "object_corners": "derived" if env.object_corners is None else "recorded",
        "object_rotation": "derived" if env.object_rotation is None else "recorded"}
    return {
        SCAN_MERGED: _parquet_bytes(_rows(env)),
        OBJECT_NAMES: _dumps(list(env.object_ids)),
        RECEPTACLE_NAMES: _dumps(list(env.receptacle_ids)),
        RECEPTACLE_BOXES: _dumps({i: {"cornerPoints": c.tolist()}
                                  for i, c in zip(env.receptacle_ids, corners, strict=True)}),
        OBJECT_ALLOWED: _dumps({i: [env.receptacle_ids[r] for r in np.flatnonzero(a)]
                                for i, a in zip(env.object_ids, allowed, strict=True)}),
        EXTRAS: json.dumps(extras, allow_nan=False) + "\n"}


def lookup_json(recorded: Recorded) -> dict:
    """The ``lookup.json`` of ``recorded``: class -> id over its sorted vocabulary."""
    vocabulary = recorded.vocabulary()
    return {"pickupable2id": {c: i for i, c in enumerate(vocabulary["objects"])},
            "receptacle2id": {c: i for i, c in enumerate(vocabulary["receptacles"])}}


def export_flowmaps2026(recorded: Recorded, root, *, progress: Progress = None
                        ) -> pathlib.Path:
    """Write ``recorded`` into the folder ``root`` in the authors' layout: ``root/lookup.json``
    and one folder ``root/<environment name>/`` per environment (see the module's docstring).
    Every environment's files are written aside and renamed into place together; nothing is
    written through a symbolic link; a ``root`` holding an environment folder that this export
    does not write (an earlier export's) is refused. Returns ``root/lookup.json``."""
    validate_recorded(recorded)
    _pyarrow()
    for env in recorded.environments:  # every refusal before anything is written
        if env.receptacle_corners is None:
            raise ValueError(f"environment {env.name!r} has no receptacle boxes (a version-2 "
                             f"scene graph); the authors' layout needs them")
        check_export_size(env)
        bad = [(i, c) for i, c in zip((*env.receptacle_ids, *env.object_ids),
                                      (*env.receptacle_classes, *env.object_classes),
                                      strict=True) if class_of(i) != c]
        if bad:
            raise ValueError(f"environment {env.name!r}: the id {bad[0][0]!r} does not start "
                             f"with its class {bad[0][1]!r} and '|'; the authors' layout "
                             f"reads an id's class from it")
    root = pathlib.Path(check_output_dir("root", root))
    names = [SCAN_MERGED, OBJECT_NAMES, RECEPTACLE_NAMES, RECEPTACLE_BOXES, OBJECT_ALLOWED,
             EXTRAS]
    for env in recorded.environments:
        check_no_link_below(root, env.name, "root")
    if root.is_dir():  # an earlier export's folders would be read with this one's
        written = {os.path.normcase(os.path.abspath(root / n)) for n in recorded.names()}
        stale = [name for name, folder in environment_folders(root)
                 if os.path.normcase(os.path.abspath(folder)) not in written]
        if stale:
            raise ValueError(f"root: {os.fspath(root)!r} already holds the environment folder "
                             f"{stale[0]!r} ({len(stale)} in all), which this export does not "
                             f"write; their loader and import-flowmaps2026 would read it with "
                             f"the new ones: choose an empty folder")
    root = make_output_dir("root", root, [LOOKUP])
    write_files({root / LOOKUP: _dumps(lookup_json(recorded))}, name="root")
    items = recorded.environments if progress is None else progress(recorded.environments)
    for env in items:
        folder = make_output_dir("root", root / env.name, names)
        write_files({folder / name: data for name, data in export_files(env).items()},
                    name="root")
    return root / LOOKUP
