"""Checkpoints with orbax: keep the last k and the best by validation loss; clear errors.

Layout of a checkpoint directory (by default ``<run_dir>/checkpoints``)::

    <dir>/last/<step>/{state, config}   the ``keep_last`` most recent saves
    <dir>/best/<step>/{state, config}   the single save with the lowest validation loss so far

Two ``orbax.checkpoint.CheckpointManager`` instances do this: ``last`` keeps ``max_to_keep``
recent steps, ``best`` keeps one step chosen by ``best_fn`` (validation loss, mode ``min``). A
separate "best" manager means the best survives even when it falls out of the last k. Each save
holds the whole :class:`~flowmaps_jax.training.TrainState` (step, params, EMA params, optimiser
state, PRNG and data keys) plus the run's config as JSON. Saves are synchronous and atomic: orbax
writes to a temporary directory and renames it when complete, so an interrupted save never
appears as a checkpoint.

Restoring needs a target state with the right structure (``training.abstract_state(cfg)``;
``load_config`` reads the config stored in the checkpoint). A missing, empty, partial or corrupt
directory raises ``ValueError`` naming the path.
"""

from __future__ import annotations

import logging
import math
import pathlib
from typing import Any

import orbax.checkpoint as ocp

from flowmaps_jax.validation import check_int

LAST = "last"
BEST = "best"
_ITEMS = ("state", "config")
# Files orbax (OCDBT format) always writes for a pytree item; checked before restoring.
_STATE_FILES = ("_METADATA", "manifest.ocdbt")

# orbax logs every save/restore at INFO through absl; keep training output readable.
logging.getLogger("absl").setLevel(logging.WARNING)


def _last_manager(path: pathlib.Path, keep_last: int | None):
    """Manager of recent saves; ``keep_last=None`` opens an existing directory for reading."""
    options = ocp.CheckpointManagerOptions(
        max_to_keep=keep_last, enable_async_checkpointing=False, create=keep_last is not None)
    return ocp.CheckpointManager(path, options=options, item_names=_ITEMS)


def _best_manager(path: pathlib.Path, create: bool = True):
    """Manager keeping the single save with the lowest ``val_loss`` metric."""
    options = ocp.CheckpointManagerOptions(
        max_to_keep=1, best_fn=lambda metrics: metrics["val_loss"], best_mode="min",
        keep_checkpoints_without_metrics=False, enable_async_checkpointing=False, create=create)
    return ocp.CheckpointManager(path, options=options, item_names=_ITEMS)


def _reader(sub: pathlib.Path, which: str):
    return _best_manager(sub, create=False) if which == BEST else _last_manager(sub, None)


def _save_args(state, config: dict):
    return ocp.args.Composite(state=ocp.args.StandardSave(state),
                              config=ocp.args.JsonSave(config))


class CheckpointStore:
    """Writes checkpoints of one run: ``save`` (last k) and ``save_if_best`` (best by val loss).

    directory: checkpoint root (created if needed); keep_last: recent checkpoints kept (k >= 1).
    """

    def __init__(self, directory: str | pathlib.Path, keep_last: int = 2):
        keep_last = check_int("keep_last", keep_last)
        self.directory = pathlib.Path(directory).absolute()
        self.directory.mkdir(parents=True, exist_ok=True)
        self._last = _last_manager(self.directory / LAST, keep_last)
        self._best = _best_manager(self.directory / BEST)

    def save(self, state, config: dict) -> int:
        """Save ``state`` (a TrainState) and ``config`` (JSON dict) under its step; returns the
        step. Saving a step that is already saved is a no-op."""
        step = int(state.step)
        if step not in self._last.all_steps():
            self._last.save(step, args=_save_args(state, config), force=True)
            self._last.wait_until_finished()
        return step

    @property
    def best_val_loss(self) -> float | None:
        """Validation loss of the kept best checkpoint (None if there is none)."""
        step = self._best.best_step()
        if step is None:
            return None
        metrics = self._best.metrics(step)
        return None if metrics is None else float(metrics["val_loss"])

    def save_if_best(self, state, config: dict, val_loss: float) -> bool:
        """Save to ``best`` if ``val_loss`` beats the kept best; returns whether it saved."""
        if not math.isfinite(val_loss):
            return False
        best = self.best_val_loss
        if best is not None and val_loss >= best:
            return False
        step = int(state.step)
        if step in self._best.all_steps():
            self._best.delete(step)
        self._best.save(step, args=_save_args(state, config), metrics={"val_loss": val_loss},
                        force=True)
        self._best.wait_until_finished()
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
# Restoring


def resolve_checkpoint_dir(directory: str | pathlib.Path) -> pathlib.Path:
    """The checkpoint root for ``directory``: the root itself or a run directory holding
    ``checkpoints/``. Raises ValueError if neither exists."""
    path = pathlib.Path(directory).absolute()
    if not path.exists():
        raise ValueError(f"checkpoint directory {path} does not exist")
    if not path.is_dir():
        raise ValueError(f"checkpoint path {path} is not a directory")
    if (path / "checkpoints").is_dir() and not (path / LAST).is_dir():
        path = path / "checkpoints"
    if not (path / LAST).is_dir() and not (path / BEST).is_dir():
        raise ValueError(f"{path} is not a checkpoint directory (expected {LAST}/ or {BEST}/ "
                         f"inside; was it written by flowmaps_jax.train?)")
    return path


def _step_for(root: pathlib.Path, which: str) -> tuple[pathlib.Path, int]:
    sub = root / which
    if not sub.is_dir():
        raise ValueError(f"no {which!r} checkpoint in {root} ({sub} does not exist)")
    manager = _reader(sub, which)
    try:
        step = manager.best_step() if which == BEST else manager.latest_step()
    finally:
        manager.close()
    if step is None:
        raise ValueError(f"no {which!r} checkpoint in {sub} (the directory holds no finished "
                         f"save)")
    return sub, step


def _restore(directory, which: str, target_state) -> tuple[Any, dict]:
    root = resolve_checkpoint_dir(directory)
    sub, step = _step_for(root, which)
    step_dir = sub / str(step)
    missing = [item for item in _ITEMS if not (step_dir / item).is_dir()]
    missing += [f"state/{name}" for name in _STATE_FILES
                if "state" not in missing and not (step_dir / "state" / name).is_file()]
    if missing:
        raise ValueError(f"checkpoint {step_dir} is incomplete or corrupt: missing {missing}")
    manager = _reader(sub, which)
    try:
        if target_state is None:
            state_args = ocp.args.StandardRestore()
        else:
            state_args = ocp.args.StandardRestore(target_state)
        restored = manager.restore(step, args=ocp.args.Composite(
            state=state_args, config=ocp.args.JsonRestore()))
    except Exception as err:  # orbax/tensorstore raise many types; report them uniformly
        raise ValueError(f"checkpoint {step_dir} is corrupt, incomplete or does not match the "
                         f"model ({type(err).__name__}: {_short(err)})") from err
    finally:
        manager.close()
    if restored.config is None:
        raise ValueError(f"checkpoint {step_dir} has no config")
    return restored.state, restored.config


def restore_latest(directory: str | pathlib.Path, target_state=None) -> tuple[Any, dict]:
    """(state, config dict) of the most recent checkpoint under ``directory``.

    target_state: a TrainState (or its ``jax.eval_shape``) giving the structure to restore into;
    None restores a raw pytree of arrays.
    """
    return _restore(directory, LAST, target_state)


def restore_best(directory: str | pathlib.Path, target_state=None) -> tuple[Any, dict]:
    """(state, config dict) of the checkpoint with the lowest validation loss."""
    return _restore(directory, BEST, target_state)


def load_config(directory: str | pathlib.Path, which: str = LAST):
    """The :class:`~flowmaps_jax.config.TrainConfig` stored with the ``which`` checkpoint
    ("last" or "best")."""
    from flowmaps_jax.config import TrainConfig

    if which not in (LAST, BEST):
        raise ValueError(f"which must be {LAST!r} or {BEST!r}; got {which!r}")
    root = resolve_checkpoint_dir(directory)
    sub, step = _step_for(root, which)
    manager = _reader(sub, which)
    try:
        restored = manager.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore()))
    except Exception as err:
        raise ValueError(f"cannot read the config of checkpoint {sub / str(step)} "
                         f"({type(err).__name__}: {_short(err)})") from err
    finally:
        manager.close()
    return TrainConfig.from_dict(restored.config)


def load_for_inference(directory: str | pathlib.Path, which: str = BEST, ema: bool = True):
    """(params, TrainConfig) for sampling/evaluation: EMA params (default) of the best checkpoint,
    or of the latest when no validation has been run yet."""
    from flowmaps_jax.training import abstract_state

    root = resolve_checkpoint_dir(directory)
    if which == BEST and _best_step_or_none(root) is None:
        which = LAST
    cfg = load_config(root, which)
    state, _ = _restore(root, which, abstract_state(cfg))
    return (state.ema_params if ema else state.params), cfg


def _best_step_or_none(root: pathlib.Path) -> int | None:
    try:
        return _step_for(root, BEST)[1]
    except ValueError:
        return None


def _short(err: Exception, limit: int = 400) -> str:
    text = str(err)
    return text if len(text) <= limit else text[:limit] + " ..."
