"""``python -m flowmaps_jax.train``: train FlowMaps (or the MLP baseline) on FlowSim.

Examples::

    python -m flowmaps_jax.train                          # cpu preset, FlowMaps
    python -m flowmaps_jax.train --preset smoke --model mlp --set model.baseline_variance=learned
    python -m flowmaps_jax.train --steps 5000 --set model.dim=96 --set lr=5e-4
    python -m flowmaps_jax.train --resume --run-dir runs/flowmaps-cpu-20250101-120000
    python -m flowmaps_jax.train --resume --run-dir runs/X --from-step 500   # an older save
    python -m flowmaps_jax.train --overwrite --run-dir runs/X   # old run moved to X.old-<time>

A run directory holds ``config.json`` (the resolved config), ``metrics.jsonl`` (one JSON record
per log interval: ``"kind": "train"`` with mean loss/grad_norm/lr and steps/s and samples/s over
the compiled steps only, or ``"kind": "val"`` with the EMA validation loss) and ``checkpoints/``
(see :mod:`flowmaps_jax.training.checkpoint`). It belongs to one run
(:mod:`flowmaps_jax.training.rundir`): a new run needs an empty directory (or ``--overwrite``,
or one whose run saved no checkpoint: ``--resume`` also starts that one again from step 0), one
process writes it at a time, and nothing in it is written before every check has passed,
resource bounds included (:func:`flowmaps_jax.training.config.check_run_resources`).

The batch and noise of step i depend only on the state's keys and i, so ``--resume`` continues a
run exactly, and the metrics of the steps since the last train record travel in the checkpoint,
so the records of a resumed run are those of a run never stopped. ``--resume`` may change only
the fields in :data:`RESUMABLE_FIELDS`. Ctrl-C saves a checkpoint and exits; a NaN/inf loss, or a
state with NaN/inf that a save refuses, stops the run without saving the bad state (the last good
checkpoint stays). A failed write (a full disk) stops with one line naming it (exit code 74).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import errno
import functools
import io
import json
import math
import os
import pathlib
import signal
import sys
import threading
import time
import typing
from collections.abc import Callable

import jax
import numpy as np
from tqdm import tqdm

from flowmaps_jax import distributed
from flowmaps_jax.training import checkpoint, data, objectives, rundir
from flowmaps_jax.training import state as train_state
from flowmaps_jax.training.config import (
    DEFAULT_PRESET,
    PRESETS,
    TrainConfig,
    _flatten,
    apply_overrides,
    check_run_resources,
    format_config,
    get_preset,
)
from flowmaps_jax.training.objectives import MODEL_KINDS
from flowmaps_jax.validation import check_instance, check_int

EXIT_OK, EXIT_NAN, EXIT_WRITE_FAILED, EXIT_INTERRUPTED = 0, 1, 74, 130


@dataclasses.dataclass
class RunResult:
    """Outcome of :func:`run`.

    status: "done" (reached cfg.steps), "stopped" (reached stop_at), "interrupted" (Ctrl-C) or
        "nan" (non-finite loss or state; nothing saved for that state).
    step: steps completed in the final state; state: that TrainState (None after "nan").
    run_dir, checkpoint_dir: where outputs went; best_val_loss: best validation loss seen, at
    step best_step (the step ``evaluate`` loads by default); None when no validation after step
    0 has run.
    """

    status: str
    step: int
    state: train_state.TrainState | None
    run_dir: pathlib.Path
    checkpoint_dir: pathlib.Path
    best_val_loss: float | None
    best_step: int | None = None


class _StopFlag:
    """First Ctrl-C sets the flag (checked between steps); a second one raises as usual."""

    def __init__(self):
        self.requested = False
        self._previous = None

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def _handle(self, signum, frame):
        self.requested = True
        signal.signal(signal.SIGINT, self._previous or signal.default_int_handler)

    def __exit__(self, *exc):
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)


def default_run_dir(cfg: TrainConfig) -> pathlib.Path:
    """``runs/<model_kind>-<preset>-<YYYYmmdd-HHMMSS>`` under the current directory."""
    return pathlib.Path("runs") / f"{cfg.model_kind}-{cfg.preset}-{time.strftime('%Y%m%d-%H%M%S')}"


class Compiled(typing.NamedTuple):
    """The jitted functions of a run: objective, fused train step, eval loss."""

    objective: objectives.Objective
    train_step: Callable
    eval_loss: Callable


def compiled_functions(cfg: TrainConfig, mesh=None) -> Compiled:
    """:class:`Compiled` for ``cfg`` on ``mesh`` (None: one device); cached so that several runs
    with the same computation in one process (tests, resume) compile once. On a multi-host job
    the train step takes a batch assembled from every host's share
    (:func:`~flowmaps_jax.training.state.make_train_step`); otherwise it draws the batch itself
    (:func:`~flowmaps_jax.training.state.make_fused_train_step`)."""
    return _compiled_functions(_computational(cfg), mesh, jax.process_count() > 1)


@functools.lru_cache(maxsize=2)
def _compiled_functions(cfg: TrainConfig, mesh, multi_host: bool) -> Compiled:
    objective = objectives.objective_for(cfg)
    step = (train_state.make_train_step if multi_host else train_state.make_fused_train_step)
    return Compiled(objective=objective, train_step=step(cfg, objective, mesh=mesh),
                    eval_loss=train_state.make_eval_loss(cfg, objective, mesh=mesh))


def _computational(cfg: TrainConfig) -> TrainConfig:
    """``cfg`` with the fields that do not change the compiled functions reset (cache key)."""
    base = TrainConfig()
    return dataclasses.replace(cfg, log_every=base.log_every, val_every=base.val_every,
                               ckpt_every=base.ckpt_every, keep_last=base.keep_last,
                               preset=base.preset, data=base.data,
                               routine_envs=base.routine_envs,
                               routine_samples=base.routine_samples)


def _read_records(path: pathlib.Path, upto: int, log: Callable[[str], None]) -> list[str]:
    """The lines of ``metrics.jsonl`` up to step ``upto``. A half-written last line (a crash
    mid-write) is dropped with a message; a bad line elsewhere is a ValueError naming it."""
    lines = path.read_bytes().decode("utf-8", errors="replace").split("\n")
    numbered = [(n, line) for n, line in enumerate(lines, 1) if line.strip()]
    kept = []
    for n, line in numbered:
        try:
            record = json.loads(line)
            if not isinstance(record, dict) or not isinstance(record.get("step", 0), int):
                raise ValueError("not a JSON object with an integer step")
        except ValueError as err:
            if n != numbered[-1][0]:
                raise ValueError(f"{path} line {n} is not a metrics record ({err}); repair or "
                                 f"delete that line, then resume again") from None
            log(f"Dropped the half-written last line of {path} (line {n}: {_clip(line)})")
            continue
        if record.get("step", 0) <= upto:
            kept.append(line)
    return kept


def _clip(text: str, limit: int = 60) -> str:
    return repr(text if len(text) <= limit else text[:limit] + "...")


class _MetricsLog:
    """Appends JSON records to ``metrics.jsonl``; on resume first rewrites it (atomically) with
    ``kept`` (the lines up to the restored step, from :func:`_read_records`). ``path=None``
    writes nothing (the other processes of a multi-host job)."""

    def __init__(self, path: pathlib.Path | None, kept: list[str] | None = None):
        self.path = path
        if path is not None and kept is not None:
            rundir.write_atomic(path, "".join(line + "\n" for line in kept))
        self._file = rundir.open_append(path) if path is not None else None

    def write(self, record: dict) -> None:
        if self._file is not None:
            self._file.write(json.dumps(record) + "\n")
            self._file.flush()

    def close(self) -> None:
        if self._file is not None:
            self._file.close()


# Fields that --resume may change; every other field would change the model, its parameters,
# its optimiser or its data, i.e. mix two runs in one directory.
RESUMABLE_FIELDS = ("steps", "log_every", "val_every", "ckpt_every", "keep_last",
                    "routine_envs", "routine_samples", "devices", "preset")


def check_resumable(saved: TrainConfig, cfg: TrainConfig) -> None:
    """ValueError naming the first field where ``cfg`` differs from the checkpoint's ``saved``
    config outside :data:`RESUMABLE_FIELDS`."""
    old, new = _flatten(saved.to_dict()), _flatten(cfg.to_dict())
    for key in sorted(set(old) | set(new)):
        if key.split(".")[0] not in RESUMABLE_FIELDS and old.get(key) != new.get(key):
            raise ValueError(
                f"--resume cannot change {key} (the checkpoint has {old.get(key)!r}, this run "
                f"asks for {new.get(key)!r}): it would change the model, its parameters, its "
                f"optimiser or its data. Only {', '.join(RESUMABLE_FIELDS)} may change on "
                f"resume; train with other settings in a new --run-dir")


def _checkpoint_root(run_dir: pathlib.Path) -> pathlib.Path:
    ckpt_dir = run_dir / "checkpoints"
    if not ckpt_dir.exists() and ((run_dir / "last").is_dir() or (run_dir / "best").is_dir()):
        raise ValueError(f"run_dir {str(run_dir)!r} is a checkpoint directory (it holds last/ or "
                         f"best/), not a run directory: resume the run that holds it, "
                         f"--run-dir {run_dir.parent}")
    return checkpoint.resolve_checkpoint_dir(ckpt_dir if ckpt_dir.exists() else run_dir)


def _unsaved_config(run_dir: pathlib.Path, from_step: int | None) -> TrainConfig | None:
    """The ``config.json`` of a run that saved no checkpoint yet (killed or interrupted before
    its first save), which ``--resume`` starts again from step 0; None when the run directory
    holds a checkpoint (or anything else). ValueError if there is nothing to start from."""
    if not run_dir.is_dir() or rundir.has_checkpoint(run_dir):
        _checkpoint_root(run_dir)  # a checkpoint directory given as the run: refused
        return None
    if from_step is not None:
        raise ValueError(f"--from-step {from_step}: the run in {run_dir} saved no checkpoint")
    try:
        return TrainConfig.from_dict(json.loads((run_dir / "config.json").read_text()))
    except FileNotFoundError:
        raise ValueError(f"run directory {run_dir} holds no checkpoint and no config.json: "
                         f"nothing to resume; start a new run there") from None
    except (OSError, ValueError, TypeError) as err:
        raise ValueError(f"run directory {run_dir} holds no checkpoint, and its config.json "
                         f"is unreadable ({err}); start a new run there") from None


def _restore_for_resume(cfg: TrainConfig, run_dir: pathlib.Path, from_step: int | None,
                        mesh, log: Callable[[str], None] = print) -> checkpoint.Restored | None:
    """The verified checkpoint to continue from (onto ``mesh``, whatever device count it was
    saved from), after checking that ``cfg`` may resume it; None for a run that saved no
    checkpoint yet (it starts again from step 0 with its ``config.json``)."""
    unsaved = _unsaved_config(run_dir, from_step)
    if unsaved is not None:
        check_resumable(unsaved, cfg)
        log(f"No checkpoint was saved in {run_dir} yet: starting the run again from step 0")
        return None
    root = _checkpoint_root(run_dir)
    check_resumable(checkpoint.load_config(root, step=from_step), cfg)
    restored = checkpoint.restore(root, train_state.abstract_state(cfg, mesh=mesh),
                                  step=from_step)
    if int(restored.state.step) > cfg.steps:
        raise ValueError(f"the checkpoint is at step {int(restored.state.step)}, past "
                         f"steps={cfg.steps}; pass --steps with at least that many")
    return restored


def run(cfg: TrainConfig, run_dir: str | pathlib.Path, *, resume: bool = False,
        overwrite: bool = False, from_step: int | None = None, stop_at: int | None = None,
        progress: bool = True, on_step: Callable[[int, dict], None] | None = None,
        log: Callable[[str], None] = print) -> RunResult:
    """Train per ``cfg`` into ``run_dir``; see the module docstring for what is written.

    resume: continue from the latest checkpoint in ``run_dir`` (or the saved step
        ``from_step``); ValueError if there is none, if it is damaged (the message names the
        newest intact step) or if ``cfg`` differs from the checkpoint's config outside
        :data:`RESUMABLE_FIELDS`. Later saved steps are moved aside when ``from_step`` is given.
    overwrite: a new run in a non-empty ``run_dir`` first moves the old run to
        ``<run_dir>.old-<timestamp>``; without it (and without ``resume``) that is a ValueError.
    stop_at: stop after this step (saving a checkpoint) without changing the schedule, which
        always spans ``cfg.steps``. on_step(step, metrics): called after every step (tests).

    Nothing in ``run_dir`` is written before every check has passed, and ``run_dir/.lock``
    keeps other processes out while the run lasts (see :mod:`flowmaps_jax.training.rundir`).
    A failed checkpoint write (e.g. a full disk) raises ``checkpoint.CheckpointSaveError``.
    """
    check_instance("cfg", cfg, TrainConfig)
    run_dir = rundir.check_run_dir(run_dir)
    if stop_at is not None and not check_int("stop_at", stop_at) <= cfg.steps:
        raise ValueError(f"stop_at must lie in 1..steps={cfg.steps}; got {stop_at}")
    if from_step is not None and not resume:
        raise ValueError("from_step (--from-step) needs resume (--resume)")
    mesh = distributed.training_mesh(cfg.devices)
    distributed.check_divides("batch_size", cfg.batch_size, mesh, "the scenes of a batch")
    data.host_train_part(cfg)  # a multi-host job: the data must divide over the hosts
    check_run_resources(cfg, devices=1 if mesh is None else mesh.size)  # before anything runs
    primary = jax.process_index() == 0
    with _claim(run_dir, resume=resume, overwrite=overwrite, log=log):
        resumed = _restore_for_resume(cfg, run_dir, from_step, mesh, log) if resume else None
        metrics_path, kept = run_dir / "metrics.jsonl", None
        if resumed is not None and metrics_path.exists() and primary:
            kept = _read_records(metrics_path, int(resumed.state.step), log)
        elif resume and primary:  # starting again: the old run's records go
            kept = []
        log("Config:\n" + format_config(cfg))
        log(f"Run directory: {run_dir.absolute()} (config.json, metrics.jsonl, checkpoints/)")
        log(f"Devices: {distributed.describe(mesh)}")
        compiled = compiled_functions(cfg, mesh)
        train_scenes, val_scenes = data.load_splits(cfg, log, mesh=_generation_mesh(mesh))
        train_scenes = _place_scenes(train_scenes, mesh)
        val_batches = distributed.replicate(data.make_val_batches(cfg, val_scenes), mesh)
        # Every check has passed: from here on the run directory is written.
        if resumed is not None:
            state = resumed.state
            log(f"Resumed from {resumed.path} at step {int(state.step)}")
            if from_step is not None and primary:
                moved_to, moved = checkpoint.set_aside(_checkpoint_root(run_dir), from_step)
                if moved:
                    log(f"Moved the later checkpoints (steps {moved}) aside to {moved_to}")
        else:
            state = train_state.init_state(cfg, objective=compiled.objective, mesh=mesh)
        if primary:
            rundir.write_atomic(run_dir / "config.json",
                                json.dumps(cfg.to_dict(), indent=2) + "\n")
        distributed.barrier("run directory ready")  # process 0 has set later steps aside
        window = (resumed.meta or {}).get("log_window") if resumed is not None else None
        metrics_log = _MetricsLog(metrics_path if primary else None, kept)
        return _train(cfg, run_dir, state, window or {}, metrics_log,
                      _step_taker(cfg, compiled.train_step, mesh), compiled.eval_loss,
                      train_scenes, val_scenes, val_batches,
                      mesh, stop_at=stop_at, progress=progress, on_step=on_step, log=log)


@contextlib.contextmanager
def _claim(run_dir: pathlib.Path, *, resume: bool, overwrite: bool, log: Callable[[str], None]):
    """Hold ``run_dir`` for this run (:func:`flowmaps_jax.training.rundir.claim`).

    On a multi-host job the first process owns the run directory (lock, config, metrics; every
    process takes part in the checkpoint saves, which orbax coordinates). The others learn
    whether it could claim it, so a refused run stops every process at once with the reason.
    """
    if jax.process_count() == 1:
        with rundir.claim(run_dir, resume=resume, overwrite=overwrite, log=log):
            yield
        return
    with contextlib.ExitStack() as held:
        error = ""
        if jax.process_index() == 0:
            try:
                held.enter_context(rundir.claim(run_dir, resume=resume, overwrite=overwrite,
                                                log=log))
            except ValueError as err:
                error = str(err)
        if distributed.agree(not error):
            yield
            return
        raise ValueError(error or f"process 0 could not claim the run directory {run_dir} "
                                  "(its log says why)")


def _generation_mesh(mesh):
    """Where FlowSim data is generated: over the training mesh on one host; over this host's
    own devices on a multi-host job (each host generates its own share)."""
    return mesh if jax.process_count() == 1 else distributed.local_mesh()


def _place_scenes(scenes, mesh):
    """Training scenes where the train step reads them: on one host, replicated over the mesh
    (the fused step draws any scene on every device); on a multi-host job, where they are."""
    if scenes is None or jax.process_count() > 1:
        return scenes
    return distributed.replicate(scenes, mesh)


def _step_taker(cfg: TrainConfig, step_fn: Callable, mesh) -> Callable:
    """``take(state, train_scenes, step) -> (state, metrics)`` for this job's layout.

    One host: the fused step draws the batch itself from the (replicated) scenes. Several hosts:
    each host draws its share of the global batch from its own scenes, with the step's batch
    key folded with its process index, and the shares form one global batch split over the
    mesh (:func:`flowmaps_jax.distributed.from_hosts`); no data crosses hosts.
    """
    if jax.process_count() == 1:
        return lambda state, scenes, step: step_fn(state, scenes)
    hosts, index = jax.process_count(), jax.process_index()
    local_batch = jax.jit(data.default_batch_fn(
        dataclasses.replace(cfg, batch_size=cfg.batch_size // hosts, devices=None)))

    def take(state, scenes, step):
        # The keys are replicated: every host reads the same values from its own copy.
        batch_key = jax.random.fold_in(np.asarray(state.data_key), step)
        noise_key = jax.random.fold_in(np.asarray(state.rng), step)
        batch = local_batch(jax.random.fold_in(batch_key, index), scenes)
        return step_fn(state, distributed.from_hosts(batch, mesh),
                       distributed.replicate(noise_key, mesh))

    return take


def _train(cfg, run_dir, state, window_state, metrics_log, take_step, eval_fn, train_scenes,
           val_scenes, val_batches, mesh, *, stop_at, progress, on_step, log) -> RunResult:
    """The step loop of :func:`run`, once the run directory is held and validated."""
    ckpt_dir = run_dir / "checkpoints"
    cfg_dict = cfg.to_dict()
    start = int(state.step)
    end = cfg.steps if stop_at is None else stop_at
    samples_per_step = cfg.batch_size * cfg.queries_per_scene

    try:
        store = checkpoint.CheckpointStore(ckpt_dir, cfg.keep_last)
    except BaseException:
        metrics_log.close()
        raise
    best, best_step = store.best_val_loss, store.best_step()

    probe = None
    if cfg.routine_envs > 0:
        from flowmaps_jax.evaluation import routine
        from flowmaps_jax.sample import Predictor

        probe = routine.build_probe(val_scenes, cfg.flowsim,
                                    min(cfg.routine_envs, val_scenes.num_envs), cfg.seed)
    last_routine: dict = {}

    # Metrics of the steps since the last train record (restored on resume, so the next record
    # averages the same steps as in a run that was never interrupted).
    window: list[dict] = list(window_state.get("records", []))
    timed_steps = int(window_state.get("timed_steps", 0))  # compiled steps in the window
    step_seconds = float(window_state.get("step_seconds", 0.0))  # and their time only

    def log_window() -> dict:
        return {"records": window, "timed_steps": timed_steps, "step_seconds": step_seconds}

    def validate(step: int) -> float:
        nonlocal best, best_step, last_routine
        val_loss = float(eval_fn(state.ema_params, val_batches))
        improved = step > 0 and store.save_if_best(state, cfg_dict, val_loss,
                                                   log_window=log_window())
        if improved:
            best, best_step = val_loss, step
        metrics_log.write({"kind": "val", "step": step, "val_loss": val_loss,
                           "best": bool(improved)})
        if probe is not None:
            params, on = _inference_params(state, mesh)
            predictor = Predictor.from_params(params, cfg.model, cfg.model_kind, cfg.flowsim,
                                              mesh=on)
            last_routine = routine.routine_metrics(predictor, probe,
                                                   num_samples=cfg.routine_samples)
            metrics_log.write({"kind": "routine", "step": step, **last_routine})
        return val_loss

    status, step, last_val = "done", start, None
    bar = None
    try:
        with _StopFlag() as stop:
            log(f"Compiling; training steps {start + 1}..{end} of {cfg.steps} "
                f"({samples_per_step} query-samples per step) ...")
            compile_start = time.perf_counter()
            if start == 0:
                last_val = validate(0)
            while step < end:
                if stop.requested:
                    status = "interrupted"
                    break
                if cfg.data == "endless" and (
                        train_scenes is None or step % data.endless_chunk_steps(cfg) == 0):
                    train_scenes = _place_scenes(data.endless_scenes(
                        cfg, state.data_key, step, mesh=_generation_mesh(mesh)), mesh)
                step_start = time.perf_counter()
                state, metrics = take_step(state, train_scenes, step)
                metrics = {k: float(v) for k, v in jax.device_get(metrics).items()}
                step_time = time.perf_counter() - step_start
                if not math.isfinite(metrics["loss"]):
                    status = "nan"
                    log(f"\nLoss is {metrics['loss']} at step {step + 1}: stopping without "
                        f"saving this state.")
                    break
                step += 1
                if bar is None:  # first step done: compilation is over, start the clock
                    log(f"  compiled (train step, validation) and ran the first step in "
                        f"{time.perf_counter() - compile_start:.1f} s")
                    bar = tqdm(total=cfg.steps, initial=step, unit="step", disable=not progress,
                               dynamic_ncols=True, desc="train")
                else:
                    bar.update(1)
                    timed_steps, step_seconds = timed_steps + 1, step_seconds + step_time
                window.append(metrics)
                bar.set_postfix(loss=f"{metrics['loss']:.4f}",
                                val=f"{last_val:.4f}" if last_val is not None else "-",
                                next=f"{last_routine['offset_+1']:.2f}" if last_routine else "-",
                                refresh=False)
                if step % cfg.log_every == 0 or step == end:
                    rate = timed_steps / step_seconds if step_seconds > 0 else 0.0
                    record = {k: float(np.mean([m[k] for m in window])) for k in window[0]}
                    record.update(kind="train", step=step, steps_per_sec=rate,
                                  samples_per_sec=rate * samples_per_step)
                    metrics_log.write(record)
                    window, timed_steps, step_seconds = [], 0, 0.0
                if step % cfg.val_every == 0 or step == cfg.steps:
                    last_val = validate(step)
                if step % cfg.ckpt_every == 0:
                    store.save(state, cfg_dict, log_window=log_window())
                if on_step is not None:
                    on_step(step, metrics)
            else:
                status = "done" if step == cfg.steps else "stopped"
            if status != "nan":
                store.save(state, cfg_dict, log_window=log_window())
    except checkpoint.NonFiniteStateError as err:
        status = "nan"
        log(f"\n{err}. Stopping without saving this state.")
    except checkpoint.CheckpointSaveError as err:
        latest = store.latest_step()
        saved = (f"the saved checkpoints are intact (latest: step {latest})"
                 if latest is not None else "no checkpoint was saved yet (--resume starts the "
                 "run again from step 0)")
        raise checkpoint.CheckpointSaveError(
            err.errno, f"{err}. Training stopped at step {step}; {saved}. Free some space, then "
            f"continue with python -m flowmaps_jax.train --resume --run-dir {run_dir}") from err
    finally:
        if bar is not None:
            bar.close()
        with contextlib.suppress(OSError):  # a full disk: the error in flight says so
            metrics_log.close()
        latest = store.latest_step()
        store.close()

    if probe is not None and jax.process_index() == 0:
        _write_routine_curve(run_dir, log)
    _print_summary(log, status, step, cfg, run_dir, ckpt_dir, latest, best, best_step)
    return RunResult(status=status, step=step, state=None if status == "nan" else state,
                     run_dir=run_dir, checkpoint_dir=ckpt_dir, best_val_loss=best,
                     best_step=best_step)


def _inference_params(state, mesh) -> tuple:
    """(EMA params, mesh) for the routine diagnostic's Predictor: sampled over the training mesh
    on one host; on a multi-host job each host samples its own copy (the probe is small)."""
    if jax.process_count() > 1:
        return jax.device_get(state.ema_params), None
    return state.ema_params, mesh


def _write_routine_curve(run_dir: pathlib.Path, log: Callable[[str], None]) -> None:
    """routine_curve.png from the run's routine records (skipped when there are none)."""
    from flowmaps_jax.evaluation import routine

    records = routine.read_routine_records(run_dir / "metrics.jsonl")
    if records:
        image = io.BytesIO()  # rendered first, then written by a rename: no link is followed
        routine.plot_learning_curve(records, title=run_dir.name).savefig(image, dpi=100,
                                                                         format="png")
        rundir.write_atomic(run_dir / "routine_curve.png", image.getvalue())
        last = records[-1]
        log(f"Routines at step {last['step']} (one step ahead, exact 0.2 / 0.7 / 0.1): "
            f"offsets 0 / +1 / +2 = {last['offset_0']:.2f} / {last['offset_+1']:.2f} / "
            f"{last['offset_+2']:.2f}; TV {last['tv']:.3f}, rank cost "
            f"{last['search_cost_ratio']:.3f} → {run_dir / 'routine_curve.png'}")


def _print_summary(log, status, step, cfg, run_dir, ckpt_dir, latest, best,
                   best_step=None) -> None:
    headline = {"done": f"Finished {step} steps.",
                "stopped": f"Stopped after step {step} of {cfg.steps}.",
                "interrupted": f"Interrupted at step {step} of {cfg.steps}; checkpoint saved.",
                "nan": "Training diverged (non-finite loss or state)."}[status]
    log(headline)
    if latest is None:
        log(f"No checkpoint was saved in {ckpt_dir}.")
        return
    has_best = best is not None and best_step is not None
    best_text = f"; best validation loss {best:.5f} at step {best_step}" if has_best else ""
    log(f"Checkpoint: {ckpt_dir.absolute()} (latest step {latest}{best_text})")
    log(f"Evaluate it:  python -m flowmaps_jax.evaluate --checkpoint {ckpt_dir}")
    if has_best and best_step != latest:
        log(f"  (evaluate and search load the best step, {best_step}, by default; "
            f"--which latest loads step {latest}, the last)")
    elif has_best:
        log(f"  (the best step is the last, {latest}: evaluate and search load it)")
    else:  # no validation since step 0: the best falls back to the latest save
        log(f"  (no best-by-validation step yet: evaluate and search load step {latest})")
    if status != "done":
        log(f"Resume it:    python -m flowmaps_jax.train --resume --run-dir {run_dir}")


# --------------------------------------------------------------------------------------------
# Command line


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m flowmaps_jax.train",
        description="Train FlowMaps (flow matching) or the MLP baseline on FlowSim.")
    parser.add_argument("--preset", choices=sorted(PRESETS), default=None,
                        help=f"named configuration (default {DEFAULT_PRESET})")
    parser.add_argument("--model", choices=tuple(MODEL_KINDS), default=None,
                        help="flowmaps (default) or mlp (Gaussian baseline)")
    parser.add_argument("--run-dir", default=None,
                        help="output directory (default runs/<model>-<preset>-<timestamp>); "
                             "a new run needs an empty or missing one")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --run-dir from its latest checkpoint")
    parser.add_argument("--from-step", type=int, default=None, metavar="N",
                        help="with --resume: continue from the saved step N instead (e.g. when "
                             "the newest step is damaged); later steps are moved aside")
    parser.add_argument("--overwrite", action="store_true",
                        help="start a new run in a non-empty --run-dir after moving the old run "
                             "to <run-dir>.old-<timestamp>")
    parser.add_argument("--steps", type=int, default=None, help="total training steps")
    parser.add_argument("--stop-at", type=int, default=None,
                        help="stop (with a checkpoint) after this step; resume later")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE",
                        help="override any config field, e.g. --set model.dim=64 --set lr=1e-3")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


def _resume_base(run_dir: pathlib.Path, from_step: int | None) -> TrainConfig:
    """The config a resumed run starts from: the checkpoint's, with the fields --resume may
    change taken from ``config.json`` when that file is readable (it holds the last run's
    --steps etc. even when no checkpoint was saved since)."""
    unsaved = _unsaved_config(run_dir, from_step)
    if unsaved is not None:  # no checkpoint yet: the run starts again with its config.json
        return unsaved
    saved = checkpoint.load_config(_checkpoint_root(run_dir), step=from_step)
    try:
        latest = TrainConfig.from_dict(json.loads((run_dir / "config.json").read_text()))
    except (OSError, ValueError, TypeError):  # missing or unreadable: the checkpoint's config
        return saved
    try:
        check_resumable(saved, latest)
    except ValueError:
        raise ValueError(f"{run_dir / 'config.json'} is not the config of the run's "
                         f"checkpoints (another model or settings); restore or delete it, then "
                         f"resume") from None
    return dataclasses.replace(saved, **{name: getattr(latest, name)
                                         for name in RESUMABLE_FIELDS})


def resolve_config(args: argparse.Namespace) -> tuple[TrainConfig, pathlib.Path]:
    """The run's config and directory from parsed arguments (ValueError on bad input)."""
    if args.from_step is not None and not args.resume:
        raise ValueError("--from-step needs --resume")
    if args.resume:
        if args.run_dir is None:
            raise ValueError("--resume needs --run-dir (the run to continue)")
        if args.preset is not None or args.model is not None:
            raise ValueError("--resume uses the run's saved config; change fields with --set, "
                             "not --preset/--model")
        if args.overwrite:
            raise ValueError("--resume and --overwrite exclude each other")
        run_dir = rundir.check_run_dir(args.run_dir)
        cfg = _resume_base(run_dir, args.from_step)
    else:
        cfg = get_preset(args.preset or DEFAULT_PRESET)
        run_dir = None
    overrides = list(args.overrides)
    if args.model is not None:
        overrides.append(f"model_kind={args.model}")
    if args.steps is not None:
        overrides.append(f"steps={args.steps}")
    cfg = apply_overrides(cfg, overrides)
    if run_dir is None:
        run_dir = rundir.check_run_dir(args.run_dir if args.run_dir else default_run_dir(cfg))
    return cfg, run_dir


def _one_line(err: OSError) -> str:
    """A failed write as one line (the message's own line breaks folded)."""
    return " ".join(str(err).split()) or os.strerror(err.errno or errno.EIO)


def _exit_now(code: int) -> typing.NoReturn:
    """Leave the process without interpreter teardown. After Ctrl-C outside the step loop (data
    generation, compilation) XLA may still be working in its own threads, and tearing the
    interpreter down under them ends in SIGSEGV; the run's lock is already released."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit code (0 ok, 1 non-finite loss or state, 74 a write
    failed, e.g. a full disk, 130 interrupted)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        distributed.initialize()  # a multi-host job: connect the processes first
        cfg, run_dir = resolve_config(args)
        result = run(cfg, run_dir, resume=args.resume, overwrite=args.overwrite,
                     from_step=args.from_step, stop_at=args.stop_at,
                     progress=not args.no_progress)
    except ValueError as err:
        parser.error(str(err))
    except OSError as err:  # a full disk or another failed write: one line, not a traceback
        print(f"{parser.prog}: error: {_one_line(err)}", file=sys.stderr)
        if argv is None:  # no teardown: orbax's threads would print tracebacks after the line
            _exit_now(EXIT_WRITE_FAILED)
        return EXIT_WRITE_FAILED
    except KeyboardInterrupt:  # outside the step loop (data, compilation) or a second Ctrl-C
        print("\nInterrupted; the current state was not saved.", file=sys.stderr)
        if argv is None:  # the real command: see _exit_now
            _exit_now(EXIT_INTERRUPTED)
        return EXIT_INTERRUPTED
    return {"nan": EXIT_NAN, "interrupted": EXIT_INTERRUPTED}.get(result.status, EXIT_OK)


if __name__ == "__main__":
    sys.exit(main())
