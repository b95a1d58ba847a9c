"""Reading checkpoints: find the saved steps, restore one and verify it. Needs no training code.

Layout of a checkpoint directory (written by :class:`flowmaps_jax.training.checkpoint.
CheckpointStore`; by default ``<run_dir>/checkpoints``)::

    <dir>/last/<step>/{state, config, meta}   the ``keep_last`` most recent saves
    <dir>/best/<step>/{state, config, meta}   the single save with the lowest validation loss

``state`` is the whole training state (step, params, EMA params, optimiser state, PRNG and data
keys), ``config`` the run's config as JSON, ``meta`` the SHA-256 of every array and of the config.

The read API is two functions: :func:`saved_steps` (which steps are saved, of one kind or all)
and :func:`restore` (one step, verified). Every restore recomputes the checksums and checks
finiteness; a missing, partial, altered or non-finite step raises ``ValueError`` naming it, and
names the newest intact step and how to load it. Steps written before checksums existed (no
``meta`` item) are checked for finiteness only. :func:`model_spec` reads the part of a stored
config that inference needs (the model family, its sizes, the simulator), so that
:func:`flowmaps_jax.predictor.load` restores a model without the training code (no optax).
"""

from __future__ import annotations

import hashlib
import json
import logging
import pathlib
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from flowmaps_jax.flowsim.config import FlowSimConfig
from flowmaps_jax.model.config import ModelConfig
from flowmaps_jax.model.families import model_family
from flowmaps_jax.model.family import ModelFamily
from flowmaps_jax.validation import check_choice, check_int, check_path

LATEST = "latest"
BEST = "best"
WHICH = (BEST, LATEST)
SUBDIRS = {LATEST: "last", BEST: "best"}
"""On disk the recent saves live in last/ (k of them), the best one in best/."""
ITEMS = ("state", "config", "meta")
# Files orbax (OCDBT format) always writes for a pytree item; checked before restoring.
_STATE_FILES = ("_METADATA", "manifest.ocdbt")
_STEP_METADATA = "_CHECKPOINT_METADATA"  # orbax's per-step file; lists the saved items

# orbax logs every save/restore at INFO through absl; keep the output readable.
logging.getLogger("absl").setLevel(logging.WARNING)


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
# Checksums and finiteness (the ``meta`` item)


def leaf_name(path) -> str:
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
        out.append((leaf_name(path), np.asarray(jax.device_get(leaf))))
    return out


def _digest(arr: np.ndarray) -> str:
    header = f"{arr.dtype.name}{arr.shape}".encode()
    return hashlib.sha256(header + np.ascontiguousarray(arr).tobytes()).hexdigest()


def config_checksum(config: dict) -> str:
    """SHA-256 of a JSON config dict (key order does not matter)."""
    return hashlib.sha256(json.dumps(config, sort_keys=True).encode()).hexdigest()


def name_list(names: list[str], limit: int = 3) -> str:
    """The first ``limit`` names, then how many more."""
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


def state_checksums(state) -> tuple[dict[str, str], list[str]]:
    """(SHA-256 of every array leaf of ``state`` by :func:`leaf_name`, ``name (k of n)`` of every
    floating leaf holding NaN or inf): what a save records and a restore checks."""
    leaves = _host_leaves(state)
    return {name: _digest(arr) for name, arr in leaves}, _non_finite(leaves)


def _verify(state, config: dict, meta: dict | None) -> None:
    """Raise _Damaged unless ``state``/``config`` match the checksums in ``meta`` and are finite."""
    got, bad = state_checksums(state)
    if meta is not None:
        expected = meta.get("checksums") if isinstance(meta, dict) else None
        if not isinstance(expected, dict):
            raise _Damaged("has an unreadable meta item (no checksums)")
        if set(got) != set(expected):
            raise _Damaged(f"does not match its checksums: arrays "
                           f"{name_list(sorted(set(got) ^ set(expected)))} differ in name")
        changed = [name for name in got if got[name] != expected[name]]
        if changed:
            raise _Damaged(f"fails its checksums: {len(changed)} of {len(got)} arrays differ "
                           f"from what was saved ({name_list(changed)})")
        if meta.get("config_sha256") != config_checksum(config):
            raise _Damaged("fails its checksums: the stored config differs from what was saved")
    if bad:
        raise _Damaged(f"holds NaN or inf values in {name_list(bad)}")


# --------------------------------------------------------------------------------------------
# Finding steps


def resolve_checkpoint_dir(directory: str | pathlib.Path) -> pathlib.Path:
    """The checkpoint root for ``directory``: the root itself or a run directory holding
    ``checkpoints/``. Raises ValueError if neither exists."""
    path = pathlib.Path(check_path("checkpoint_dir", directory)).absolute()
    if not path.exists():
        raise ValueError(f"checkpoint directory {path} does not exist")
    if not path.is_dir():
        raise ValueError(f"checkpoint path {path} is not a directory")
    last, best = SUBDIRS[LATEST], SUBDIRS[BEST]
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


def saved_copies(root: pathlib.Path) -> list[tuple[int, pathlib.Path]]:
    """Every saved (step, subdirectory) under the checkpoint root ``root``, newest step first,
    last/ before best/."""
    pairs = [(step, root / SUBDIRS[which]) for which in (LATEST, BEST)
             for step in _steps_in(root / SUBDIRS[which])]
    return sorted(pairs, key=lambda pair: -pair[0])


def _step_for(root: pathlib.Path, which: str) -> tuple[pathlib.Path, int]:
    sub = root / SUBDIRS[which]
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


def saved_steps(directory: str | pathlib.Path, which: str | None = None) -> list[int]:
    """The steps saved under ``directory`` (a checkpoint root or a run directory), ascending:
    every step (in last/ or best/) by default; with ``which`` ("latest" or "best") the one step
    a restore of that checkpoint reads, or [] if there is none."""
    root = resolve_checkpoint_dir(directory)
    if which is None:
        return sorted({step for step, _ in saved_copies(root)})
    which = check_choice("which", which, WHICH)
    try:
        return [_step_for(root, which)[1]]
    except ValueError:
        return []


# --------------------------------------------------------------------------------------------
# Restoring one step


def _saved_items(step_dir: pathlib.Path) -> list[str]:
    """The items orbax recorded for this step (``meta`` is absent from steps saved before
    checksums existed)."""
    try:
        handlers = json.loads((step_dir / _STEP_METADATA).read_text())["item_handlers"]
        return [item for item in ITEMS if item in handlers]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise _Damaged(f"is incomplete or corrupt: cannot read {_STEP_METADATA} "
                       f"({type(err).__name__})") from None


def _saved_structure(state_dir: pathlib.Path):
    """The saved state's structure, shapes and dtypes, placed on this process's first device:
    the restore target when the caller gives none (a checkpoint saved on N devices restores on
    one)."""
    metadata = ocp.StandardCheckpointHandler().metadata(state_dir)
    device = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    return jax.tree.map(lambda m: jax.ShapeDtypeStruct(m.shape, m.dtype, sharding=device),
                        metadata)


def _read_step(sub: pathlib.Path, step: int, target_state=None, *,
               with_state: bool = True) -> Restored:
    """Restore and verify one saved copy; raises _Damaged saying what is wrong."""
    step_dir = sub / str(step)
    items = _saved_items(step_dir)
    missing = [item for item in ITEMS if item not in items and item != "meta"]
    missing += [item for item in items if not (step_dir / item).is_dir()]
    missing += [f"state/{name}" for name in _STATE_FILES
                if "state" not in missing and not (step_dir / "state" / name).is_file()]
    if missing:
        raise _Damaged(f"is incomplete or corrupt: missing {missing}")
    args = {"config": ocp.args.JsonRestore()}
    if "meta" in items:
        args["meta"] = ocp.args.JsonRestore()
    manager = _reader(sub)
    try:
        if with_state:
            target = _saved_structure(step_dir / "state") if target_state is None \
                else target_state
            args["state"] = ocp.args.StandardRestore(target)
        restored = manager.restore(step, args=ocp.args.Composite(**args))
    except Exception as err:  # orbax/tensorstore raise many types; report them uniformly
        raise _Damaged(f"is corrupt, incomplete or does not match the model "
                       f"({type(err).__name__}: {shorten(err)})") from err
    finally:
        manager.close()
    config, meta = restored["config"], restored["meta"] if "meta" in items else None
    if not isinstance(config, dict):
        raise _Damaged("has no config")
    if with_state:
        _verify(restored["state"], config, meta)
    elif meta is not None and meta.get("config_sha256") != config_checksum(config):
        raise _Damaged("fails its checksums: the stored config differs from what was saved")
    return Restored(state=restored["state"] if with_state else None, config=config, meta=meta,
                    step=step, path=step_dir)


def _run_dir_of(root: pathlib.Path) -> pathlib.Path | None:
    if root.name == "checkpoints" or (root.parent / "config.json").is_file():
        return root.parent
    return None


def _intact_hint(root: pathlib.Path, target_state=None, skip=()) -> str:
    """A sentence naming the newest step with an intact copy (other than the copies ``skip``,
    as (step, subdirectory) pairs) and how to load it or resume from it."""
    for step, sub in saved_copies(root):
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
        except _Damaged as err:
            failures.append(f"checkpoint {sub / str(step)} {err}")
    raise ValueError(failures[0] + "." + _intact_hint(root, target_state, skip=copies))


def _select(root: pathlib.Path, which: str, step: int | None) -> list[tuple[int, pathlib.Path]]:
    """The saved copies that ``which``/``step`` designate (the same step may sit in last/ and
    best/)."""
    if step is None:
        sub, found = _step_for(root, which)
        return [(found, sub)]
    step = check_int("step", step, minimum=0)
    copies = [(s, sub) for s, sub in saved_copies(root) if s == step]
    if not copies:
        steps = sorted({s for s, _ in saved_copies(root)})
        raise ValueError(f"step {step} is not saved in {root} (saved steps: {steps})")
    return copies


def restore(directory: str | pathlib.Path, target_state=None, *, which: str = LATEST,
            step: int | None = None, with_state: bool = True) -> Restored:
    """The verified :class:`Restored` checkpoint ``which`` ("latest" or "best") under
    ``directory``, or the saved ``step`` (from last/ or best/) when given.

    target_state: a TrainState (or its ``jax.eval_shape``) giving the structure to restore into;
    None restores the saved structure as nested dicts of arrays on this process's first device.
    with_state=False reads and checks the config alone (``state`` is None). Raises
    ``ValueError`` for a missing, damaged or non-finite checkpoint, naming the newest intact
    step when there is one.
    """
    which = check_choice("which", which, WHICH)
    root = resolve_checkpoint_dir(directory)
    copies = _select(root, which, step)
    if with_state:
        return _restore_copies(root, copies, target_state)
    try:
        return _restore_copies(root, copies, None, with_state=False)
    except ValueError as err:
        raise ValueError(f"cannot read the config: {err}") from None


def shorten(err: Exception | str, limit: int = 400) -> str:
    """An error's text, cut to ``limit`` characters."""
    text = str(err)
    return text if len(text) <= limit else text[:limit] + " ..."


# --------------------------------------------------------------------------------------------
# The model a stored config describes


DEFAULT_FAMILY = "flowmaps"
"""The family of a stored config without ``model_kind`` (``TrainConfig``'s default)."""


class ModelSpec(NamedTuple):
    """The part of a stored run config that inference needs."""

    kind: str
    """The model family's name (``TrainConfig.model_kind``)."""
    model: ModelConfig
    flowsim: FlowSimConfig

    @property
    def family(self) -> ModelFamily:
        return model_family(self.kind)

    def abstract_params(self):
        """Structure, shapes and dtypes of the params this model initialises (nothing
        computed)."""
        return jax.eval_shape(lambda key: self.family.init(key, self.model), jax.random.key(0))


def model_spec(config: dict) -> ModelSpec:
    """The model family, model sizes and simulator of a stored run config (a checkpoint's
    ``config`` item or a shipped model's ``.json`` ``config``; ``TrainConfig.to_dict()``).
    Checks them, and that the model fits the simulator; the training fields are not read.
    Raises ``ValueError`` naming what is wrong."""
    if not isinstance(config, dict):
        raise ValueError(f"the config must be a dict; got {type(config).__name__}")
    kind = config.get("model_kind", DEFAULT_FAMILY)
    model_family(kind)  # ValueError listing the families
    model = ModelConfig.from_dict(config["model"]) if "model" in config else ModelConfig()
    flowsim = FlowSimConfig.from_dict(config["flowsim"]) if "flowsim" in config \
        else FlowSimConfig()
    if model.num_descriptors < flowsim.num_descriptors:
        raise ValueError(f"model.num_descriptors={model.num_descriptors} is smaller than the "
                         f"simulator's {flowsim.num_descriptors} descriptor ids")
    if model.tau_max != flowsim.num_timesteps:
        raise ValueError(f"model.tau_max={model.tau_max} must equal "
                         f"flowsim.num_timesteps={flowsim.num_timesteps}")
    return ModelSpec(kind=kind, model=model, flowsim=flowsim)


def check_params(params, spec: ModelSpec, where: str) -> None:
    """``ValueError`` unless ``params`` has the structure, shapes and dtypes that ``spec``'s
    family initialises (weights that do not fit their config)."""
    expected = spec.abstract_params()
    got_tree, want_tree = jax.tree.structure(params), jax.tree.structure(expected)
    if got_tree != want_tree:
        raise ValueError(f"{where} holds parameters of another structure than the "
                         f"{spec.kind!r} model its config describes")
    for (path, leaf), want in zip(jax.tree_util.tree_flatten_with_path(params)[0],
                                  jax.tree.leaves(expected), strict=True):
        if np.shape(leaf) != want.shape or leaf.dtype != want.dtype:
            raise ValueError(f"{where}: parameter {leaf_name(path)} is {np.shape(leaf)} "
                             f"{leaf.dtype}; the model its config describes has "
                             f"{want.shape} {want.dtype}")
