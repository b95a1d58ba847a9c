"""Checkpoints with orbax: keep the last k and the best by validation loss; verified restores.

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
(:class:`NonFiniteStateError`). Every restore recomputes the checksums and checks finiteness; a
missing, partial, altered or non-finite step raises ``ValueError`` naming it, and names the
newest intact step and how to load it (``restore(dir, step=N)``, ``sample.load(dir, step=N)``,
``python -m flowmaps_jax.train --resume --from-step N``). Steps written before checksums existed
(no ``meta`` item) are checked for finiteness only. A failed write (e.g. a full disk) raises
:class:`CheckpointSaveError` with one short message; the partial save is removed.

Restoring needs a target state with the right structure (``training.state.abstract_state(cfg)``;
``load_config`` reads the config stored in the checkpoint).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import io
import json
import logging
import math
import pathlib
import shutil
import sys
import time
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from flowmaps_jax.training.config import TrainConfig
from flowmaps_jax.validation import check_choice, check_int, check_path

LATEST = "latest"
BEST = "best"
WHICH = (BEST, LATEST)
# On disk the recent saves live in last/ (k of them), the best one in best/.
_SUBDIR = {LATEST: "last", BEST: "best"}
_ITEMS = ("state", "config", "meta")
# Files orbax (OCDBT format) always writes for a pytree item; checked before restoring.
_STATE_FILES = ("_METADATA", "manifest.ocdbt")
_STEP_METADATA = "_CHECKPOINT_METADATA"  # orbax's per-step file; lists the saved items
META_FORMAT = 1

# orbax logs every save/restore at INFO through absl; keep training output readable.
logging.getLogger("absl").setLevel(logging.WARNING)


class NonFiniteStateError(ValueError):
    """A state with NaN or inf in its params, EMA params or optimiser state was not saved."""


class CheckpointSaveError(OSError):
    """Writing a checkpoint failed (e.g. no space left on device); the message is one line."""

    def __str__(self) -> str:
        return str(self.strerror)


class Restored(NamedTuple):
    """A verified checkpoint: ``state``, ``config`` (dict), ``meta`` (dict, None for steps saved
    before checksums existed), ``step`` and the step directory ``path``."""

    state: Any
    config: dict
    meta: dict | None
    step: int
    path: pathlib.Path


class _Damaged(ValueError):
    """One saved copy of a step failed to restore or verify (internal)."""


def _last_manager(path: pathlib.Path, keep_last: int | None):
    """Manager of recent saves; ``keep_last=None`` opens an existing directory for reading."""
    writer = keep_last is not None
    options = ocp.CheckpointManagerOptions(
        max_to_keep=keep_last, enable_async_checkpointing=False, create=writer,
        cleanup_tmp_directories=writer)
    return ocp.CheckpointManager(path, options=options, item_names=_ITEMS)


def _best_manager(path: pathlib.Path, create: bool = True):
    """Manager keeping the single save with the lowest ``val_loss`` metric."""
    options = ocp.CheckpointManagerOptions(
        max_to_keep=1, best_fn=lambda metrics: metrics["val_loss"], best_mode="min",
        keep_checkpoints_without_metrics=False, enable_async_checkpointing=False, create=create,
        cleanup_tmp_directories=create)
    return ocp.CheckpointManager(path, options=options, item_names=_ITEMS)


def _reader(sub: pathlib.Path):
    return _best_manager(sub, create=False) if sub.name == _SUBDIR[BEST] else \
        _last_manager(sub, None)


# --------------------------------------------------------------------------------------------
# Checksums and finiteness


def _leaf_name(path) -> str:
    """``params/encoder/kernel`` for a key path, the same for a TrainState and its raw restore."""
    parts = []
    for entry in path:
        for attr in ("name", "key", "idx"):
            if hasattr(entry, attr):
                parts.append(str(getattr(entry, attr)))
                break
    return "/".join(parts)


def _host_leaves(tree) -> list[tuple[str, np.ndarray]]:
    out = []
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        if jnp.issubdtype(getattr(leaf, "dtype", np.float32), jax.dtypes.prng_key):
            leaf = jax.random.key_data(leaf)
        out.append((_leaf_name(path), np.asarray(jax.device_get(leaf))))
    return out


def _digest(arr: np.ndarray) -> str:
    header = f"{arr.dtype.name}{arr.shape}".encode()
    return hashlib.sha256(header + np.ascontiguousarray(arr).tobytes()).hexdigest()


def _config_digest(config: dict) -> str:
    return hashlib.sha256(json.dumps(config, sort_keys=True).encode()).hexdigest()


def _names(names: list[str], limit: int = 3) -> str:
    more = f" and {len(names) - limit} more" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


def _non_finite(leaves: list[tuple[str, np.ndarray]]) -> list[str]:
    """``name (k of n)`` for every floating leaf holding NaN or inf."""
    bad = []
    for name, arr in leaves:
        if jnp.issubdtype(arr.dtype, jnp.inexact):
            count = arr.size - int(np.count_nonzero(np.isfinite(arr)))
            if count:
                bad.append(f"{name} ({count} of {arr.size})")
    return bad


def describe_state(state, config: dict, log_window: dict | None = None) -> dict:
    """The ``meta`` item of a save: SHA-256 of every array leaf and of ``config``, plus the
    loop's ``log_window``. Raises :class:`NonFiniteStateError` if a float leaf is NaN or inf."""
    leaves = _host_leaves(state)
    bad = _non_finite(leaves)
    if bad:
        raise NonFiniteStateError(
            f"refusing to save step {int(state.step)}: the state holds NaN or inf values in "
            f"{_names(bad)}")
    return {"format": META_FORMAT, "checksums": {name: _digest(arr) for name, arr in leaves},
            "config_sha256": _config_digest(config), "log_window": log_window}


def _verify(state, config: dict, meta: dict | None) -> None:
    """Raise _Damaged unless ``state``/``config`` match the checksums in ``meta`` and are finite."""
    leaves = _host_leaves(state)
    if meta is not None:
        expected = meta.get("checksums") if isinstance(meta, dict) else None
        if not isinstance(expected, dict):
            raise _Damaged("has an unreadable meta item (no checksums)")
        got = {name: _digest(arr) for name, arr in leaves}
        if set(got) != set(expected):
            raise _Damaged(f"does not match its checksums: arrays "
                           f"{_names(sorted(set(got) ^ set(expected)))} differ in name")
        changed = [name for name in got if got[name] != expected[name]]
        if changed:
            raise _Damaged(f"fails its checksums: {len(changed)} of {len(got)} arrays differ "
                           f"from what was saved ({_names(changed)})")
        if meta.get("config_sha256") != _config_digest(config):
            raise _Damaged("fails its checksums: the stored config differs from what was saved")
    bad = _non_finite(leaves)
    if bad:
        raise _Damaged(f"holds NaN or inf values in {_names(bad)}")


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
        reason = f"{type(err).__name__}: {_short(text.splitlines()[0] if text else '', 300)}"
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
        self._last = _last_manager(self.directory / _SUBDIR[LATEST], keep_last)
        self._best = _best_manager(self.directory / _SUBDIR[BEST])

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
        meta = describe_state(state, config, log_window)
        step = int(state.step)
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
# Finding and restoring steps


def resolve_checkpoint_dir(directory: str | pathlib.Path) -> pathlib.Path:
    """The checkpoint root for ``directory``: the root itself or a run directory holding
    ``checkpoints/``. Raises ValueError if neither exists."""
    path = pathlib.Path(check_path("checkpoint_dir", directory)).absolute()
    if not path.exists():
        raise ValueError(f"checkpoint directory {path} does not exist")
    if not path.is_dir():
        raise ValueError(f"checkpoint path {path} is not a directory")
    last, best = _SUBDIR[LATEST], _SUBDIR[BEST]
    if (path / "checkpoints").is_dir() and not (path / last).is_dir():
        path = path / "checkpoints"
    if not (path / last).is_dir() and not (path / best).is_dir():
        raise ValueError(f"{path} is not a checkpoint directory (expected {last}/ or {best}/ "
                         f"inside; was it written by python -m flowmaps_jax.train?)")
    return path


def _steps_in(sub: pathlib.Path) -> list[int]:
    """Finished steps in ``sub`` (orbax renames a save's temporary directory when it is done)."""
    if not sub.is_dir():
        return []
    return sorted(int(p.name) for p in sub.iterdir() if p.name.isdigit() and p.is_dir())


def _copies(root: pathlib.Path) -> list[tuple[int, pathlib.Path]]:
    """Every saved (step, subdirectory), newest step first, last/ before best/."""
    pairs = [(step, root / _SUBDIR[which]) for which in (LATEST, BEST)
             for step in _steps_in(root / _SUBDIR[which])]
    return sorted(pairs, key=lambda pair: -pair[0])


def _step_for(root: pathlib.Path, which: str) -> tuple[pathlib.Path, int]:
    sub = root / _SUBDIR[which]
    if not sub.is_dir():
        raise ValueError(f"no {which!r} checkpoint in {root} ({sub} does not exist)")
    manager = _reader(sub)
    try:
        step = manager.best_step() if which == BEST else manager.latest_step()
    finally:
        manager.close()
    if step is None:
        raise ValueError(f"no {which!r} checkpoint in {sub} (the directory holds no finished "
                         f"save)")
    return sub, step


def saved_step(directory: str | pathlib.Path, which: str) -> int | None:
    """Step of the ``which`` ("latest" or "best") checkpoint under ``directory``; None if none."""
    try:
        return _step_for(resolve_checkpoint_dir(directory), which)[1]
    except ValueError:
        return None


def saved_steps(directory: str | pathlib.Path) -> list[int]:
    """Every step saved under ``directory`` (in last/ or best/), ascending."""
    return sorted({step for step, _ in _copies(resolve_checkpoint_dir(directory))})


def _saved_items(step_dir: pathlib.Path) -> list[str]:
    """The items orbax recorded for this step (``meta`` is absent from steps saved before
    checksums existed)."""
    try:
        handlers = json.loads((step_dir / _STEP_METADATA).read_text())["item_handlers"]
        return [item for item in _ITEMS if item in handlers]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise _Damaged(f"is incomplete or corrupt: cannot read {_STEP_METADATA} "
                       f"({type(err).__name__})") from None


def _read_step(sub: pathlib.Path, step: int, target_state=None, *,
               with_state: bool = True) -> Restored:
    """Restore and verify one saved copy; raises _Damaged saying what is wrong."""
    step_dir = sub / str(step)
    items = _saved_items(step_dir)
    missing = [item for item in _ITEMS if item not in items and item != "meta"]
    missing += [item for item in items if not (step_dir / item).is_dir()]
    missing += [f"state/{name}" for name in _STATE_FILES
                if "state" not in missing and not (step_dir / "state" / name).is_file()]
    if missing:
        raise _Damaged(f"is incomplete or corrupt: missing {missing}")
    args = {"config": ocp.args.JsonRestore()}
    if "meta" in items:
        args["meta"] = ocp.args.JsonRestore()
    if with_state:
        args["state"] = ocp.args.StandardRestore(target_state) if target_state is not None \
            else ocp.args.StandardRestore()
    manager = _reader(sub)
    try:
        restored = manager.restore(step, args=ocp.args.Composite(**args))
    except Exception as err:  # orbax/tensorstore raise many types; report them uniformly
        raise _Damaged(f"is corrupt, incomplete or does not match the model "
                       f"({type(err).__name__}: {_short(err)})") from err
    finally:
        manager.close()
    config, meta = restored["config"], restored["meta"] if "meta" in items else None
    if not isinstance(config, dict):
        raise _Damaged("has no config")
    if with_state:
        _verify(restored["state"], config, meta)
    elif meta is not None and meta.get("config_sha256") != _config_digest(config):
        raise _Damaged("fails its checksums: the stored config differs from what was saved")
    return Restored(state=restored["state"] if with_state else None, config=config, meta=meta,
                    step=step, path=step_dir)


def _run_dir_of(root: pathlib.Path) -> pathlib.Path | None:
    if root.name == "checkpoints" or (root.parent / "config.json").is_file():
        return root.parent
    return None


def intact_hint(root: pathlib.Path, target_state=None, skip=()) -> str:
    """A sentence naming the newest step with an intact copy (other than the copies ``skip``,
    as (step, subdirectory) pairs) and how to load it or resume from it."""
    for step, sub in _copies(root):
        if (step, sub) in skip:
            continue
        try:
            _read_step(sub, step, target_state)
        except _Damaged:
            continue
        run_dir = _run_dir_of(root)
        train = "" if run_dir is None else (
            f", or continue training from it with python -m flowmaps_jax.train --resume "
            f"--run-dir {run_dir} --from-step {step}")
        return (f" The newest intact checkpoint is step {step} ({sub.name}/): load it with "
                f"flowmaps_jax.sample.load({str(root)!r}, step={step}){train}.")
    return " No other saved step is intact."


def _restore_copies(root: pathlib.Path, copies: list[tuple[int, pathlib.Path]], target_state,
                    with_state: bool = True) -> Restored:
    """The first copy that restores and verifies; else ValueError naming the first failure and
    the newest intact step."""
    failures = []
    for step, sub in copies:
        try:
            return _read_step(sub, step, target_state, with_state=with_state)
        except _Damaged as err:
            failures.append(f"checkpoint {sub / str(step)} {err}")
    raise ValueError(failures[0] + "." + intact_hint(root, target_state, skip=copies))


def _select(root: pathlib.Path, which: str, step: int | None) -> list[tuple[int, pathlib.Path]]:
    """The saved copies that ``which``/``step`` designate (the same step may sit in last/ and
    best/)."""
    if step is None:
        sub, found = _step_for(root, check_choice("which", which, WHICH))
        return [(found, sub)]
    step = check_int("step", step, minimum=0)
    copies = [(s, sub) for s, sub in _copies(root) if s == step]
    if not copies:
        steps = sorted({s for s, _ in _copies(root)})
        raise ValueError(f"step {step} is not saved in {root} (saved steps: {steps})")
    return copies


def restore(directory: str | pathlib.Path, target_state=None, *, which: str = LATEST,
            step: int | None = None) -> Restored:
    """The verified :class:`Restored` checkpoint ``which`` ("latest" or "best") under
    ``directory``, or the saved ``step`` (from last/ or best/) when given.

    target_state: a TrainState (or its ``jax.eval_shape``) giving the structure to restore into;
    None restores a raw pytree of arrays. Raises ``ValueError`` for a missing, damaged or
    non-finite checkpoint, naming the newest intact step when there is one.
    """
    root = resolve_checkpoint_dir(directory)
    return _restore_copies(root, _select(root, which, step), target_state)


def restore_latest(directory: str | pathlib.Path, target_state=None) -> tuple[Any, dict]:
    """(state, config dict) of the most recent checkpoint under ``directory`` (see
    :func:`restore`)."""
    restored = restore(directory, target_state, which=LATEST)
    return restored.state, restored.config


def restore_best(directory: str | pathlib.Path, target_state=None) -> tuple[Any, dict]:
    """(state, config dict) of the checkpoint with the lowest validation loss."""
    restored = restore(directory, target_state, which=BEST)
    return restored.state, restored.config


def load_config(directory: str | pathlib.Path, which: str = LATEST,
                step: int | None = None) -> TrainConfig:
    """The :class:`~flowmaps_jax.training.config.TrainConfig` stored with the ``which``
    checkpoint ("latest" or "best"), or with the saved ``step`` when given."""
    which = check_choice("which", which, WHICH)
    root = resolve_checkpoint_dir(directory)
    copies = _select(root, which, step)
    try:
        restored = _restore_copies(root, copies, None, with_state=False)
    except ValueError as err:
        raise ValueError(f"cannot read the config: {err}") from None
    return TrainConfig.from_dict(restored.config)


def set_aside(directory: str | pathlib.Path, after_step: int) -> tuple[pathlib.Path | None,
                                                                      list[int]]:
    """Move every saved step later than ``after_step`` (in last/ and best/) into
    ``<root>/set-aside-<timestamp>/``, so that a run resumed from ``after_step`` writes its own
    later steps. Returns (that folder or None if nothing moved, the moved steps)."""
    root = resolve_checkpoint_dir(directory)
    later = [(step, sub) for step, sub in _copies(root) if step > after_step]
    if not later:
        return None, []
    dest = root / f"set-aside-{time.strftime('%Y%m%d-%H%M%S')}"
    while dest.exists():
        dest = dest.with_name(dest.name + "x")
    for step, sub in later:
        (dest / sub.name).mkdir(parents=True, exist_ok=True)
        (sub / str(step)).rename(dest / sub.name / str(step))
    return dest, sorted({step for step, _ in later})


def _short(err: Exception | str, limit: int = 400) -> str:
    text = str(err)
    return text if len(text) <= limit else text[:limit] + " ..."
