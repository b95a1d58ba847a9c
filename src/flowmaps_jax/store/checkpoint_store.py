"""Writing a run's checkpoints (the last k saves and the best by validation loss; layout:
:mod:`.checkpoints`): synchronous and atomic, never a non-finite state; a failed write raises
:class:`CheckpointSaveError` and the partial save is removed.
"""

from __future__ import annotations

import contextlib
import errno
import io
import logging
import math
import pathlib
import shutil
import sys

import orbax.checkpoint as ocp

from flowmaps_jax.atomic_files import check_tree_no_links
from flowmaps_jax.store.checkpoints import BEST, LATEST, SUBDIRS, best_manager, last_manager
from flowmaps_jax.store.integrity import describe_state, shorten
from flowmaps_jax.store.packing import pack
from flowmaps_jax.validation import check_int


class CheckpointSaveError(OSError):
    """Writing a checkpoint failed (e.g. no space left on device); the message is one line."""

    def __str__(self) -> str:
        return str(self.strerror)


class _HoldRecords(logging.Filter):
    """Keeps log records back while a save runs; replayed if it succeeds, dropped if it fails."""

    def __init__(self):
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def filter(self, record):
        self.records.append(record)
        return False


@contextlib.contextmanager
def _quiet():
    """Hold back what orbax/tensorstore print during a save (a failed write prints hundreds of
    lines of asyncio tracebacks); replay it only when the save succeeds."""
    logger, hold, text = logging.getLogger("absl"), _HoldRecords(), io.StringIO()
    logger.addFilter(hold)
    try:
        with contextlib.redirect_stderr(text):
            yield
    finally:
        logger.removeFilter(hold)
    if text.getvalue():
        sys.stderr.write(text.getvalue())
    for record in hold.records:
        logger.handle(record)


def _save_error(err: BaseException, step: int, sub: pathlib.Path) -> CheckpointSaveError:
    text = str(err)
    full = isinstance(err, OSError) and err.errno == errno.ENOSPC
    if full or "No space left on device" in text or "os_error_code='28'" in text:
        code, reason = errno.ENOSPC, "No space left on device"
    else:
        code = getattr(err, "errno", None) or errno.EIO
        reason = f"{type(err).__name__}: {shorten(text.splitlines()[0] if text else '', 300)}"
    return CheckpointSaveError(code, f"could not save checkpoint step {step} in {sub}: {reason}")


class CheckpointStore:
    """Writes checkpoints of one run into ``directory`` (created if needed; no symbolic links):
    ``save`` (the ``keep_last`` recent) and ``save_if_best`` (best by val loss)."""

    def __init__(self, directory: str | pathlib.Path, keep_last: int = 2):
        keep_last = check_int("keep_last", keep_last)
        self.directory = pathlib.Path(directory).absolute()
        self.directory.mkdir(parents=True, exist_ok=True)
        # orbax's keep-last deletes old steps: only the run's own, never through a link
        check_tree_no_links(f"checkpoint directory {str(self.directory)!r}", self.directory)
        self._last = last_manager(self.directory / SUBDIRS[LATEST], keep_last)
        self._best = best_manager(self.directory / SUBDIRS[BEST])

    def _write(self, manager, step: int, state, config: dict, meta: dict, **kwargs) -> None:
        sub = self.directory / pathlib.Path(str(manager.directory)).name
        item, layout = pack(state)
        args = ocp.args.Composite(state=ocp.args.StandardSave(item),
                                  config=ocp.args.JsonSave(config),
                                  meta=ocp.args.JsonSave({**meta, "layout": layout}))
        try:
            with _quiet():
                manager.save(step, args=args, force=True, **kwargs)
                manager.wait_until_finished()
        except Exception as err:  # orbax/tensorstore raise many types; report them uniformly
            for partial in sub.glob(f"{step}.orbax-checkpoint-tmp*"):
                shutil.rmtree(partial, ignore_errors=True)
            raise _save_error(err, step, sub) from err

    def save(self, state, config: dict, *, log_window: dict | None = None) -> int:
        """Save ``state`` and ``config`` (JSON dict) under its step (a no-op if saved); returns the
        step. ``log_window``: the loop's metrics window (kept in ``meta``)."""
        step = int(state.step)
        if step not in self._last.all_steps():
            self._write(self._last, step, state, config, describe_state(state, config, log_window))
        return step

    @property
    def best_val_loss(self) -> float | None:
        """Validation loss of the kept best checkpoint (None if there is none)."""
        step = self._best.best_step()
        if step is None:
            return None
        metrics = self._best.metrics(step)
        return None if metrics is None else float(metrics["val_loss"])

    def save_if_best(self, state, config: dict, val_loss: float, *,
                     log_window: dict | None = None) -> bool:
        """Save to ``best`` if ``val_loss`` beats the kept best; returns whether it saved."""
        if not math.isfinite(val_loss):
            return False
        best = self.best_val_loss
        if best is not None and val_loss >= best:
            return False
        self.save_best(state, config, val_loss, log_window=log_window)
        return True

    def save_best(self, state, config: dict, val_loss: float, *,
                  log_window: dict | None = None) -> bool:
        """Save ``state`` to ``best`` as an improvement the caller has decided on (a save of the
        same step replaced; a kept later best at most ``val_loss`` stays); returns whether it
        saved."""
        step = int(state.step)
        kept_step, kept_loss = self._best.best_step(), self.best_val_loss
        if kept_step is not None and kept_step > step and kept_loss is not None \
                and kept_loss <= val_loss:
            return False
        meta = describe_state(state, config, log_window)
        if step in self._best.all_steps():
            self._best.delete(step)
        self._write(self._best, step, state, config, meta, metrics={"val_loss": val_loss})
        return True

    def latest_step(self) -> int | None:
        return self._last.latest_step()

    def best_step(self) -> int | None:
        return self._best.best_step()

    def close(self) -> None:
        self._last.close()
        self._best.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
