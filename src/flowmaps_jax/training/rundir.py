"""A run directory belongs to one run, written by one process at a time.

* :func:`check_run_dir`: the path must be (or become) a writable directory: a file, a path under
  a file or a read-only place is a ``ValueError``.
* :func:`claim` (a context manager) takes the directory for a run. A new run (no ``resume``)
  needs an empty or missing directory; ``overwrite`` first moves an old run aside to
  ``<dir>.old-<timestamp>``. The lock file ``<dir>/.lock`` (created with ``O_EXCL``, holding
  ``<pid> <host>``) keeps a second process out while the first one runs; a lock left by a
  process that no longer exists (kill -9, power loss) is taken over with a message. The lock is
  released on exit, and a directory the claim created is removed again if nothing was written.
* :func:`write_atomic` writes a file through a temporary file and a rename, so a crash or a full
  disk never leaves it half-written.
"""

from __future__ import annotations

import contextlib
import os
import pathlib
import socket
import time
from collections.abc import Callable, Iterator

from flowmaps_jax.validation import check_output_dir

LOCK_NAME = ".lock"


def check_run_dir(run_dir) -> pathlib.Path:
    """``run_dir`` as a Path, if it is or can become a writable directory (else ValueError)."""
    return pathlib.Path(check_output_dir("run_dir", run_dir))


def write_atomic(path: pathlib.Path, text: str) -> None:
    """Write ``text`` to ``path`` via ``<path>.tmp`` and a rename (no half-written file)."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "w") as file:
            file.write(text)
            file.flush()
            os.fsync(file.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _identity() -> str:
    return f"{os.getpid()} {socket.gethostname()}"


def _holder_alive(text: str) -> bool:
    """Whether the process named in a lock file may still be running (unknown: assume so)."""
    parts = text.split()
    if len(parts) != 2 or not parts[0].isdigit():
        return True
    pid, host = int(parts[0]), parts[1]
    if host != socket.gethostname():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class RunLock:
    """``<run_dir>/.lock`` held by this process; :meth:`release` removes it if it is still ours."""

    def __init__(self, run_dir: pathlib.Path, log: Callable[[str], None] = print):
        self.path = run_dir / LOCK_NAME
        self._me = _identity()
        for _ in range(3):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                self._take_over_if_stale(log)
                continue
            except OSError as err:
                raise ValueError(f"run_dir {str(run_dir)!r} is not writable ({err.strerror})"
                                 ) from None
            with os.fdopen(fd, "w") as file:
                file.write(self._me + "\n")
            return
        raise ValueError(f"could not take the lock {self.path}; another process keeps taking it")

    def _read(self) -> str | None:
        try:
            return self.path.read_text().strip()
        except FileNotFoundError:
            return None

    def _take_over_if_stale(self, log: Callable[[str], None]) -> None:
        holder = self._read()
        if holder is None:  # released meanwhile: try again
            return
        try:
            age = time.time() - self.path.stat().st_mtime
        except FileNotFoundError:
            return
        # An empty lock file is being written right now, or was left by a crash in between.
        pid = holder.split()[0] if holder else "?"
        if (age < 10) if not holder else _holder_alive(holder):
            raise ValueError(
                f"run directory {self.path.parent} is in use by process {pid} (lock file "
                f"{self.path}); wait for that run to finish, or delete the lock file if you are "
                f"sure no process is writing there")
        stale = self.path.with_name(f"{LOCK_NAME}.stale-{os.getpid()}")
        try:
            self.path.rename(stale)  # atomic: only one process takes a given stale lock
        except FileNotFoundError:
            return
        if stale.read_text().strip() != holder:  # took a fresh lock by mistake: put it back
            stale.rename(self.path)
            return
        stale.unlink()
        log(f"Took over the stale lock {self.path} of process {pid}, which is no longer "
            f"running.")

    def release(self) -> None:
        if self._read() == self._me:
            self.path.unlink(missing_ok=True)


def _entries(run_dir: pathlib.Path) -> list[str]:
    return sorted(p.name for p in run_dir.iterdir() if p.name != LOCK_NAME)


def move_aside(run_dir: pathlib.Path) -> pathlib.Path:
    """Rename ``run_dir`` to a free ``<run_dir>.old-<timestamp>`` and return that path."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    target = run_dir.with_name(f"{run_dir.name}.old-{stamp}")
    suffix = 1
    while target.exists():
        suffix += 1
        target = run_dir.with_name(f"{run_dir.name}.old-{stamp}-{suffix}")
    run_dir.rename(target)
    return target


@contextlib.contextmanager
def claim(run_dir: pathlib.Path, *, resume: bool, overwrite: bool = False,
          log: Callable[[str], None] = print) -> Iterator[RunLock]:
    """Hold ``run_dir`` for one run (see the module docstring); ValueError if it is not free."""
    run_dir = check_run_dir(run_dir)
    if resume and overwrite:
        raise ValueError("--resume and --overwrite exclude each other")
    created = not run_dir.exists()
    if created and resume:
        raise ValueError(f"run directory {run_dir} does not exist; nothing to resume")
    run_dir.mkdir(parents=True, exist_ok=True)
    lock = RunLock(run_dir, log)
    try:
        held = _entries(run_dir)
        if held and not resume:
            if not overwrite:
                raise ValueError(
                    f"run directory {run_dir} is not empty (it holds {', '.join(held[:4])}"
                    f"{', ...' if len(held) > 4 else ''}): continue the run there with --resume, "
                    f"or start a new one with --overwrite (the old contents are then moved to "
                    f"{run_dir}.old-<timestamp>), or choose another --run-dir")
            old = move_aside(run_dir)  # our lock file moves along: nobody wrote meanwhile
            (old / LOCK_NAME).unlink(missing_ok=True)
            log(f"--overwrite: moved the old run in {run_dir} to {old}")
            run_dir.mkdir()
            created = True
            lock = RunLock(run_dir, log)
        yield lock
    finally:
        lock.release()
        if created:
            with contextlib.suppress(OSError):
                run_dir.rmdir()  # only succeeds if nothing was written
