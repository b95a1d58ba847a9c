"""``python -m flowmaps_jax.train``: train FlowMaps (or the MLP baseline) on FlowSim.

Examples::

    python -m flowmaps_jax.train                          # cpu preset, FlowMaps
    python -m flowmaps_jax.train --preset smoke --model mlp --set mlp_variance=learned
    python -m flowmaps_jax.train --steps 5000 --set model.dim=96 --set lr=5e-4
    python -m flowmaps_jax.train --resume --run-dir runs/flowmaps-cpu-20250101-120000

A run directory holds ``config.json`` (the resolved config), ``metrics.jsonl`` (one JSON record
per log interval: ``"kind": "train"`` with mean loss/grad_norm/lr and steps/s and samples/s over
the compiled steps only, or ``"kind": "val"`` with the EMA validation loss) and ``checkpoints/``
(see :mod:`flowmaps_jax.checkpoint`). The batch and noise of step i depend only on the state's
keys and i, so ``--resume`` continues a run exactly. Ctrl-C saves a checkpoint and exits; a
NaN/inf loss stops the run without saving the bad state (the last good checkpoint stays).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
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

from flowmaps_jax import checkpoint, training
from flowmaps_jax.config import (
    DEFAULT_PRESET,
    MODEL_KINDS,
    PRESETS,
    TrainConfig,
    apply_overrides,
    format_config,
    get_preset,
)
from flowmaps_jax.validation import check_int

EXIT_OK, EXIT_NAN, EXIT_INTERRUPTED = 0, 1, 130


@dataclasses.dataclass
class RunResult:
    """Outcome of :func:`run`.

    status: "done" (reached cfg.steps), "stopped" (reached stop_at), "interrupted" (Ctrl-C) or
        "nan" (non-finite loss; nothing saved for that state).
    step: steps completed in the final state; state: that TrainState (None after "nan").
    run_dir, checkpoint_dir: where outputs went; best_val_loss: best validation loss seen.
    """

    status: str
    step: int
    state: training.TrainState | None
    run_dir: pathlib.Path
    checkpoint_dir: pathlib.Path
    best_val_loss: float | None


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


def load_splits(cfg: TrainConfig, log: Callable[[str], None] = print):
    """(train scenes or None for endless data, validation scenes), generated in-process.

    The splits are fixed datasets (their seeds live in ``flowsim.scenes``), so they are cached
    per (simulator config, sizes) for later runs in the same process.
    """
    train_envs = cfg.train_envs if cfg.data == "train" else None
    key = (cfg.flowsim, train_envs, cfg.val_envs)
    if key not in _SPLIT_CACHE:
        from flowmaps_jax.flowsim.scenes import train_split, validation_split

        start = time.perf_counter()
        train = None
        if train_envs is not None:
            log(f"Generating the FlowSim training split ({train_envs} environments) ...")
            train = train_split(cfg.flowsim, num_envs=train_envs)
        log(f"Generating the FlowSim validation split ({cfg.val_envs} environments) ...")
        val = validation_split(cfg.flowsim, num_envs=cfg.val_envs)
        jax.block_until_ready((train, val))
        log(f"  data ready in {time.perf_counter() - start:.1f} s")
        _SPLIT_CACHE.clear()  # keep at most one dataset in memory
        _SPLIT_CACHE[key] = (train, val)
    return _SPLIT_CACHE[key]


_SPLIT_CACHE: dict = {}


class Compiled(typing.NamedTuple):
    """The jitted functions of a run: objective, fused train step, eval loss."""

    objective: training.Objective
    train_step: Callable
    eval_loss: Callable


def compiled_functions(cfg: TrainConfig) -> Compiled:
    """:class:`Compiled` for ``cfg``; cached so that several runs with the same computation in
    one process (tests, resume) compile once."""
    return _compiled_functions(_computational(cfg))


@functools.lru_cache(maxsize=2)
def _compiled_functions(cfg: TrainConfig) -> Compiled:
    objective = training.objective_for(cfg)
    return Compiled(objective=objective,
                    train_step=training.make_fused_train_step(cfg, objective),
                    eval_loss=training.make_eval_loss(cfg, objective))


def _computational(cfg: TrainConfig) -> TrainConfig:
    """``cfg`` with the fields that do not change the compiled functions reset (cache key)."""
    base = TrainConfig()
    return dataclasses.replace(cfg, log_every=base.log_every, val_every=base.val_every,
                               ckpt_every=base.ckpt_every, keep_last=base.keep_last,
                               run_dir=None, preset=base.preset, data=base.data,
                               routine_envs=base.routine_envs,
                               routine_samples=base.routine_samples)


class _MetricsLog:
    """Appends JSON records to ``metrics.jsonl``; on resume drops records past the restored step."""

    def __init__(self, path: pathlib.Path, resume_step: int | None):
        self.path = path
        if resume_step is not None and path.exists():
            kept = [line for line in path.read_text().splitlines()
                    if line.strip() and json.loads(line).get("step", 0) <= resume_step]
            path.write_text("".join(line + "\n" for line in kept))
        self._file = path.open("a")

    def write(self, record: dict) -> None:
        self._file.write(json.dumps(record) + "\n")
        self._file.flush()

    def close(self) -> None:
        self._file.close()


def run(cfg: TrainConfig, run_dir: str | pathlib.Path, *, resume: bool = False,
        stop_at: int | None = None, progress: bool = True,
        on_step: Callable[[int, dict], None] | None = None,
        log: Callable[[str], None] = print) -> RunResult:
    """Train per ``cfg`` into ``run_dir``; see the module docstring for what is written.

    resume: continue from the latest checkpoint in ``run_dir`` (ValueError if there is none).
    stop_at: stop after this step (saving a checkpoint) without changing the schedule, which
        always spans ``cfg.steps``. on_step(step, metrics): called after every step (tests).
    """
    run_dir = pathlib.Path(run_dir)
    ckpt_dir = run_dir / "checkpoints"
    if stop_at is not None and not check_int("stop_at", stop_at) <= cfg.steps:
        raise ValueError(f"stop_at must lie in 1..steps={cfg.steps}; got {stop_at}")
    if resume:
        checkpoint.resolve_checkpoint_dir(ckpt_dir if ckpt_dir.exists() else run_dir)
    log("Config:\n" + format_config(cfg))
    run_dir.mkdir(parents=True, exist_ok=True)
    cfg_dict = cfg.to_dict()
    (run_dir / "config.json").write_text(json.dumps(cfg_dict, indent=2) + "\n")

    train_scenes, val_scenes = load_splits(cfg, log)
    objective, step_fn, eval_fn = compiled_functions(cfg)
    val_batches = training.make_val_batches(cfg, val_scenes)

    if resume:
        state, _ = checkpoint.restore_latest(ckpt_dir, training.abstract_state(cfg, objective))
        log(f"Resumed from {ckpt_dir} at step {int(state.step)}")
    else:
        state = training.init_state(cfg, objective=objective)
    start = int(state.step)
    end = cfg.steps if stop_at is None else stop_at
    samples_per_step = cfg.batch_size * cfg.queries_per_scene

    store = checkpoint.CheckpointStore(ckpt_dir, cfg.keep_last)
    metrics_log = _MetricsLog(run_dir / "metrics.jsonl", start if resume else None)
    best = store.best_val_loss

    probe = None
    if cfg.routine_envs > 0:
        from flowmaps_jax import routine
        from flowmaps_jax.sample import Predictor

        probe = routine.build_probe(val_scenes, cfg.flowsim,
                                    min(cfg.routine_envs, val_scenes.num_envs), cfg.seed)
    last_routine: dict = {}

    def validate(step: int) -> float:
        nonlocal best, last_routine
        val_loss = float(eval_fn(state.ema_params, val_batches))
        improved = step > 0 and store.save_if_best(state, cfg_dict, val_loss)
        if improved:
            best = val_loss
        metrics_log.write({"kind": "val", "step": step, "val_loss": val_loss,
                           "best": bool(improved)})
        if probe is not None:
            predictor = Predictor.from_params(state.ema_params, cfg.model, cfg.model_kind,
                                              cfg.flowsim)
            last_routine = routine.routine_metrics(predictor, probe,
                                                   num_samples=cfg.routine_samples)
            metrics_log.write({"kind": "routine", "step": step, **last_routine})
        return val_loss

    status, step, last_val = "done", start, None
    window: list[dict] = []  # metrics since the last log record
    timed_steps, step_seconds = 0, 0.0  # compiled steps in the window and their time only
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
                        train_scenes is None or step % training.endless_chunk_steps(cfg) == 0):
                    train_scenes = training.endless_scenes(cfg, state.data_key, step)
                step_start = time.perf_counter()
                state, metrics = step_fn(state, train_scenes)
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
                    store.save(state, cfg_dict)
                if on_step is not None:
                    on_step(step, metrics)
            else:
                status = "done" if step == cfg.steps else "stopped"
            if status != "nan":
                store.save(state, cfg_dict)
    finally:
        if bar is not None:
            bar.close()
        metrics_log.close()
        latest = store.latest_step()
        store.close()

    if probe is not None:
        _write_routine_curve(run_dir, log)
    _print_summary(log, status, step, cfg, run_dir, ckpt_dir, latest, best)
    return RunResult(status=status, step=step, state=None if status == "nan" else state,
                     run_dir=run_dir, checkpoint_dir=ckpt_dir, best_val_loss=best)


def _write_routine_curve(run_dir: pathlib.Path, log: Callable[[str], None]) -> None:
    """routine_curve.png from the run's routine records (skipped when there are none)."""
    from flowmaps_jax import routine

    records = routine.read_routine_records(run_dir / "metrics.jsonl")
    if records:
        routine.plot_learning_curve(records, title=run_dir.name).savefig(
            run_dir / "routine_curve.png", dpi=100)
        last = records[-1]
        log(f"Routines at step {last['step']} (one step ahead, exact 0.2 / 0.7 / 0.1): "
            f"offsets 0 / +1 / +2 = {last['offset_0']:.2f} / {last['offset_+1']:.2f} / "
            f"{last['offset_+2']:.2f}; TV {last['tv']:.3f}, search cost ratio "
            f"{last['search_cost_ratio']:.3f} → {run_dir / 'routine_curve.png'}")


def _print_summary(log, status, step, cfg, run_dir, ckpt_dir, latest, best) -> None:
    headline = {"done": f"Finished {step} steps.",
                "stopped": f"Stopped after step {step} of {cfg.steps}.",
                "interrupted": f"Interrupted at step {step} of {cfg.steps}; checkpoint saved.",
                "nan": "Training diverged (non-finite loss)."}[status]
    log(headline)
    if latest is None:
        log(f"No checkpoint was saved in {ckpt_dir}.")
        return
    best_text = f"; best validation loss {best:.5f}" if best is not None else ""
    log(f"Checkpoint: {ckpt_dir.absolute()} (latest step {latest}{best_text})")
    log(f"Evaluate it:  python -m flowmaps_jax.evaluate --checkpoint {ckpt_dir}")
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
    parser.add_argument("--model", choices=MODEL_KINDS, default=None,
                        help="flowmaps (default) or mlp (Gaussian baseline)")
    parser.add_argument("--run-dir", default=None,
                        help="output directory (default runs/<model>-<preset>-<timestamp>)")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --run-dir from its latest checkpoint")
    parser.add_argument("--steps", type=int, default=None, help="total training steps")
    parser.add_argument("--stop-at", type=int, default=None,
                        help="stop (with a checkpoint) after this step; resume later")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE",
                        help="override any config field, e.g. --set model.dim=64 --set lr=1e-3")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


def resolve_config(args: argparse.Namespace) -> tuple[TrainConfig, pathlib.Path]:
    """The run's config and directory from parsed arguments (ValueError on bad input)."""
    if args.resume:
        if args.run_dir is None:
            raise ValueError("--resume needs --run-dir (the run to continue)")
        if args.preset is not None or args.model is not None:
            raise ValueError("--resume uses the run's saved config; change fields with --set, "
                             "not --preset/--model")
        run_dir = pathlib.Path(args.run_dir)
        config_path = run_dir / "config.json"
        if config_path.exists():
            try:
                cfg = TrainConfig.from_dict(json.loads(config_path.read_text()))
            except (json.JSONDecodeError, TypeError) as err:
                raise ValueError(f"cannot read {config_path}: {err}") from err
        else:
            cfg = checkpoint.load_config(run_dir)
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
        run_dir = pathlib.Path(args.run_dir) if args.run_dir else default_run_dir(cfg)
    return cfg, run_dir


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit code (0 ok, 1 non-finite loss, 130 interrupted)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        cfg, run_dir = resolve_config(args)
        result = run(cfg, run_dir, resume=args.resume, stop_at=args.stop_at,
                     progress=not args.no_progress)
    except ValueError as err:
        parser.error(str(err))
    except KeyboardInterrupt:  # outside the step loop (data, compilation) or a second Ctrl-C
        print("\nInterrupted; the current state was not saved.", file=sys.stderr)
        return EXIT_INTERRUPTED
    return {"nan": EXIT_NAN, "interrupted": EXIT_INTERRUPTED}.get(result.status, EXIT_OK)


if __name__ == "__main__":
    sys.exit(main())
