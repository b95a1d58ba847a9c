"""Resume policy: which checkpoint ``--resume`` continues and with which config
(:func:`load_config`, :func:`check_resumable`: only ``resumable_fields`` may change,
:func:`restore_for_resume`: None for a run that saved nothing yet, :func:`resume_config`).
Reading and verifying checkpoints is :mod:`flowmaps_jax.store.checkpoints`.
"""

from __future__ import annotations

import dataclasses
import pathlib
from collections.abc import Callable

from flowmaps_jax.store import checkpoints, rundir
from flowmaps_jax.training import state as train_state
from flowmaps_jax.training.config import TrainConfig, config_from_stored, resumable_fields
from flowmaps_jax.training.overrides import flatten
from flowmaps_jax.untrusted_files import read_json


def load_config(directory: str | pathlib.Path, which: str = checkpoints.LATEST,
                step: int | None = None) -> TrainConfig:
    """The run config (a :class:`~flowmaps_jax.training.config.TrainConfig` or another world's)
    stored with the ``which`` checkpoint ("latest" or "best"), or with the saved ``step``."""
    return config_from_stored(checkpoints.restore(directory, which=which, step=step,
                                                  with_state=False).config)



def check_resumable(saved: TrainConfig, cfg: TrainConfig, config_json: pathlib.Path | None = None
                    ) -> None:
    """ValueError naming the first field where ``cfg`` differs from the checkpoint's ``saved``
    config outside its :func:`~flowmaps_jax.training.config.resumable_fields`; with
    ``config_json``, ``cfg`` was read from that file, and the message says it is not the run's."""
    old, new = flatten(saved.to_dict()), flatten(cfg.to_dict())
    if type(saved) is not type(cfg):
        raise ValueError(f"--resume cannot change the world (the checkpoint trains on "
                         f"{saved.world!r}, this run asks for {cfg.world!r}): train it in a new "
                         f"--run-dir" if config_json is None else
                         f"{config_json} is not the config of the run's checkpoints (another "
                         f"world); restore or delete it, then resume")
    resumable = resumable_fields(cfg)
    changed = [key for key in sorted(set(old) | set(new))
               if key.split(".")[0] not in resumable and old.get(key) != new.get(key)]
    if changed:
        key = changed[0]
        raise ValueError(
            f"--resume cannot change {key} (the checkpoint has {old.get(key)!r}, this run "
            f"asks for {new.get(key)!r}): it would change the model, its parameters, its "
            f"optimiser or its data. Only {', '.join(resumable)} may change on "
            f"resume; train with other settings in a new --run-dir" if config_json is None
            else f"{config_json} is not the config of the run's checkpoints (another model or "
                 f"settings: {key} differs); restore or delete it, then resume")


def _unsaved_config(run_dir: pathlib.Path, from_step: int | None) -> TrainConfig | None:
    """The ``config.json`` of a run that saved no ``last`` checkpoint yet, which ``--resume``
    starts again from step 0; None when it holds one. ValueError if there is nothing to start
    from."""
    rundir.check_own_files(run_dir)  # before anything in it is read
    only_best = from_step is None and rundir.only_best_saved(run_dir)
    if not run_dir.is_dir() or (rundir.has_checkpoint(run_dir) and not only_best):
        rundir.checkpoint_root(run_dir)  # a checkpoint directory given as the run: refused
        return None
    if from_step is not None:
        raise ValueError(f"--from-step {from_step}: the run in {run_dir} saved no checkpoint")
    try:
        return config_from_stored(read_json("", run_dir / "config.json"))
    except (OSError, ValueError, TypeError) as err:
        missing = isinstance(err, FileNotFoundError)
        if missing and only_best:
            return load_config(run_dir / "checkpoints", checkpoints.BEST)
        why = "no config.json" if missing else f"an unreadable config.json ({err})"
        raise ValueError(f"run directory {run_dir} holds no checkpoint and {why}: nothing to "
                         f"resume; start a new run there") from None


def restore_for_resume(cfg: TrainConfig, run_dir: pathlib.Path, from_step: int | None,
                       mesh, log: Callable[[str], None] = print) -> checkpoints.Restored | None:
    """The verified checkpoint to continue from (onto ``mesh``), ``cfg`` checked against it;
    None for a run that saved no checkpoint yet."""
    unsaved = _unsaved_config(run_dir, from_step)
    root = None if unsaved is not None else rundir.checkpoint_root(run_dir)
    check_resumable(load_config(root, step=from_step) if root is not None else unsaved, cfg)
    if root is None:
        log(f"No checkpoint of the state to continue was saved in {run_dir} yet: starting the "
            f"run again from step 0")
        return None
    restored = checkpoints.restore(root, train_state.abstract_state(cfg, mesh=mesh),
                                  step=from_step)
    if int(restored.state.step) > cfg.steps:
        raise ValueError(f"the checkpoint is at step {int(restored.state.step)}, past "
                         f"steps={cfg.steps}; pass --steps with at least that many")
    return restored


def resume_config(run_dir: pathlib.Path, from_step: int | None,
                  log: Callable[[str], None] = print) -> TrainConfig:
    """The config a resumed run starts from: the checkpoint's, with the resumable fields from a
    readable ``config.json``."""
    unsaved = _unsaved_config(run_dir, from_step)
    if unsaved is not None:  # no checkpoint yet: the run starts again with its config.json
        return unsaved
    saved = load_config(rundir.checkpoint_root(run_dir), step=from_step)
    try:
        latest = config_from_stored(read_json("", run_dir / "config.json"))
    except (OSError, ValueError, TypeError) as err:  # the checkpoint's config
        if not isinstance(err, FileNotFoundError):
            log(f"{run_dir / 'config.json'} is unreadable ({' '.join(str(err).split())[:200]}): "
                f"resuming with the config saved in the checkpoint, which replaces it")
        return saved
    check_resumable(saved, latest, run_dir / "config.json")
    return dataclasses.replace(saved, **{name: getattr(latest, name)
                                         for name in resumable_fields(saved)})
