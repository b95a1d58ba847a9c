"""A run directory belongs to one run, written by one process at a time (docs/guarantees.md,
"One writer per run"): :func:`claim` takes it (lock ``<dir>/.lock`` created with ``O_EXCL``,
holding ``<pid> <host>``; symbolic links refused), :func:`write_atomic` / :func:`open_append`
write in it, :func:`kept_records` are the metrics lines a resumed run keeps.
"""

from __future__ import annotations

import contextlib
import errno
import os
import pathlib
import shutil
import socket
import time
from collections.abc import Callable, Iterator

import jax

from flowmaps_jax import distributed
from flowmaps_jax.atomic_files import check_no_links, check_tree_no_links, move_aside, write_file
from flowmaps_jax.store import checkpoints
from flowmaps_jax.untrusted_files import parse_json

LOCK_NAME = ".lock"
METRICS = "metrics.jsonl"
RUN_FILES = ("config.json", METRICS, "routine_curve.png", "checkpoints")
"""What a training run writes in its directory (besides the lock)."""
_TEMPORARY = tuple(f"{name}.tmp" for name in RUN_FILES[:3])  # write_atomic's, if it was killed
DISK_ERRNOS = frozenset(getattr(errno, name) for name in ("ENOSPC", "EDQUOT", "EFBIG", "EIO")
                        if hasattr(errno, name))
"""Failed writes that are the machine's state, not a bad argument (exit code 74)."""


_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)


def write_atomic(path: pathlib.Path, data: str | bytes) -> None:
    """Write ``data`` to ``path`` whole or not at all (``atomic_files.write_file``)."""
    write_file(path, data, name="run file")


def open_append(path: pathlib.Path):
    """``path`` opened for appending text; a symbolic link there is an error, not followed."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | _NOFOLLOW, 0o644)
    except OSError as err:
        if err.errno == errno.ELOOP:
            raise ValueError(f"{path} is a symbolic link; a run writes only its own "
                             f"files") from None
        raise
    return os.fdopen(fd, "a")


def check_own_files(run_dir: pathlib.Path) -> None:
    """``ValueError`` naming the path if anything in ``run_dir`` is a symbolic link."""
    if pathlib.Path(run_dir).is_dir():
        check_tree_no_links("run directory file", run_dir)


def _saved_nothing(run_dir: pathlib.Path) -> list[str] | None:
    """The entries of ``run_dir`` if they are only what a run leaves before its first
    checkpoint (config, metrics, an empty or unfinished ``checkpoints/``), else None."""
    held = _entries(run_dir)
    if not held or not set(held) <= {*RUN_FILES, *_TEMPORARY}:
        return None
    ckpt = run_dir / "checkpoints"
    if ckpt.exists():
        if ckpt.is_symlink() or not ckpt.is_dir():
            return None
        for sub in ckpt.iterdir():
            if sub.name not in ("last", "best") or sub.is_symlink() or not sub.is_dir():
                return None
            # a finished save is a directory named by its step; orbax's unfinished ones are not
            if any(p.name.isdigit() for p in sub.iterdir()):
                return None
    return held


def has_checkpoint(run_dir: pathlib.Path) -> bool:
    """Whether a run directory holds something beyond a run that saved no checkpoint."""
    return bool(_entries(run_dir)) and _saved_nothing(run_dir) is None


def clear_unsaved(run_dir: pathlib.Path, held: list[str]) -> None:
    """Remove the leftovers ``held`` of a run that saved no checkpoint (links are removed, never
    followed)."""
    for name in held:
        path = run_dir / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink(missing_ok=True)


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


@contextlib.contextmanager
def claim(run_dir: pathlib.Path, *, resume: bool, overwrite: bool = False,
          log: Callable[[str], None] = print) -> Iterator[RunLock | None]:
    """Hold ``run_dir`` for one run; ValueError if it is not free. Yields the lock (None on the
    other processes of a multi-host job). ``overwrite`` moves an old run aside for a new one
    (ignored with ``resume``)."""
    if jax.process_count() == 1:
        with _claim_here(run_dir, resume=resume, overwrite=overwrite, log=log) as lock:
            yield lock
        return
    with contextlib.ExitStack() as held:
        error, lock = "", None
        if jax.process_index() == 0:
            try:
                lock = held.enter_context(_claim_here(run_dir, resume=resume,
                                                      overwrite=overwrite, log=log))
            except ValueError as err:
                error = str(err)
        if distributed.agree(not error):
            yield lock
            return
        raise ValueError(error or f"process 0 could not claim the run directory {run_dir} "
                                  "(its log says why)")


@contextlib.contextmanager
def _claim_here(run_dir: pathlib.Path, *, resume: bool, overwrite: bool,
                log: Callable[[str], None]) -> Iterator[RunLock]:
    """:func:`claim` by this process alone (``run_dir`` checked by the caller)."""
    run_dir = pathlib.Path(run_dir)
    if overwrite and not resume:
        here = pathlib.Path.cwd().resolve()
        if run_dir.resolve() == here or run_dir.resolve() in here.parents:
            raise ValueError(f"--overwrite cannot move run_dir {str(run_dir)!r} aside: it is the "
                             f"current directory or holds it; give the run directory by its "
                             f"own path, e.g. runs/NAME")
    created = not run_dir.exists()
    if created and resume:
        raise ValueError(f"run directory {run_dir} does not exist; nothing to resume")
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        if err.errno in DISK_ERRNOS:
            raise
        raise ValueError(f"run_dir {str(run_dir)!r} cannot be created ({err.strerror})") from None
    lock = RunLock(run_dir, log)
    try:
        if resume:  # before anything in it is read
            check_own_files(run_dir)
        held = _entries(run_dir)
        unsaved = _saved_nothing(run_dir) if held and not resume and not overwrite else None
        if unsaved:
            clear_unsaved(run_dir, unsaved)
            log(f"Run directory {run_dir} held a run that saved no checkpoint "
                f"({', '.join(unsaved)}); starting afresh there")
        elif held and not resume:
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
        check_no_links("run directory file", run_dir, RUN_FILES)  # and their .tmp
        check_own_files(run_dir)  # a new run: what is left after the leftovers were cleared
        yield lock
    finally:
        lock.release()
        if created:
            with contextlib.suppress(OSError):
                run_dir.rmdir()  # only succeeds if nothing was written


# --------------------------------------------------------------------------------------------
# The metrics file and the checkpoints of a run


def kept_records(run_dir: pathlib.Path, resumed_step: int | None,
                 log: Callable[[str], None]) -> list[str]:
    """The lines of ``metrics.jsonl`` up to ``resumed_step`` (None: none). A half-written last
    line is dropped with a message; a bad line elsewhere is a ValueError naming it."""
    path = run_dir / METRICS
    if resumed_step is None or not path.exists():
        return []
    lines = path.read_bytes().decode("utf-8", errors="replace").split("\n")
    numbered = [(n, line) for n, line in enumerate(lines, 1) if line.strip()]
    kept = []
    for n, line in numbered:
        try:
            record, why = parse_json(f"line {n}", line),\
                "not a JSON object with an integer step"
        except ValueError as err:
            record, why = None, str(err)
        if not isinstance(record, dict) or not isinstance(record.get("step", 0), int):
            if n != numbered[-1][0]:
                raise ValueError(f"{path} line {n} is not a metrics record ({why}); repair or "
                                 f"delete that line, then resume again")
            log(f"Dropped the half-written last line of {path} (line {n}: {_clip(line)})")
            continue
        if record.get("step", 0) <= resumed_step:
            kept.append(line)
    return kept


def _clip(text: str, limit: int = 60) -> str:
    return repr(text if len(text) <= limit else text[:limit] + "...")


def checkpoint_root(run_dir: pathlib.Path) -> pathlib.Path:
    """The checkpoint directory of the run in ``run_dir`` (ValueError for a checkpoint
    directory given as the run)."""
    ckpt_dir = run_dir / "checkpoints"
    if not ckpt_dir.exists() and ((run_dir / "last").is_dir() or (run_dir / "best").is_dir()):
        raise ValueError(f"run_dir {str(run_dir)!r} is a checkpoint directory (it holds last/ or "
                         f"best/), not a run directory: resume the run that holds it, "
                         f"--run-dir {run_dir.parent}")
    return checkpoints.resolve_checkpoint_dir(ckpt_dir if ckpt_dir.exists() else run_dir)


def only_best_saved(run_dir: pathlib.Path) -> bool:
    """Whether the run's checkpoints hold a finished ``best`` step and no ``last`` one."""
    root = run_dir / "checkpoints"
    if not root.is_dir() or root.is_symlink():
        return False
    held = {sub.name for _, sub in checkpoints.saved_copies(root)}
    return held == {"best"}
