"""Reading files this project did not write, or that may have changed since: :func:`read_npz`
(members whitelisted, declared sizes checked before decompressing, no pickles) and
:func:`parse_json` / :func:`read_json` (size and nesting bounded). Any failure is a
``ValueError`` naming the file.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import zipfile
from collections.abc import Sequence
from typing import Any

import numpy as np

from flowmaps_jax.resources import array_bytes, memory_limit


def read_npz(name: str, source: Any, *, allowed: Sequence[str] | None = None,
             required: Sequence[str] = (), max_bytes: int | None = None,
             expected: dict[str, tuple[tuple[int, ...], Any]] | None = None
             ) -> dict[str, np.ndarray]:
    """The arrays of an untrusted ``.npz`` (a path or a file object): members ``<key>.npy`` for
    keys in ``allowed`` (None: any) with ``required`` present, declared sizes at most
    ``max_bytes``, ``expected`` ({key: (shape, dtype)}) exact, no pickles, all checked before
    anything is decompressed. ValueError naming ``name``.
    """
    limit = memory_limit() if max_bytes is None else int(max_bytes)
    try:
        archive = zipfile.ZipFile(source)
    except (OSError, zipfile.BadZipFile, ValueError) as err:
        raise ValueError(f"{name} is not a readable .npz file ({err})") from None
    with archive, contextlib.ExitStack() as members:
        infos = archive.infolist()
        keys = []
        for info in infos:
            key = info.filename[:-4] if info.filename.endswith(".npy") else None
            if key is None or (allowed is not None and key not in allowed) \
                    or (expected is not None and key not in expected):
                raise ValueError(f"{name} holds an unexpected member {info.filename!r}")
            keys.append(key)
        if len(set(keys)) != len(keys):
            raise ValueError(f"{name} holds a member twice")
        missing = [k for k in (*required, *(expected or {})) if k not in keys]
        if missing:
            raise ValueError(f"{name} is missing arrays {sorted(set(missing))}")
        declared = sum(info.file_size for info in infos)
        if declared > limit:
            raise ValueError(f"{name} declares {declared / 1e9:.3g} GB of arrays, more than the "
                             f"{limit / 1e9:.3g} GB allowed; not reading it")
        headers = []
        for info, key in zip(infos, keys, strict=True):
            with _member_errors(name, info):
                member = members.enter_context(archive.open(info))
                headers.append((member, _npy_header(member, info.file_size,
                                                    None if expected is None else expected[key])))
        total = sum(array_bytes(shape, dtype) for _, (shape, _, dtype) in headers)
        if total > limit:
            raise ValueError(f"{name} holds {total / 1e9:.3g} GB of arrays (by their headers), "
                             f"more than the {limit / 1e9:.3g} GB allowed; not reading it")
        arrays = {}
        for info, key, (member, header) in zip(infos, keys, headers, strict=True):
            with _member_errors(name, info):
                arrays[key] = _read_npy_data(member, *header)
    return arrays


@contextlib.contextmanager
def _member_errors(name: str, info):
    try:
        yield
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
        raise ValueError(f"{name}: member {info.filename!r} is not a valid array "
                         f"({err})") from None


def _npy_header(member, declared: int, expected) -> tuple:
    """(shape, fortran, dtype) of one ``.npy`` member, checked against its declared size."""
    version = np.lib.format.read_magic(member)
    readers = {(1, 0): np.lib.format.read_array_header_1_0,
               (2, 0): np.lib.format.read_array_header_2_0}
    if version not in readers:
        raise ValueError(f"unsupported .npy format version {version}")
    shape, fortran, dtype = readers[version](member)
    if dtype.hasobject:
        raise ValueError("it holds Python objects")
    if expected is not None and (tuple(shape) != tuple(expected[0])
                                 or dtype != np.dtype(expected[1])):
        raise ValueError(f"expected shape {tuple(expected[0])} and dtype "
                         f"{np.dtype(expected[1])}; got {tuple(shape)} and {dtype}")
    if array_bytes(shape, dtype) > declared:
        raise ValueError(f"its header claims {array_bytes(shape, dtype)} bytes, more than the "
                         f"{declared} declared")
    return tuple(shape), fortran, dtype


def _read_npy_data(member, shape, fortran, dtype) -> np.ndarray:
    """The data of one ``.npy`` member after its header, read once into the array."""
    array = np.empty(shape, dtype, order="F" if fortran else "C")
    buffer = memoryview(array.reshape(-1, order="A").view(np.uint8))
    done = 0
    while done < len(buffer):
        count = member.readinto(buffer[done:done + 2**20])
        if not count:
            raise ValueError(f"it holds {done} bytes of data where its header says "
                             f"{len(buffer)}")
        done += count
    if member.read(1):
        raise ValueError(f"it holds more data than the {len(buffer)} bytes its header says")
    return array


MAX_JSON_DEPTH = 64
"""The deepest nesting of arrays and objects accepted in a JSON file read from disk (a config is
about 4 deep); deeper text is refused before it is parsed (Python's parser would recurse)."""
MAX_JSON_BYTES = 16 * 1024 * 1024
_JSON_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"?', re.DOTALL)
"""A JSON string; an unterminated one runs to the end (one pass: linear in the text's length)."""


def json_depth(text: str) -> int:
    """The deepest nesting of ``[`` / ``{`` in the JSON ``text``, strings skipped (a malformed
    text gets some count; the parser refuses it anyway)."""
    brackets = np.frombuffer(_JSON_STRING.sub("", text).encode(), np.uint8)
    steps = (np.isin(brackets, (ord("["), ord("{"))).astype(np.int64)
             - np.isin(brackets, (ord("]"), ord("}"))))
    return int(np.cumsum(steps).max(initial=0))


def parse_json(name: str, text: str | bytes, *, max_depth: int = MAX_JSON_DEPTH) -> Any:
    """The value of the untrusted JSON ``text``; ``ValueError`` naming ``name`` (the file) if it
    is not UTF-8, not JSON, or nested deeper than ``max_depth`` (never a ``RecursionError``)."""
    if isinstance(text, bytes):
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError as err:
            raise ValueError(f"{name} is not UTF-8 text ({err.reason} at byte {err.start})"
                             ) from None
    depth = json_depth(text)
    if depth > max_depth:
        raise ValueError(f"{name} is nested {depth} levels deep, more than the {max_depth} "
                         f"a file of this project has; not reading it")
    try:
        return json.loads(text)
    except RecursionError:
        raise ValueError(f"{name} is nested too deeply to read") from None
    except ValueError as err:
        raise ValueError(f"{name} is not valid JSON ({err})") from None


def read_json(name: str, path: Any, *, max_bytes: int = MAX_JSON_BYTES,
              max_depth: int = MAX_JSON_DEPTH) -> Any:
    """The value of the untrusted JSON file ``path`` (at most ``max_bytes``, nested at most
    ``max_depth``); ``ValueError`` naming ``name`` and the file for any failure but a missing
    or unreadable file (its ``OSError`` propagates)."""
    label = f"{name} {os.fspath(path)!r}" if name else repr(os.fspath(path))
    size = os.stat(path).st_size
    if size > max_bytes:
        raise ValueError(f"{label} holds {size:,} bytes, more than the {max_bytes:,} allowed")
    with open(path, "rb") as file:
        return parse_json(label, file.read(max_bytes + 1), max_depth=max_depth)
