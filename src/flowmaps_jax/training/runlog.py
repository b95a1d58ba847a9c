"""A run's records (``metrics.jsonl``: ``"train"``, ``"val"`` and ``"routine"`` records), its
checkpoints, the best val step and the closing summary; :mod:`flowmaps_jax.training.loop` calls
these."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import math
import pathlib
from collections.abc import Callable

import jax
import numpy as np

from flowmaps_jax.store import rundir
from flowmaps_jax.store.checkpoint_store import CheckpointSaveError, CheckpointStore
from flowmaps_jax.store.model_spec import DEFAULT_FAMILY
from flowmaps_jax.store.pretrained import HOLDS
from flowmaps_jax.store.rundir import METRICS
from flowmaps_jax.training import state as train_state
from flowmaps_jax.training.config import TrainConfig
from flowmaps_jax.untrusted_files import read_json

# --------------------------------------------------------------------------------------------
# metrics.jsonl and the checkpoints


class RunBook:
    """``metrics.jsonl`` and the checkpoint store of a run, with the metrics of the steps since
    the last train record (the window) and the best val loss and its step as of ``start_step``.

    kept: on resume, the lines ``metrics.jsonl`` is first rewritten with (None: append).
    window: the window a resumed run's checkpoint carried. primary: False on the other
    processes of a multi-host job (no metrics written).
    """

    def __init__(self, run_dir: pathlib.Path, cfg: TrainConfig, *, kept: list[str] | None,
                 window: dict | None, primary: bool = True, start_step: int = 0):
        self.run_dir, self.config = run_dir, cfg.to_dict()
        path = run_dir / METRICS
        if primary and kept is not None:
            rundir.write_atomic(path, "".join(line + "\n" for line in kept))
        self._file = rundir.open_append(path) if primary else None
        try:
            self.store = CheckpointStore(run_dir / "checkpoints", cfg.keep_last)
        except BaseException:
            self._close_file()
            raise
        window = window or {}
        self.best_loss, self.best_step = _best_as_of(window, kept, self.store, start_step)
        self.window: list[dict] = list(window.get("records", []))
        self.timed_steps = int(window.get("timed_steps", 0))  # compiled steps in the window
        self.step_seconds = float(window.get("step_seconds", 0.0))  # and their time only

    def add_step(self, metrics: dict, seconds: float | None) -> None:
        """One step's metrics; ``seconds`` None for a step that also compiled (not timed)."""
        self.window.append(metrics)
        if seconds is not None:
            self.timed_steps, self.step_seconds = self.timed_steps + 1, self.step_seconds + seconds

    def write_train(self, step: int, samples_per_step: int) -> None:
        """The train record of the window (its mean metrics and speed); the window restarts."""
        rate = self.timed_steps / self.step_seconds if self.step_seconds > 0 else 0.0
        record = {k: float(np.mean([m[k] for m in self.window])) for k in self.window[0]}
        record.update(kind="train", step=step, steps_per_sec=rate,
                      samples_per_sec=rate * samples_per_step)
        self._write(record)
        self.window, self.timed_steps, self.step_seconds = [], 0, 0.0

    def write_val(self, state, step: int, val_loss: float) -> None:
        """The val record of ``state``; a val loss that beats the best (after step 0) saves
        ``state`` as the ``best`` checkpoint."""
        improved = step > 0 and math.isfinite(val_loss) and (
            self.best_loss is None or val_loss < self.best_loss)
        if improved:
            self.store.save_best(state, self.config, val_loss,
                                 log_window=self.window_state(best=(val_loss, step)))
            self.best_loss, self.best_step = val_loss, step
        self._write({"kind": "val", "step": step, "val_loss": val_loss, "best": bool(improved)})

    def write_routine(self, step: int, metrics: dict) -> None:
        self._write({"kind": "routine", "step": step, **metrics})

    def save(self, state) -> None:
        """A checkpoint of ``state`` in ``last`` (a step already saved is not saved again)."""
        self.store.save(state, self.config, log_window=self.window_state())

    def window_state(self, best: tuple[float, int] | None = None) -> dict:
        """The window as JSON data, carried by every checkpoint, with the best val loss and its
        step so far (``best``: those the save itself makes)."""
        loss, step = (self.best_loss, self.best_step) if best is None else best
        return {"records": self.window, "timed_steps": self.timed_steps,
                "step_seconds": self.step_seconds, "best_val_loss": loss, "best_step": step}

    def latest_step(self) -> int | None:
        return self.store.latest_step()

    def save_failed(self, err: CheckpointSaveError, step: int) -> CheckpointSaveError:
        """``err`` (a failed checkpoint write) completed with what is saved and how to go on."""
        latest = self.store.latest_step()
        saved = (f"the saved checkpoints are intact (latest: step {latest})"
                 if latest is not None else "no checkpoint was saved yet (--resume starts the "
                 "run again from step 0)")
        return CheckpointSaveError(
            err.errno, f"{err}. Training stopped at step {step}; {saved}. Free some space, then "
            f"continue with python -m flowmaps_jax.train --resume --run-dir {self.run_dir}")

    def _write(self, record: dict) -> None:
        if self._file is not None:
            self._file.write(json.dumps(record) + "\n")
            self._file.flush()

    def _close_file(self) -> None:
        if self._file is not None:
            with contextlib.suppress(OSError):  # a full disk: the error in flight says so
                self._file.close()

    def close(self) -> None:
        self._close_file()
        self.store.close()

    def __enter__(self) -> RunBook:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _best_as_of(window: dict, kept: list[str] | None, store: CheckpointStore,
                start_step: int) -> tuple[float | None, int | None]:
    """(best val loss, its step) of a run as of ``start_step`` (see :class:`RunBook`)."""
    if "best_val_loss" in window:  # saved with the checkpoint the run continues
        loss, step = window["best_val_loss"], window.get("best_step")
        return (None if loss is None else float(loss)), (None if step is None else int(step))
    if kept is not None and jax.process_count() == 1:  # older checkpoints: the kept records
        best = (None, None)
        for line in kept:
            record = json.loads(line)
            if record.get("kind") == "val" and record.get("best") is True:
                best = (float(record["val_loss"]), int(record["step"]))
        return best
    step = store.best_step()
    if step is None or step > start_step:
        return None, None
    return store.best_val_loss, step


# --------------------------------------------------------------------------------------------
# The end of a run


@dataclasses.dataclass
class RunResult:
    """Outcome of :func:`flowmaps_jax.training.loop.run`: status "done", "stopped" (stop_at),
    "interrupted" or "nan"; step completed and that state (None after "nan"); best_val_loss at
    best_step (None before a val pass after step 0).
    """

    status: str
    step: int
    state: train_state.TrainState | None
    run_dir: pathlib.Path
    checkpoint_dir: pathlib.Path
    best_val_loss: float | None
    best_step: int | None = None


def print_summary(result: RunResult, total_steps: int, latest: int | None,
                  log: Callable[[str], None]) -> None:
    """How the run ended, where its checkpoints are (``latest``: the last saved step) and the
    commands that evaluate, export or resume it (the same for every world)."""
    status, step, ckpt_dir = result.status, result.step, result.checkpoint_dir
    best, best_step = result.best_val_loss, result.best_step
    headline = {"done": f"Finished {step} steps.",
                "stopped": f"Stopped after step {step} of {total_steps}.",
                "interrupted": f"Interrupted at step {step} of {total_steps}; checkpoint saved.",
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
    else:  # no val pass since step 0: the best falls back to the latest save
        log(f"  (no best-by-validation step yet: evaluate and search load step {latest})")
    log(f"Export it:    python -m flowmaps_jax.export --checkpoint {result.run_dir} --name "
        f"{_export_name(result.run_dir)}   (into {result.run_dir / 'export'}; the packaged "
        f"weights change only if --out names their folder)")
    if status != "done":
        log(f"Resume it:    python -m flowmaps_jax.train --resume --run-dir {result.run_dir}")


def _export_name(run_dir: pathlib.Path) -> str:
    """The pretrained name a run's model exports as (from its config.json)."""
    try:
        config = read_json("", run_dir / "config.json")
        kind = str(config.get("model_kind", DEFAULT_FAMILY))
        variance = config.get("model", {}).get("baseline_variance")
    except (OSError, ValueError, AttributeError):
        return DEFAULT_FAMILY
    return next((name for name, (family, held) in HOLDS.items()
                 if family == kind and held in (None, variance)), kind)


def write_routine_curve(run_dir: pathlib.Path, log: Callable[[str], None]) -> None:
    """routine_curve.png from the run's routine records (skipped when there are none)."""
    from flowmaps_jax.evaluation import routine

    records = routine.read_routine_records(run_dir / METRICS)
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
