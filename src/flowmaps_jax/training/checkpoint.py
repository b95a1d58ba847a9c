"""Writing checkpoints with orbax: keep the last k and the best by validation loss.

Layout of a checkpoint directory (by default ``<run_dir>/checkpoints``)::

    <dir>/last/<step>/{state, config, meta}   the ``keep_last`` most recent saves
    <dir>/best/<step>/{state, config, meta}   the single save with the lowest validation loss

Two ``orbax.checkpoint.CheckpointManager`` instances do this: ``last`` keeps ``max_to_keep``
recent steps, ``best`` keeps one step chosen by ``best_fn`` (validation loss, mode ``min``). A
separate "best" manager means the best survives even when it falls out of the last k. Each save
holds the whole :class:`~flowmaps_jax.training.state.TrainState` (step, params, EMA params,
optimiser state, PRNG and data keys), the run's config as JSON, and a JSON ``meta`` item with
the SHA-256 of every array and of the config (plus the training loop's unlogged metrics window,
so that a resumed run logs the same records as a straight one). Saves are synchronous and
atomic: orbax writes the three items to a temporary directory and renames it when complete, so
an interrupted save never appears as a checkpoint.

Integrity. A state holding NaN or inf (params, EMA or optimiser state) is never saved
(:class:`NonFiniteStateError`). A failed write (e.g. a full disk) raises
:class:`CheckpointSaveError` with one short message; the partial save is removed.

Reading is :mod:`flowmaps_jax.checkpoint_reader` (no training code, so that inference can use
it): :func:`saved_steps` and :func:`restore`, re-exported here, verify every restore.
Restoring into a ``TrainState`` needs a target of the right structure
(``training.state.abstract_state(cfg)``); :func:`load_config` reads the stored config as a
:class:`~flowmaps_jax.training.config.TrainConfig`.
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
import time

import orbax.checkpoint as ocp

from flowmaps_jax.checkpoint_reader import (
    BEST,
    LATEST,
    SUBDIRS,
    WHICH,
    Restored,
    best_manager,
    config_checksum,
    last_manager,
    name_list,
    resolve_checkpoint_dir,
    restore,
    saved_copies,
    saved_steps,
    shorten,
    state_checksums,
)
from flowmaps_jax.training.config import TrainConfig
from flowmaps_jax.validation import check_int

__all__ = ["BEST", "LATEST", "WHICH", "CheckpointSaveError", "CheckpointStore",
           "NonFiniteStateError", "Restored", "describe_state", "load_config",
           "resolve_checkpoint_dir", "restore", "saved_steps", "set_aside"]

META_FORMAT = 1


class NonFiniteStateError(ValueError):
    """A state with NaN or inf in its params, EMA params or optimiser state was not saved."""


class CheckpointSaveError(OSError):
    """Writing a checkpoint failed (e.g. no space left on device); the message is one line."""

    def __str__(self) -> str:
        return str(self.strerror)


def describe_state(state, config: dict, log_window: dict | None = None) -> dict:
    """The ``meta`` item of a save: SHA-256 of every array leaf and of ``config``, plus the
    loop's ``log_window``. Raises :class:`NonFiniteStateError` if a float leaf is NaN or inf."""
    checksums, bad = state_checksums(state)
    if bad:
        raise NonFiniteStateError(
            f"refusing to save step {int(state.step)}: the state holds NaN or inf values in "
            f"{name_list(bad)}")
    return {"format": META_FORMAT, "checksums": checksums,
            "config_sha256": config_checksum(config), "log_window": log_window}


# --------------------------------------------------------------------------------------------
# Saving


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
    """Writes checkpoints of one run: ``save`` (last k) and ``save_if_best`` (best by val loss).

    directory: checkpoint root (created if needed); keep_last: recent checkpoints kept (k >= 1).
    Both saves raise :class:`NonFiniteStateError` (nothing written) for a state holding NaN or
    inf, and :class:`CheckpointSaveError` when the write fails (the partial save is removed).
    """

    def __init__(self, directory: str | pathlib.Path, keep_last: int = 2):
        keep_last = check_int("keep_last", keep_last)
        self.directory = pathlib.Path(directory).absolute()
        self.directory.mkdir(parents=True, exist_ok=True)
        self._last = last_manager(self.directory / SUBDIRS[LATEST], keep_last)
        self._best = best_manager(self.directory / SUBDIRS[BEST])

    def _write(self, manager, step: int, state, config: dict, meta: dict, **kwargs) -> None:
        sub = self.directory / pathlib.Path(str(manager.directory)).name
        args = ocp.args.Composite(state=ocp.args.StandardSave(state),
                                  config=ocp.args.JsonSave(config), meta=ocp.args.JsonSave(meta))
        try:
            with _quiet():
                manager.save(step, args=args, force=True, **kwargs)
                manager.wait_until_finished()
        except Exception as err:  # orbax/tensorstore raise many types; report them uniformly
            for partial in sub.glob(f"{step}.orbax-checkpoint-tmp*"):
                shutil.rmtree(partial, ignore_errors=True)
            raise _save_error(err, step, sub) from err

    def save(self, state, config: dict, *, log_window: dict | None = None) -> int:
        """Save ``state`` (a TrainState) and ``config`` (JSON dict) under its step; returns the
        step. Saving a step that is already saved is a no-op. ``log_window``: JSON data the
        training loop needs to resume its metrics window exactly (kept in ``meta``)."""
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
        """Save ``state`` to ``best`` as an improvement the caller has decided on (a resumed run
        replaying steps before a best its first run saved: the same save comes again later), a
        save of the same step replaced. A kept best of a later step with a val loss at most
        ``val_loss`` stays, as orbax's best-of-one would keep it (nothing is written); returns
        whether it saved."""
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


# --------------------------------------------------------------------------------------------
# Reading back (the rest is flowmaps_jax.checkpoint_reader)


def load_config(directory: str | pathlib.Path, which: str = LATEST,
                step: int | None = None) -> TrainConfig:
    """The :class:`~flowmaps_jax.training.config.TrainConfig` stored with the ``which``
    checkpoint ("latest" or "best"), or with the saved ``step`` when given."""
    return TrainConfig.from_dict(restore(directory, which=which, step=step,
                                         with_state=False).config)


def set_aside(directory: str | pathlib.Path, after_step: int) -> tuple[pathlib.Path | None,
                                                                      list[int]]:
    """Move every saved step later than ``after_step`` (in last/ and best/) into
    ``<root>/set-aside-<timestamp>/``, so that a run resumed from ``after_step`` writes its own
    later steps. Returns (that folder or None if nothing moved, the moved steps)."""
    root = resolve_checkpoint_dir(directory)
    later = [(step, sub) for step, sub in saved_copies(root) if step > after_step]
    if not later:
        return None, []
    dest = root / f"set-aside-{time.strftime('%Y%m%d-%H%M%S')}"
    while dest.exists():
        dest = dest.with_name(dest.name + "x")
    for step, sub in later:
        (dest / sub.name).mkdir(parents=True, exist_ok=True)
        (sub / str(step)).rename(dest / sub.name / str(step))
    return dest, sorted({step for step, _ in later})
