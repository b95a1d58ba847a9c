"""The orbax checkpoint directory of a run (``<dir>/last/<step>`` the ``keep_last`` recent
saves, ``<dir>/best/<step>`` the lowest validation loss; each {state, config, meta}): finding,
restoring, verifying and setting aside steps. A damaged step is a ValueError naming it and the
newest intact step (docs/guarantees.md)."""

from __future__ import annotations

import contextlib
import gc
import io
import logging
import os
import pathlib
import sys
import tempfile
import time
from typing import Any, NamedTuple

import jax
import orbax.checkpoint as ocp

from flowmaps_jax.atomic_files import check_tree_no_links
from flowmaps_jax.store.integrity import Damaged, shorten, verify, verify_config, verify_leaves
from flowmaps_jax.store.model_spec import ModelSpec, check_params, model_spec
from flowmaps_jax.store.packing import PACKED, host_arrays, unpack
from flowmaps_jax.untrusted_files import parse_json
from flowmaps_jax.validation import check_choice, check_dir, check_flag, check_int, prefix_errors

LATEST = "latest"
BEST = "best"
WHICH = (BEST, LATEST)
SUBDIRS = {LATEST: "last", BEST: "best"}
ITEMS = ("state", "config", "meta")
# Files orbax (OCDBT) always writes for a pytree item; each writing process also has
# ocdbt.process_<i>/d/.
_STATE_FILES = ("_METADATA", "manifest.ocdbt")
_STEP_METADATA = "_CHECKPOINT_METADATA"  # orbax's per-step file; lists the saved items

# orbax logs every save/restore at INFO through absl; keep the output readable.
logging.getLogger("absl").setLevel(logging.WARNING)


class Restored(NamedTuple):
    """A verified checkpoint: ``state``, ``config`` (dict), ``meta`` (dict or None), ``step`` and
    the step directory ``path``."""

    state: Any
    config: dict
    meta: dict | None
    step: int
    path: pathlib.Path


def last_manager(path: pathlib.Path, keep_last: int | None):
    """orbax manager of the recent saves in ``path``; ``keep_last=None`` opens an existing
    directory for reading."""
    writer = keep_last is not None
    options = ocp.CheckpointManagerOptions(
        max_to_keep=keep_last, enable_async_checkpointing=False, create=writer,
        cleanup_tmp_directories=writer)
    return ocp.CheckpointManager(path, options=options, item_names=ITEMS)


def best_manager(path: pathlib.Path, create: bool = True):
    """orbax manager keeping the single save with the lowest ``val_loss`` metric."""
    options = ocp.CheckpointManagerOptions(
        max_to_keep=1, best_fn=lambda metrics: metrics["val_loss"], best_mode="min",
        keep_checkpoints_without_metrics=False, enable_async_checkpointing=False, create=create,
        cleanup_tmp_directories=create)
    return ocp.CheckpointManager(path, options=options, item_names=ITEMS)


def _reader(sub: pathlib.Path):
    return best_manager(sub, create=False) if sub.name == SUBDIRS[BEST] else \
        last_manager(sub, None)


# --------------------------------------------------------------------------------------------
# Finding steps


def resolve_checkpoint_dir(directory: str | pathlib.Path) -> pathlib.Path:
    """The checkpoint root for ``directory`` (the root or a run directory holding
    ``checkpoints/``); ValueError if neither, or if anything in it is a symbolic link."""
    path = pathlib.Path(check_dir("checkpoint_dir", directory)).absolute()
    last, best = SUBDIRS[LATEST], SUBDIRS[BEST]
    if (path / "checkpoints").is_dir() and not (path / last).is_dir():
        path = path / "checkpoints"
    if not (path / last).is_dir() and not (path / best).is_dir():
        raise ValueError(f"{path} is not a checkpoint directory (expected {last}/ or {best}/ "
                         f"inside; was it written by python -m flowmaps_jax.train?)")
    check_tree_no_links("checkpoint directory file", path)
    return path


def _steps_in(sub: pathlib.Path) -> list[int]:
    """Finished steps in ``sub`` (orbax renames a save's temporary directory when it is done)."""
    if not sub.is_dir():
        return []
    return sorted(int(p.name) for p in sub.iterdir() if p.name.isdigit() and p.is_dir())


def saved_copies(root: pathlib.Path) -> list[tuple[int, pathlib.Path]]:
    """Every saved (step, subdirectory) under ``root``, newest first, last/ before best/."""
    pairs = [(step, root / SUBDIRS[which]) for which in (LATEST, BEST)
             for step in _steps_in(root / SUBDIRS[which])]
    return sorted(pairs, key=lambda pair: -pair[0])


def _step_for(root: pathlib.Path, which: str) -> tuple[pathlib.Path, int]:
    sub, step = root / SUBDIRS[which], None
    if sub.is_dir():
        manager = _reader(sub)
        try:
            step = manager.best_step() if which == BEST else manager.latest_step()
        finally:
            manager.close()
    if step is None:
        raise ValueError(f"no {which!r} checkpoint in {root} ({sub.name}/ is missing or holds "
                         f"no finished save)")
    return sub, step


def saved_steps(directory: str | pathlib.Path, which: str | None = None) -> list[int]:
    """The steps saved under ``directory``, ascending; with ``which`` the one step a restore of
    it reads ([] if none)."""
    if which is not None:
        check_choice("which", which, WHICH)
    root = resolve_checkpoint_dir(directory)
    if which is None:
        return sorted({step for step, _ in saved_copies(root)})
    try:
        return [_step_for(root, which)[1]]
    except ValueError:
        return []


# --------------------------------------------------------------------------------------------
# Restoring one step


def _saved_items(step_dir: pathlib.Path) -> list[str]:
    """The items orbax recorded for this step."""
    try:
        raw = (step_dir / _STEP_METADATA).read_bytes()
        handlers = parse_json(_STEP_METADATA, raw)["item_handlers"]
        return [item for item in ITEMS if item in handlers]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise Damaged(f"is incomplete or corrupt: cannot read {_STEP_METADATA} "
                      f"({type(err).__name__})") from None


def _missing_state_files(state_dir: pathlib.Path) -> list[str]:
    """The ``state/...`` files and folders orbax writes that a saved state lacks."""
    missing = [f"state/{name}" for name in _STATE_FILES if not (state_dir / name).is_file()]
    processes = state_dir / "array_metadatas"
    names = sorted(p.name for p in processes.iterdir()) if processes.is_dir() else []
    for name in names:
        if not name.startswith("process_"):
            continue
        data = state_dir / f"ocdbt.{name}" / "d"
        if not data.is_dir() or not any(data.iterdir()):
            missing.append(f"state/ocdbt.{name}" + ("/d" if data.parent.is_dir() else ""))
    if (state_dir / "d").exists() and not any((state_dir / "d").iterdir()):
        missing.append("state/d")
    return missing


@contextlib.contextmanager
def _silenced():
    """Hold back what orbax and tensorstore print (fd 2 and unraisable exceptions) while a step
    is read: shown again after a read that succeeded, dropped after one that failed. Any
    exception of the read (orbax and tensorstore raise many types) becomes one
    :class:`Damaged` that sums it up."""
    sys.stderr.flush()
    saved_fd, saved_hook, text = os.dup(2), sys.unraisablehook, io.StringIO()
    failed, failure = True, None
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        sys.unraisablehook = lambda _: None
        try:
            with contextlib.redirect_stderr(text):
                yield
            failed = False
        except Exception as err:
            failure = f"{type(err).__name__}: {_first_line(err)}"
        finally:
            if failed:  # its un-awaited coroutines report here, unheard, once the exception
                gc.collect()  # that held them is gone (a full collection: ~1 s on a big heap)
            sys.stderr.flush()
            os.dup2(saved_fd, 2)
            os.close(saved_fd)
            sys.unraisablehook = saved_hook
            if not failed:
                sink.seek(0)
                shown = sink.read().decode(errors="replace") + text.getvalue()
                if shown:
                    sys.stderr.write(shown)
    if failure is not None:
        raise Damaged(f"is corrupt, incomplete or does not match the model ({failure})")


def _saved_structure(state_dir: pathlib.Path):
    """The saved state's structure, shapes and dtypes on this process's first device."""
    metadata = ocp.StandardCheckpointHandler().metadata(state_dir)
    device = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    return jax.tree.map(lambda m: jax.ShapeDtypeStruct(m.shape, m.dtype, sharding=device),
                        metadata)


def _read_step(sub: pathlib.Path, step: int, target_state=None, *,
               with_state: bool = True) -> Restored:
    """Restore and verify one saved copy; raises Damaged saying what is wrong."""
    step_dir = sub / str(step)
    items = _saved_items(step_dir)
    missing = [item for item in ITEMS if item not in items and item != "meta"]
    missing += [item for item in items if not (step_dir / item).is_dir()]
    if "state" not in missing:
        missing += _missing_state_files(step_dir / "state")
    if missing:
        raise Damaged(f"is incomplete or corrupt: missing {missing}")
    args, packed = {"config": ocp.args.JsonRestore()}, False
    if "meta" in items:
        args["meta"] = ocp.args.JsonRestore()
    with _silenced():
        manager = _reader(sub)
        try:
            if with_state:  # a packed state (store.packing) is restored as saved
                stored = _saved_structure(step_dir / "state")
                packed = PACKED in stored
                args["state"] = ocp.args.StandardRestore(
                    stored if packed or target_state is None else target_state)
            restored = manager.restore(step, args=ocp.args.Composite(**args))
        finally:
            manager.close()
    config, meta = restored["config"], restored["meta"] if "meta" in items else None
    if not isinstance(config, dict):
        raise Damaged("has no config")
    if not with_state:
        verify_config(config, meta)
        return Restored(state=None, config=config, meta=meta, step=step, path=step_dir)
    state = restored["state"]
    if not packed:
        verify(state, config, meta)
        return Restored(state=state, config=config, meta=meta, step=step, path=step_dir)
    if not isinstance(meta, dict) or "layout" not in meta:
        raise Damaged("has a packed state but no layout in its meta item")
    arrays = host_arrays(state[PACKED], meta["layout"])
    state = unpack(arrays, target_state)
    verify_leaves(arrays, config, meta)  # the bytes as read, not a copy back from the devices
    return Restored(state=state, config=config, meta=meta, step=step, path=step_dir)


def _first_line(err: Exception) -> str:
    """The first line of an orbax or tensorstore error, short."""
    text = str(err).strip().splitlines()
    line = text[0] if text else ""
    line = line.split(" See full TensorStore details")[0]
    return shorten(line, 200)


def _run_dir_of(root: pathlib.Path) -> pathlib.Path | None:
    if root.name == "checkpoints" or (root.parent / "config.json").is_file():
        return root.parent
    return None


def _intact_hint(root: pathlib.Path, target_state=None, skip=()) -> str:
    """A sentence naming the newest intact step (not in ``skip``) and how to load or resume it."""
    for step, sub in saved_copies(root):
        if (step, sub) in skip:
            continue
        try:
            _read_step(sub, step, target_state)
        except Damaged:
            continue
        run_dir = _run_dir_of(root)
        train = "" if run_dir is None else (
            f", or continue training from it with python -m flowmaps_jax.train --resume "
            f"--run-dir {run_dir} --from-step {step}")
        return (f" The newest intact checkpoint is step {step} ({sub.name}/): load it with "
                f"flowmaps_jax.predictor.load({str(root)!r}, step={step}){train}.")
    return " No other saved step is intact."


def _restore_copies(root: pathlib.Path, copies: list[tuple[int, pathlib.Path]], target_state,
                    with_state: bool = True) -> Restored:
    """The first copy that restores and verifies; else ValueError naming the first failure and
    the newest intact step."""
    failures = []
    for step, sub in copies:
        try:
            return _read_step(sub, step, target_state, with_state=with_state)
        except Damaged as err:
            failures.append(f"checkpoint {sub / str(step)} {err}")
    raise ValueError(failures[0] + "." + _intact_hint(root, target_state, skip=copies))


def _select(root: pathlib.Path, which: str, step: int | None) -> list[tuple[int, pathlib.Path]]:
    """The saved copies (in last/ and best/) that ``which``/``step`` designate."""
    if step is None:
        sub, found = _step_for(root, which)
        return [(found, sub)]
    copies = [(s, sub) for s, sub in saved_copies(root) if s == step]
    if not copies:
        steps = sorted({s for s, _ in saved_copies(root)})
        raise ValueError(f"step {step} is not saved in {root} (saved steps: {steps})")
    return copies


def restore(directory: str | pathlib.Path, target_state=None, *, which: str = LATEST,
            step: int | None = None, with_state: bool = True) -> Restored:
    """The verified :class:`Restored` checkpoint ``which`` ("latest" or "best") under
    ``directory``, or the saved ``step``.

    target_state: the structure to restore into (a TrainState or its ``jax.eval_shape``; None:
    nested dicts on this process's first device). with_state=False reads the config alone.
    ValueError for a missing, damaged or non-finite checkpoint.
    """
    check_choice("which", which, WHICH)
    step = None if step is None else check_int("step", step, 0)
    root = resolve_checkpoint_dir(directory)
    copies = _select(root, which, step)
    if with_state:
        return _restore_copies(root, copies, target_state)
    with prefix_errors("cannot read the config: "):
        return _restore_copies(root, copies, None, with_state=False)


class Weights(NamedTuple):
    """A checkpoint's verified weights: ``params``, the model ``spec`` its config describes, the
    ``step``, the whole ``restored`` checkpoint and its checkpoint ``root``."""

    params: Any
    spec: ModelSpec
    step: int
    restored: Restored
    root: pathlib.Path


def _loadable(root: pathlib.Path, which: str, step: int | None) -> str:
    """``which``, or "latest" for "best" when no validation has run yet (nothing in best/)."""
    return LATEST if step is None and which == BEST and not saved_steps(root, which) else which


def stored_config(directory: str | pathlib.Path, which: str = BEST) -> dict:
    """The run config (dict) of the checkpoint :func:`load_weights` would load, without its
    state."""
    check_choice("which", which, WHICH)
    root = resolve_checkpoint_dir(directory)
    restored = _restore_copies(root, _select(root, _loadable(root, which, None), None), None,
                               with_state=False)
    return dict(restored.config)


def load_weights(directory: str | pathlib.Path, which: str = BEST, use_ema: bool = True,
                 step: int | None = None) -> Weights:
    """The weights (EMA with ``use_ema``) of the ``which`` checkpoint (or the saved ``step``),
    checked against their config's model; "best" falls back to the latest before any
    validation. ValueError for a missing, damaged or non-finite checkpoint."""
    check_choice("which", which, WHICH)
    use_ema = check_flag("use_ema", use_ema)
    step = None if step is None else check_int("step", step, 0)
    root = resolve_checkpoint_dir(directory)
    restored = _restore_copies(root, _select(root, _loadable(root, which, step), step), None)
    with prefix_errors(f"checkpoint {restored.path}: cannot read the config: ",
                       also=(TypeError,)):
        spec = model_spec(restored.config)
    params = restored.state["ema_params" if use_ema else "params"]
    check_params(params, spec, f"checkpoint {restored.path}")
    return Weights(params=params, spec=spec, step=int(restored.state["step"]),
                   restored=restored, root=root)


def set_aside(directory: str | pathlib.Path, after_step: int) -> tuple[pathlib.Path | None,
                                                                      list[int]]:
    """Move every saved step later than ``after_step`` into ``<root>/set-aside-<timestamp>/``.
    Returns (that folder or None, the moved steps)."""
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
