"""The training loop: :func:`run` trains a model on its world, in three parts: the prelude
(every check, then the run directory is claimed, the functions compiled and the data built;
nothing is written before the last check), the step loop with its periodic train, val and
checkpoint blocks, and the summary. What a run writes and promises (resume, Ctrl-C, NaN, a
failed write): docs/guarantees.md."""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import pathlib
import signal
import threading
import time
import typing
from collections.abc import Callable

import jax
import numpy as np
from tqdm import tqdm

from flowmaps_jax import distributed
from flowmaps_jax.evaluation import routine
from flowmaps_jax.predictor import Predictor, load_model
from flowmaps_jax.store import checkpoints, rundir
from flowmaps_jax.store.checkpoint_store import CheckpointSaveError
from flowmaps_jax.store.integrity import NonFiniteStateError
from flowmaps_jax.training import objectives, runlog
from flowmaps_jax.training import state as train_state
from flowmaps_jax.training.config import (
    TrainConfig,
    check_run_resources,
    compile_key,
    format_config,
    run_configs,
)
from flowmaps_jax.training.resume import restore_for_resume
from flowmaps_jax.training.runlog import RunResult
from flowmaps_jax.validation import check_instance, check_int, check_output_dir, prefix_errors
from flowmaps_jax.worlds import world

__all__ = ["Compiled", "RunResult", "compiled_functions", "run"]


def run(cfg: TrainConfig, run_dir: str | pathlib.Path, *, resume: bool = False,
        overwrite: bool = False, from_step: int | None = None, stop_at: int | None = None,
        progress: bool = True, on_step: Callable[[int, dict], None] | None = None,
        log: Callable[[str], None] = print) -> RunResult:
    """Train per ``cfg`` (an instance of a registered world's run config class) into
    ``run_dir``.

    resume: continue from the latest checkpoint (or the saved step ``from_step``, later steps
        moved aside); ValueError if there is none, it is damaged, or ``cfg`` differs outside
        :data:`~flowmaps_jax.training.config.RESUMABLE_FIELDS`.
    overwrite: move an old run in ``run_dir`` to ``<run_dir>.old-<timestamp>`` first.
    stop_at: stop after this step (saving a checkpoint); the schedule still spans ``cfg.steps``.
    on_step(step, metrics): called after every step. A failed checkpoint write raises
    :class:`~flowmaps_jax.store.checkpoint_store.CheckpointSaveError`.
    """
    # ---- Prelude: every check, then the run's pieces; nothing is written before the last one.
    check_instance("cfg", cfg, run_configs())
    run_dir = pathlib.Path(check_output_dir("run_dir", run_dir))
    if stop_at is not None:
        check_int("stop_at", stop_at, 1, cfg.steps)
    if from_step is not None and not resume:
        raise ValueError("from_step needs resume=True (--from-step needs --resume)")
    data = world(cfg.world)  # the world: data, batches, objective, resources
    # Then the checks that depend on the devices.
    mesh = distributed.training_mesh(cfg.devices)
    distributed.check_divides("batch_size", cfg.batch_size, mesh, "the scenes of a batch")
    data.host_part(cfg)  # a multi-host job: the data must divide over the hosts
    check_run_resources(cfg, devices=1 if mesh is None else mesh.size)
    start_params = None if resume else _start_params(cfg, log)
    primary = jax.process_index() == 0
    with StopFlag() as stop, rundir.claim(run_dir, resume=resume, overwrite=overwrite,
                                           log=log):
        resumed = restore_for_resume(cfg, run_dir, from_step, mesh, log) if resume else None
        kept = None  # a new run appends to metrics.jsonl; a resumed one first trims it
        if resume and primary:  # starting again from step 0 (resumed None): no record is kept
            kept = rundir.kept_records(
                run_dir, None if resumed is None else int(resumed.state.step), log)
        log("Config:\n" + format_config(cfg))
        log(f"Run directory: {run_dir.absolute()} (config.json, metrics.jsonl, checkpoints/)")
        log(f"Devices: {distributed.describe(mesh)}")
        compiled = compiled_functions(cfg, mesh)
        train_scenes, val_scenes = data.splits(cfg, log, mesh=_generation_mesh(mesh))
        train_scenes = _place_scenes(train_scenes, mesh)
        val_batches = distributed.replicate(data.val_batches(cfg, val_scenes), mesh)
        probe = _routine_probe(cfg, val_scenes, mesh)
        take_step = _step_taker(cfg, compiled.train_step, mesh)
        endless = data.is_endless(cfg)
        # Every check has passed: from here on the run directory is written.
        if resumed is None:
            state, window = train_state.init_state(cfg, objective=compiled.objective, mesh=mesh,
                                                   start_params=start_params), None
        else:
            state, window = resumed.state, (resumed.meta or {}).get("log_window")
            log(f"Resumed from {resumed.path} at step {int(state.step)}")
            if from_step is not None and primary:
                moved_to, moved = checkpoints.set_aside(rundir.checkpoint_root(run_dir),
                                                        from_step)
                if moved:
                    log(f"Moved the later checkpoints (steps {moved}) aside to {moved_to}")
        if primary:
            rundir.write_atomic(run_dir / "config.json",
                                json.dumps(cfg.to_dict(), indent=2) + "\n")
        distributed.barrier("run directory ready")  # process 0 has set later steps aside
        start = done = int(state.step)  # done: steps completed
        end = cfg.steps if stop_at is None else stop_at
        samples_per_step = cfg.batch_size * cfg.queries_per_scene
        status = "done" if end == cfg.steps else "stopped"
        val_loss, routine = None, None

        stop.start_steps()
        with (runlog.RunBook(run_dir, cfg, kept=kept, window=window, primary=primary,
                             start_step=start) as book,
              _ProgressBar(cfg.steps, progress) as bar):
            log(f"Compiling; training steps {start + 1}..{end} of {cfg.steps} "
                f"({samples_per_step} query-samples per step) ...")
            compile_start = time.perf_counter()
            try:
                if start == 0:
                    val_loss, routine = _val_pass(0, state, compiled, val_batches, probe, book)

                # ---- The step loop: one train step, then the periodic blocks.
                for step in range(start, end):  # step: the steps completed before this one
                    if stop.requested:  # Ctrl-C: the state after the last step is saved below
                        status = "interrupted"
                        break
                    if endless and (train_scenes is None or step % data.chunk_steps(cfg) == 0):
                        train_scenes = _place_scenes(data.endless(
                            cfg, state.data_key, step, mesh=_generation_mesh(mesh)), mesh)
                    step_start = time.perf_counter()
                    state, metrics = take_step(state, train_scenes, step)
                    metrics = {k: float(v) for k, v in jax.device_get(metrics).items()}
                    seconds = time.perf_counter() - step_start
                    if not math.isfinite(metrics["loss"]):
                        status = "nan"
                        log(f"\nLoss is {metrics['loss']} at step {step + 1}: stopping without "
                            f"saving this state.")
                        break
                    done = step + 1
                    if step == start:  # the first step ends the compilation: not timed
                        log(f"  compiled (train step, validation) and ran the first step in "
                            f"{time.perf_counter() - compile_start:.1f} s")
                    book.add_step(metrics, None if step == start else seconds)
                    bar.show(done, **postfix(metrics, val_loss, routine, probe is not None))

                    if done % cfg.log_every == 0 or done == end:
                        book.write_train(done, samples_per_step)
                    if done % cfg.val_every == 0 or done == cfg.steps:
                        val_loss, routine = _val_pass(done, state, compiled, val_batches, probe,
                                                      book)
                    if done % cfg.ckpt_every == 0:
                        book.save(state)
                    if on_step is not None:
                        on_step(done, metrics)

                if status != "nan":
                    book.save(state)  # the last state, whether done, stopped or interrupted
            except NonFiniteStateError as err:
                status = "nan"
                log(f"\n{err}. Stopping without saving this state.")
            except CheckpointSaveError as err:
                raise book.save_failed(err, done) from err
            latest = book.latest_step()

        # ---- Summary.
        result = RunResult(status=status, step=done, state=None if status == "nan" else state,
                           run_dir=run_dir, checkpoint_dir=run_dir / "checkpoints",
                           best_val_loss=book.best_loss, best_step=book.best_step)
        if probe is not None and primary:
            runlog.write_routine_curve(run_dir, log)
        runlog.print_summary(result, cfg.steps, latest, log)
        return result


def _start_params(cfg, log: Callable[[str], None]):
    """The EMA params ``cfg.init_from`` names (None without it); ValueError naming it when they
    cannot be read or fit another family or architecture."""
    if cfg.init_from is None:
        return None
    with prefix_errors(f"init_from={cfg.init_from!r}: "):
        source = load_model(cfg.init_from, devices=1)
    family = source.family_name
    if family != cfg.family:
        raise ValueError(f"init_from={cfg.init_from!r} is a {family!r} model; this run trains "
                         f"{cfg.family!r}")
    fresh = jax.eval_shape(objectives.objective_for(cfg).init, jax.random.PRNGKey(0))
    overlay = functools.partial(train_state.overlay_params, where=f"init_from={cfg.init_from!r}")
    jax.eval_shape(overlay, fresh, source.params)  # init_state's overlay, traced: its check now
    log(f"Starting from the weights of {cfg.init_from} (step {source.step}); parameters they "
        f"lack keep their fresh init")
    return source.params


def _val_pass(step: int, state, compiled: Compiled, val_batches, probe: Callable | None,
              book: runlog.RunBook) -> tuple[float, dict | None]:
    """The EMA loss on the validation batches (a new best saved as ``best``), then the routine
    diagnostic when on. Returns (val loss, routine metrics or None)."""
    val_loss = float(compiled.eval_loss(state.ema_params, val_batches))
    book.write_val(state, step, val_loss)
    routine = probe(state) if probe is not None else None
    if routine is not None:
        book.write_routine(step, routine)
    return val_loss, routine


# --------------------------------------------------------------------------------------------
# The compiled functions


class Compiled(typing.NamedTuple):
    """The jitted functions of a run: objective, fused train step, eval loss."""

    objective: objectives.Objective
    train_step: Callable
    eval_loss: Callable


def compiled_functions(cfg: TrainConfig, mesh=None) -> Compiled:
    """:class:`Compiled` for ``cfg`` on ``mesh`` (None: one device), cached by
    :func:`~flowmaps_jax.training.config.compile_key`. On a multi-host job the train step takes
    a batch assembled from every host's share; otherwise it draws the batch itself."""
    return _compiled_functions(compile_key(cfg), mesh, jax.process_count() > 1)


@functools.lru_cache(maxsize=2)
def _compiled_functions(cfg: TrainConfig, mesh, multi_host: bool) -> Compiled:
    objective = objectives.objective_for(cfg)
    step = (train_state.make_train_step if multi_host else train_state.make_fused_train_step)
    return Compiled(objective=objective, train_step=step(cfg, objective, mesh=mesh),
                    eval_loss=train_state.make_eval_loss(cfg, objective, mesh=mesh))


def _step_taker(cfg: TrainConfig, step_fn: Callable, mesh) -> Callable:
    """``take(state, train_scenes, step) -> (state, metrics)``. On several hosts each draws its
    share of the batch from its own scenes (batch key folded with its process index); the
    shares form one global batch (:func:`flowmaps_jax.distributed.from_hosts`)."""
    if jax.process_count() == 1:
        return lambda state, scenes, step: step_fn(state, scenes)
    hosts, index = jax.process_count(), jax.process_index()
    local_batch = jax.jit(world(cfg.world).batch_fn(
        dataclasses.replace(cfg, batch_size=cfg.batch_size // hosts, devices=None)))

    def take(state, scenes, step):
        # The keys are replicated: every host reads the same values from its own copy.
        batch_key = jax.random.fold_in(np.asarray(state.data_key), step)
        noise_key = jax.random.fold_in(np.asarray(state.rng), step)
        batch = local_batch(jax.random.fold_in(batch_key, index), scenes)
        return step_fn(state, distributed.from_hosts(batch, mesh),
                       distributed.replicate(noise_key, mesh))

    return take


# --------------------------------------------------------------------------------------------
# Where the data lives, and the routine diagnostic


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


def _routine_probe(cfg: TrainConfig, val_scenes, mesh) -> Callable[[typing.Any], dict] | None:
    """``probe(state) -> metrics``: the routine diagnostic on ``cfg.routine_envs`` validation
    environments with the EMA weights; None when off or not in the run config."""
    if getattr(cfg, "routine_envs", 0) <= 0:
        return None
    probe = routine.build_probe(val_scenes, cfg.flowsim,
                                min(cfg.routine_envs, val_scenes.num_envs), cfg.seed,
                                history=cfg.model.history)

    def run_probe(state) -> dict:
        if jax.process_count() > 1:
            params, on = jax.device_get(state.ema_params), None
        else:
            params, on = state.ema_params, mesh
        predictor = Predictor.from_params(params, cfg.model, cfg.family, cfg.flowsim, mesh=on)
        return routine.routine_metrics(predictor, probe, num_samples=cfg.routine_samples)

    return run_probe


# --------------------------------------------------------------------------------------------
# Ctrl-C and the progress bar


class StopFlag:
    """Ctrl-C during a run. Before the step loop it raises ``KeyboardInterrupt`` and remembers
    it (one raised in a GC callback is swallowed, so :meth:`start_steps` raises it again); from
    :meth:`start_steps` on the first Ctrl-C only sets ``requested`` and a second one raises."""

    def __init__(self):
        self.requested = False
        self._raised = False
        self._in_steps = False
        self._previous = None

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def _handle(self, signum, frame):
        if self._in_steps and not self.requested:
            self.requested = True
            return
        self._raised = True
        raise KeyboardInterrupt

    def start_steps(self) -> None:
        """Before the first step: raise a Ctrl-C that was swallowed; then only flag the next."""
        if self._raised:
            raise KeyboardInterrupt
        self._in_steps = True

    def __exit__(self, *exc):
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)


def postfix(metrics: dict, val_loss: float | None, routine: dict | None,
            routine_on: bool) -> dict[str, str]:
    """The progress bar's loss, val loss and, when the routine diagnostic is on, ``next``."""
    shown = {"loss": f"{metrics['loss']:.4f}",
             "val": f"{val_loss:.4f}" if val_loss is not None else "-"}
    if routine_on:
        shown["next"] = f"{routine['offset_+1']:.2f}" if routine else "-"
    return shown


class _ProgressBar:
    """The tqdm bar of a run, from the first step on (its rate leaves out the compilation)."""

    def __init__(self, total: int, enabled: bool):
        self.total, self.enabled, self._bar = total, enabled, None

    def show(self, done: int, **postfix: str) -> None:
        """After each step: ``done`` steps completed, with ``postfix`` (loss, val, ...)."""
        if self._bar is None:
            self._bar = tqdm(total=self.total, initial=done, unit="step",
                             disable=not self.enabled, dynamic_ncols=True, desc="train")
        else:
            self._bar.update(1)
        self._bar.set_postfix(**postfix, refresh=False)

    def __enter__(self) -> _ProgressBar:
        return self

    def __exit__(self, *exc) -> None:
        if self._bar is not None:
            self._bar.close()
