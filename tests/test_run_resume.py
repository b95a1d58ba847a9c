"""A stopped run continues exactly, in every world: resumed equals straight, Ctrl-C saves and
stops, a damaged newest checkpoint is one line naming the intact one, a kill between any two
saves resumes to the same records, and Ctrl-C while the data is made exits cleanly.

The runs are the session's smoke runs of each world (tests/conftest.py, :class:`SmokeRuns`);
a test that changes one works on a copy.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys

import jax
import numpy as np
import pytest
from support import run_cli

from flowmaps_jax.evaluation import cli as eval_cli
from flowmaps_jax.predictor import load
from flowmaps_jax.store import checkpoints, rundir
from flowmaps_jax.store.checkpoint_store import CheckpointStore
from flowmaps_jax.training import cli, loop

# A damaged checkpoint makes orbax leave un-awaited coroutines behind ("unraisable" warnings).
pytestmark = pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")

WORLDS = ["flowsim", "homes", "recorded"]
SRC = pathlib.Path(__file__).resolve().parents[1] / "src"
SILENT = dict(progress=False, log=lambda _: None)
# The environment without the suite's persistent XLA cache (tests/conftest.py).
_UNCACHED = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}


@pytest.fixture(params=WORLDS)
def runs(request):
    """The world's :class:`SmokeRuns` (tests/conftest.py)."""
    return request.getfixturevalue(f"{request.param}_runs")


def _records(run_dir: pathlib.Path) -> list[dict]:
    """metrics.jsonl without its timings (steps/s, samples/s)."""
    return [{k: v for k, v in json.loads(line).items() if not k.endswith("_per_sec")}
            for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


def _snapshot(run_dir: pathlib.Path) -> dict[str, bytes]:
    return {str(p.relative_to(run_dir)): p.read_bytes()
            for p in sorted(run_dir.rglob("*")) if p.is_file()}


def _leaves(run_dir: pathlib.Path, which: str = "latest") -> list[np.ndarray]:
    return [np.asarray(x) for x in jax.tree.leaves(checkpoints.restore(run_dir,
                                                                       which=which).state)]


_main = run_cli  # tests/support.py (capfd here: the C-level streams too)


# --------------------------------------------------------------------------- resume, Ctrl-C


def test_a_resumed_run_writes_and_saves_what_a_run_never_stopped_does(runs):
    """Ctrl-C off the log and checkpoint intervals, then ``--resume``: the same data, batches,
    noise, records (the steps since the last record travel in the checkpoint), best step and
    weights as the run never stopped."""
    assert _records(runs.resumed) == _records(runs.straight)
    assert "Resumed from" in runs.resumed_printed
    window = checkpoints.restore(runs.stopped).meta["log_window"]["records"]
    assert len(window) == runs.stop_at % runs.cfg.log_every
    for which in ("latest", "best"):
        assert checkpoints.saved_steps(runs.resumed, which) == checkpoints.saved_steps(
            runs.straight, which)
        for a, b in zip(_leaves(runs.resumed, which), _leaves(runs.straight, which),
                        strict=True):
            np.testing.assert_array_equal(a, b)


def test_ctrl_c_saves_the_step_it_stopped_at(runs):
    assert runs.stopped.is_dir()  # trained on first use: Ctrl-C from a step callback
    result, stop = runs.interrupted, runs.stop_at
    assert result.status == "interrupted" and result.step == stop
    every = runs.cfg.ckpt_every
    assert checkpoints.saved_steps(runs.stopped) == [stop - stop % every, stop]
    assert checkpoints.restore(runs.stopped).step == stop
    assert not (runs.stopped / rundir.LOCK_NAME).exists()


@pytest.mark.parametrize("world, change, message", [
    ("flowsim", ["--set", "model.dim=64"], "--resume cannot change model.dim"),
    ("homes", ["--set", "homes.num_hours=120"], "--resume cannot change homes.num_hours"),
    ("recorded", ["--data", "{tmp}"], "--data cannot change on --resume"),
])
def test_resume_refuses_a_changed_setting_and_leaves_the_run(world, change, message, request,
                                                             tmp_path, capfd):
    run = request.getfixturevalue(f"{world}_runs").copy("stopped", tmp_path)
    before = _snapshot(run)
    code, _, err = _main(cli.main, ["--resume", "--run-dir", str(run),
                                    *[a.format(tmp=tmp_path) for a in change]], capfd)
    assert code == 2 and message in err, err
    assert _snapshot(run) == before


def test_ctrl_c_during_data_generation_exits_cleanly(tmp_path):
    """The real command in a subprocess: 130 and a short message, not SIGSEGV."""
    # A pytest-xdist worker ignores SIGINT, and a child would inherit that: the command gets the
    # handler a terminal gives it from a small launcher, not from a preexec_fn (which makes
    # subprocess fork() this multithreaded JAX process, which JAX warns about).
    launch = ("import runpy, signal, sys; "
              "signal.signal(signal.SIGINT, signal.default_int_handler); "
              "sys.argv[0] = 'flowmaps_jax.train'; "
              "runpy.run_module('flowmaps_jax.train', run_name='__main__', alter_sys=True)")
    proc = subprocess.Popen(
        [sys.executable, "-u", "-c", launch, "--preset", "smoke", "--set", "routine_envs=0",
         "--no-progress", "--run-dir", str(tmp_path / "run")],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env=_UNCACHED)  # compiling for real, so the signal lands mid-compilation, not after
    out = io.StringIO()
    for line in proc.stdout:
        out.write(line)
        if line.startswith("Generating the FlowSim training split"):
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=1.0)  # into the compilation of the simulator
            proc.send_signal(signal.SIGINT)
            break
    out.write(proc.stdout.read())
    assert proc.wait(timeout=120) == cli.EXIT_INTERRUPTED, out.getvalue()
    assert "Interrupted" in out.getvalue()
    assert not (tmp_path / "run" / rundir.LOCK_NAME).exists()


def test_a_ctrl_c_python_swallowed_before_the_steps_still_stops_the_run():
    """A KeyboardInterrupt raised inside a garbage-collection callback is only printed
    ("Exception ignored in ... _xla_gc_callback"): seen once under load, when the run then
    trained to the end. The flag raises it again before the first step; in the step loop the
    first Ctrl-C only asks to stop, a second one raises."""
    with loop.StopFlag() as stop:
        with contextlib.suppress(KeyboardInterrupt):  # what Python does in a gc callback
            stop._handle(signal.SIGINT, None)
        with pytest.raises(KeyboardInterrupt):
            stop.start_steps()
    with loop.StopFlag() as stop:
        stop.start_steps()
        stop._handle(signal.SIGINT, None)
        assert stop.requested
        with pytest.raises(KeyboardInterrupt):
            stop._handle(signal.SIGINT, None)
    assert signal.getsignal(signal.SIGINT) != stop._handle  # the handler is put back


# --------------------------------------------------------------------------- a kill between saves


class _Killed(BaseException):
    """A kill -9 between two saves (nothing after it runs)."""


@pytest.mark.parametrize("kill_after", [0, 1, 2, 3, 4])
def test_a_run_killed_between_any_two_saves_resumes_to_the_same_records(
        flowsim_runs, tmp_path, monkeypatch, kill_after):
    """kill_after: the saves done before the kill (0: killed at step 7, before any save; 3:
    best/20 saved and last/20 not)."""
    reference = flowsim_runs.straight
    assert flowsim_runs.saves == [("best", 10), ("last", 10), ("best", 20), ("last", 20)]
    done, original = [], CheckpointStore._write

    def write(self, manager, step, *args, **kwargs):
        original(self, manager, step, *args, **kwargs)
        done.append(step)
        if len(done) == kill_after:
            raise _Killed

    def on_step(step, metrics):
        if kill_after == 0 and step == 7:
            raise _Killed

    run_dir = tmp_path / "run"
    with monkeypatch.context() as mp:
        mp.setattr(CheckpointStore, "_write", write)
        with pytest.raises(_Killed):
            loop.run(flowsim_runs.cfg, run_dir, on_step=on_step, **SILENT)
    result = loop.run(flowsim_runs.cfg, run_dir, resume=True, **SILENT)
    assert result.status == "done" and result.best_step == 20
    assert _records(run_dir) == _records(reference)
    assert checkpoints.saved_steps(run_dir, "best") == [20]


# --------------------------------------------------------------------------- damaged checkpoints


def _damage(step_dir: pathlib.Path, how: str) -> None:
    state = step_dir / "state"
    if how == "flipped bytes":  # 64 bytes in the middle of every data file (one may be unread)
        for data in (p for p in state.rglob("*") if p.is_file() and p.parent.name == "d"):
            raw = bytearray(data.read_bytes())
            middle = len(raw) // 2
            raw[middle:middle + 64] = bytes(b ^ 0xFF for b in raw[middle:middle + 64])
            data.write_bytes(bytes(raw))
    elif how == "no data folder":
        shutil.rmtree(state / "ocdbt.process_0")
    elif how == "a data file gone":
        data = max((state / "ocdbt.process_0" / "d").iterdir(), key=lambda p: p.stat().st_size)
        data.unlink()
    elif how == "no index":
        for index in (state / "d").iterdir():
            index.unlink()


def test_a_damaged_newest_step_is_one_line_naming_the_intact_one(runs, tmp_path, capfd):
    """Every kind of damage to the newest step: restoring it is one line naming it and the
    newest intact step, nothing on the terminal and nothing changed. Every kind is that one
    ValueError of the store, so the commands (whose wording does not depend on the kind) run on
    one of them: resuming it and evaluating it are one line each, and the intact step loads."""
    stop = runs.stop_at
    intact = stop - stop % runs.cfg.ckpt_every
    copies = {how: runs.copy("stopped", tmp_path / how)
              for how in ("flipped bytes", "no data folder", "a data file gone", "no index")}
    for how, run in copies.items():
        _damage(run / "checkpoints" / "last" / str(stop), how)
    before = {how: _snapshot(run) for how, run in copies.items()}
    capfd.readouterr()
    for how, run in copies.items():
        with pytest.raises(ValueError) as info:
            checkpoints.restore(run, which="latest")
        message = str(info.value)
        assert "\n" not in message and len(message) < 1000 and "TensorStore" not in message, how
        assert f"last/{stop}" in message, (how, message)
        assert f"newest intact checkpoint is step {intact}" in message, (how, message)
        captured = capfd.readouterr()
        assert captured.err == "" and captured.out == "", (how, captured.err[-2000:])
    run = copies["flipped bytes"]
    assert load(run, step=intact).step == intact
    code, _, err = _main(cli.main, ["--resume", "--run-dir", str(run)], capfd)
    errors = [line for line in err.splitlines() if "error:" in line]
    assert code == 2 and len(errors) == 1, err[-3000:]
    assert str(run / "checkpoints" / "last" / str(stop)) in errors[0]
    assert f"newest intact checkpoint is step {intact}" in errors[0]
    assert f"--resume --run-dir {run} --from-step {intact}" in errors[0]
    code, _, err = _main(eval_cli.main, ["--checkpoint", str(run), "--which", "latest",
                                         "--out", str(tmp_path / "eval"), "--no-progress"], capfd)
    assert code == 2 and len(err.strip().splitlines()) == 1, err[-2000:]  # its predictor.load
    assert f"last/{stop}" in err and f"newest intact checkpoint is step {intact}" in err, err
    assert {how: _snapshot(run) for how, run in copies.items()} == before


def test_the_command_on_a_damaged_step_prints_one_line_and_from_step_resumes(flowsim_runs,
                                                                              tmp_path, capfd):
    """The real command in a subprocess: nothing but the one line on its terminal (what a
    test in-process cannot see: logging set up at start-up, messages at exit); then
    ``--from-step`` resumes the intact step, the later ones moved aside. In the 2-D world
    only: neither depends on the world (the line is the store's, the same for every world's
    checkpoint, as the test above checks; moving steps aside is the store's too)."""
    run, stop = flowsim_runs.copy("stopped", tmp_path), flowsim_runs.stop_at
    intact = stop - stop % flowsim_runs.cfg.ckpt_every
    _damage(run / "checkpoints" / "last" / str(stop), "no data folder")
    before = _snapshot(run)
    resume = ["--resume", "--run-dir", str(run)]
    env = {**os.environ, "PYTHONPATH": f"{SRC}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    done = subprocess.run([sys.executable, "-m", "flowmaps_jax.train", *resume, "--no-progress"],
                          env=env, capture_output=True, text=True, timeout=300)
    err = done.stderr
    noise = [line for line in err.splitlines()
             if not line.startswith(("usage:", " ")) and "error:" not in line]
    assert not noise and "Exception ignored" not in err, err[-3000:]
    errors = [line for line in err.splitlines() if "error:" in line]
    assert done.returncode == 2 and len(errors) == 1, err[-3000:]
    assert f"last/{stop}" in errors[0] and f"newest intact checkpoint is step {intact}" in errors[0]
    assert _snapshot(run) == before
    code, out, _ = _main(cli.main, [*resume, "--from-step", str(intact), "--stop-at",
                                    str(stop + 1), "--no-progress"], capfd)
    assert code == 0 and f"Moved the later checkpoints (steps [{stop}]) aside" in out
    assert checkpoints.saved_steps(run) == [intact, stop + 1]
    train = [r["step"] for r in _records(run) if r["kind"] == "train"]
    assert train[-1] == stop + 1 and train == sorted(set(train))  # none twice
