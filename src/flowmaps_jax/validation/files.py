"""File and name checks: paths, readable files and folders, writable outputs, plain names; each
``ValueError`` starts with the argument's name."""

from __future__ import annotations

import contextlib
import errno
import os
import re
import tempfile
from collections.abc import Sequence
from typing import Any

from flowmaps_jax.atomic_files import check_no_links

# ------------------------------------------------------------------------------ files


def check_path(name: str, value: Any) -> str:
    """``value`` (a str or os.PathLike, not None, a number or bytes) as a non-empty path string."""
    if not isinstance(value, (str, os.PathLike)):
        raise ValueError(f"{name} must be a path (str or os.PathLike); got "
                         f"{type(value).__name__} {value!r}")
    path = os.fspath(value)
    if not isinstance(path, str) or not path:
        raise ValueError(f"{name} must be a non-empty path; got {value!r}")
    return path


def check_file(name: str, value: Any) -> str:
    """An existing, readable regular file; a directory is named as such."""
    path = check_path(name, value)
    if os.path.isdir(path):
        raise ValueError(f"{name} {path!r} is a directory, not a file")
    if not os.path.exists(path):
        raise ValueError(f"{name} {path!r} does not exist")
    if not os.path.isfile(path):
        raise ValueError(f"{name} {path!r} is not a regular file")
    if not os.access(path, os.R_OK):
        raise ValueError(f"{name} {path!r} is not readable")
    return path


def check_dir(name: str, value: Any) -> str:
    """An existing, readable directory; a file where a directory is expected is named as such."""
    path = check_path(name, value)
    if not os.path.exists(path):
        raise ValueError(f"{name} {path!r} does not exist")
    if not os.path.isdir(path):
        raise ValueError(f"{name} {path!r} is a file, not a directory")
    if not os.access(path, os.R_OK | os.X_OK):
        raise ValueError(f"{name} {path!r} is not readable")
    return path


def _check_name_lengths(name: str, path: str) -> None:
    """``ValueError`` if a component of ``path`` is longer than the file system allows (NAME_MAX,
    usually 255 bytes) or the whole path longer than PATH_MAX: it could never be created."""
    parent = _existing_parent(path)
    try:
        name_max = os.pathconf(parent, "PC_NAME_MAX")
        path_max = os.pathconf(parent, "PC_PATH_MAX")
    except (OSError, ValueError, AttributeError):
        name_max, path_max = 255, 4096
    for part in path.split(os.sep):
        if len(os.fsencode(part)) > name_max:
            raise ValueError(f"{name} {_short_repr(path)}: the name {_short_repr(part, 40)} is "
                             f"{len(os.fsencode(part))} bytes long, more than the {name_max} "
                             f"the file system allows")
    if len(os.fsencode(os.path.abspath(path))) >= path_max:
        raise ValueError(f"{name} {_short_repr(path)} is longer than the {path_max} bytes the "
                         f"file system allows for a path")


def _existing_parent(path: str) -> str:
    parent = os.path.dirname(os.path.abspath(path))
    while not os.path.exists(parent):
        parent = os.path.dirname(parent)
    return parent


def check_output_file(name: str, value: Any, *, overwrite: bool = True) -> str:
    """A file path that can be written now: its folder exists and is writable, the path is not a
    directory nor a symbolic link (nor is its temporary ``<path>.tmp``), and (unless
    ``overwrite``) no file is there yet."""
    path = check_path(name, value)
    _check_name_lengths(name, path)
    check_no_links(name, os.path.dirname(os.path.abspath(path)), [os.path.basename(path)])
    if os.path.isdir(path):
        raise ValueError(f"{name} {path!r} is a directory; give a file path")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        what = "is not a directory" if os.path.exists(folder) else "does not exist"
        raise ValueError(f"{name} {path!r}: its folder {folder!r} {what}")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"{name} {path!r}: its folder {folder!r} is not writable")
    _probe_write(name, path, folder)
    if os.path.exists(path):
        if not overwrite:
            raise ValueError(f"{name} {path!r} already exists")
        if not os.access(path, os.W_OK):
            raise ValueError(f"{name} {path!r} exists and is not writable")
    return path


def check_output_dir(name: str, value: Any, *, empty: bool = False,
                     files: Sequence[str] = ()) -> str:
    """A directory that exists (or can be created, tried and removed again) and is writable;
    with ``empty``, one holding nothing; no link or directory at a name of ``files``."""
    path = check_path(name, value)
    _check_name_lengths(name, path)
    check_no_links(name, path, files)
    if os.path.exists(path):
        if not os.path.isdir(path):
            raise ValueError(f"{name} {path!r} is a file, not a directory")
        if not os.access(path, os.W_OK | os.X_OK):
            raise ValueError(f"{name} {path!r} is not writable")
        if empty and os.listdir(path):
            raise ValueError(f"{name} {path!r} is not empty (it holds "
                             f"{', '.join(sorted(os.listdir(path))[:5])}...)")
        for file in files:
            if os.path.isdir(os.path.join(path, file)):
                raise ValueError(f"{name} {path!r}: {file!r} there is a directory, where the "
                                 f"command writes a file; move it away or choose another "
                                 f"{name}")
        _probe_write(name, path, path)
        return path
    parent = _existing_parent(path)
    if not os.path.isdir(parent):
        raise ValueError(f"{name} {path!r} lies under {parent!r}, which is a file")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(f"{name} {path!r} cannot be created: {parent!r} is not writable")
    _probe_create(name, path, parent)
    return path


_DISK_ERRNOS = frozenset(getattr(errno, code) for code in ("ENOSPC", "EDQUOT", "EIO")
                         if hasattr(errno, code))


def _probe_write(name: str, path: str, folder: str) -> None:
    """``ValueError`` if no file can be created in the existing ``folder`` (tried, removed again;
    a full disk's ``OSError`` propagates)."""
    try:
        fd, probe = tempfile.mkstemp(prefix=".write-probe-", dir=folder)
    except OSError as err:
        if err.errno in _DISK_ERRNOS:
            raise
        raise ValueError(f"{name} {path!r} cannot be written: no file can be created in "
                         f"{folder!r} ({err.strerror})") from None
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(probe)


def _probe_create(name: str, path: str, parent: str) -> None:
    """``ValueError`` if the first missing folder of ``path`` cannot be created (tried, removed
    again; a full disk's ``OSError`` propagates)."""
    first = os.path.abspath(path)
    while os.path.dirname(first) != os.path.abspath(parent):
        first = os.path.dirname(first)
    try:
        os.mkdir(first)
    except FileExistsError:
        return  # made meanwhile
    except OSError as err:
        if err.errno in _DISK_ERRNOS:
            raise
        raise ValueError(f"{name} {path!r} cannot be created ({err.strerror})") from None
    with contextlib.suppress(OSError):
        os.rmdir(first)


# ------------------------------------------------------------------------------ names

_PLAIN_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.+-]{0,63}")


def check_plain_name(name: str, value: Any) -> str:
    """``value`` if it is a plain name: 1 to 64 letters, digits, ``_ . + -``, starting with a
    letter or digit (so no path separator, no ``..`` escape, no markup or control character)."""
    if not isinstance(value, str) or not _PLAIN_NAME.fullmatch(value) or ".." in value:
        raise ValueError(f"{name} must be a plain name (letters, digits, '_', '.', '+', '-'; "
                         f"at most 64, no path); got {_short_repr(value)}")
    return value


def _short_repr(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "..."
