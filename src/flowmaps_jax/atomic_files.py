"""The one writer every command's output files go through: never through a symbolic link, never
half-written (a temporary beside the target, then a rename); each ``ValueError`` names the path.
"""

from __future__ import annotations

import contextlib
import io
import os
import pathlib
import shutil
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any

_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)


def _link_error(name: str, path: os.PathLike | str) -> ValueError:
    try:
        target = os.readlink(path)
    except OSError:
        target = "?"
    return ValueError(f"{name} {os.fspath(path)!r} is a symbolic link (-> {target}); refusing to "
                      f"write through it: remove the link or choose another output folder")


def check_no_links(name: str, folder: Any, filenames: Iterable[str]) -> None:
    """``ValueError`` if any of ``filenames`` (or its temporary ``<name>.tmp``) inside ``folder``
    is a symbolic link: writing there would go outside ``folder``."""
    folder = pathlib.Path(folder)
    for filename in filenames:
        for candidate in (folder / filename, folder / f"{filename}.tmp"):
            if candidate.is_symlink():
                raise _link_error(name, candidate)


def check_tree_no_links(name: str, folder: Any) -> None:
    """``ValueError`` naming the path if anything under ``folder`` is a symbolic link."""
    for here, dirs, files in os.walk(folder, followlinks=False):
        for entry in sorted(dirs) + sorted(files):
            path = os.path.join(here, entry)
            if os.path.islink(path):
                try:
                    target = os.readlink(path)
                except OSError:
                    target = "?"
                raise ValueError(f"{name} {path!r} is a symbolic link (-> {target}); nothing "
                                 f"is read, written or deleted through one: replace the link "
                                 f"by the folder or file itself, or remove it")


def make_output_dir(name: str, path: Any, files: Iterable[str] = ()) -> pathlib.Path:
    """The folder ``path`` as a Path, created with its parents; ``ValueError`` naming ``name`` if a
    component is a symbolic link or a file, or a link sits at a name of ``files``."""
    path = pathlib.Path(path)
    missing = []
    probe = path
    while not os.path.lexists(probe):
        missing.append(probe)
        if probe.parent == probe:
            break
        probe = probe.parent
    if missing and not os.path.isdir(probe):
        raise ValueError(f"{name} {os.fspath(path)!r} lies under {os.fspath(probe)!r}, which is "
                         f"not a directory")
    for component in reversed(missing):
        try:
            os.mkdir(component)
        except FileExistsError:
            pass  # made meanwhile by another process: checked below
        if os.path.islink(component):
            raise _link_error(name, component)
        if not os.path.isdir(component):
            raise ValueError(f"{name} {os.fspath(component)!r} is a file, not a directory")
    if not os.path.isdir(path):
        raise ValueError(f"{name} {os.fspath(path)!r} is a file, not a directory")
    check_no_links(name, path, files)
    return path


def move_aside(path: pathlib.Path) -> pathlib.Path:
    """Rename ``path`` to a free ``<path>.old-<timestamp>`` and return that path."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    target = path.with_name(f"{path.name}.old-{stamp}")
    suffix = 1
    while target.exists():
        suffix += 1
        target = path.with_name(f"{path.name}.old-{stamp}-{suffix}")
    path.rename(target)
    return target


@contextlib.contextmanager
def output_folder(name: str, path: Any, *, overwrite: bool = False,
                  log: Callable[[str], None] = print) -> Iterator[pathlib.Path]:
    """Yields a temporary folder beside ``path``, renamed to ``path`` on leaving (removed on an
    error). A link or a non-empty folder at ``path`` is a ValueError, unless ``overwrite``
    (moved to ``<path>.old-<timestamp>``)."""
    given, path = os.fspath(path), pathlib.Path(os.path.abspath(path))
    if path.is_symlink():
        raise _link_error(name, given)
    held = sorted(os.listdir(path)) if path.is_dir() else []
    if held and not overwrite:
        raise ValueError(f"{name} {given!r} already holds {', '.join(held[:3])}"
                         f"{', ...' if len(held) > 3 else ''}: add --overwrite to replace it "
                         f"(the old folder is moved to {path.name}.old-<time>), or choose "
                         f"another folder")
    parent = make_output_dir(name, path.parent)
    tmp = pathlib.Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-", dir=parent))
    umask = os.umask(0o22)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)  # as a folder made by mkdir (mkdtemp's is private)
    old = None
    try:
        yield tmp
        if held:
            old = move_aside(path)
        os.rename(tmp, path)  # also over an empty folder; a link or a filled one: an OSError
    except BaseException:
        if old is not None and not os.path.lexists(path):
            os.rename(old, path)
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if old is not None:
        log(f"{name}: moved the old {given} to {old}")


def _write_temporary(path: pathlib.Path, raw: bytes, name: str) -> pathlib.Path:
    """``raw`` written and synced to ``<path>.tmp`` (created exclusively); returns that path."""
    if path.is_symlink():
        raise _link_error(name, path)
    if path.is_dir():
        raise ValueError(f"{name} {os.fspath(path)!r} is a directory; refusing to write there")
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.unlink(missing_ok=True)  # a leftover (or a planted link): removed, never followed
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _NOFOLLOW, 0o644)
        with os.fdopen(fd, "wb") as file:
            file.write(raw)
            file.flush()
            os.fsync(file.fileno())
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise
    return tmp


def write_files(files: dict[Any, str | bytes], *, name: str = "output file") -> None:
    """Write several files as one output: each to its ``<path>.tmp``, then all renamed, so a
    refusal or a failed write leaves none of them new."""
    paths = [pathlib.Path(path) for path in files]
    for path in paths:  # every refusal before anything is written
        if path.is_symlink():
            raise _link_error(name, path)
        if path.is_dir():
            raise ValueError(f"{name} {os.fspath(path)!r} is a directory; refusing to write "
                             f"there")
    written = []
    try:
        for path, data in zip(paths, files.values(), strict=True):
            raw = data.encode() if isinstance(data, str) else bytes(data)
            written.append((_write_temporary(path, raw, name), path))
        for tmp, path in written:
            os.replace(tmp, path)  # replaces the name itself: a link planted meanwhile goes
    except BaseException:
        for tmp, _ in written:
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
        raise


def write_file(path: Any, data: str | bytes, *, name: str = "output file") -> pathlib.Path:
    """Write ``data`` (text as UTF-8, or bytes) to ``path`` through ``<path>.tmp`` and a rename;
    returns ``path``. A link at ``path`` is a ValueError naming ``name``; an OSError removes the
    temporary file and propagates."""
    path = pathlib.Path(path)
    write_files({path: data}, name=name)
    return path


def save_figure(figure: Any, path: Any, *, name: str = "figure", **savefig_kwargs) -> pathlib.Path:
    """``figure.savefig`` rendered in memory (the format from ``path``'s suffix unless given),
    then written with :func:`write_file`."""
    path = pathlib.Path(path)
    buffer = io.BytesIO()
    savefig_kwargs.setdefault("format", path.suffix.lstrip(".") or "png")
    figure.savefig(buffer, **savefig_kwargs)
    return write_file(path, buffer.getvalue(), name=name)
