"""A run directory belongs to one run; damaged, non-finite or unwritable state never passes
silently (issue 12).

All trainings use the smoke preset without the routine diagnostic (``routine_envs`` does not
change the compiled functions, so they share the compilation of the other training tests) and
start from copies of two module-scoped runs: one straight, one interrupted at step 12.
"""

import contextlib
import dataclasses
import io
import json
import math
import os
import pathlib
import shutil
import signal
import socket
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
import pytest

from flowmaps_jax.predictor import load
from flowmaps_jax.store import checkpoints, rundir
from flowmaps_jax.training import cli, loop
from flowmaps_jax.training.config import get_preset

# A damaged checkpoint makes orbax leave un-awaited coroutines behind ("unraisable" warnings).
pytestmark = pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")

CFG = dataclasses.replace(get_preset("smoke"), routine_envs=0)
QUIET = ["--preset", "smoke", "--set", "routine_envs=0", "--no-progress"]
# The environment without the suite's persistent XLA cache (tests/conftest.py).
_UNCACHED = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
TIMING = ("steps_per_sec", "samples_per_sec")


def _records(run_dir):
    lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    return [{k: v for k, v in json.loads(line).items() if k not in TIMING} for line in lines]


def _snapshot(run_dir):
    """Every file under run_dir with its bytes (to check that nothing was rewritten)."""
    return {str(p.relative_to(run_dir)): p.read_bytes()
            for p in sorted(run_dir.rglob("*")) if p.is_file()}


def _cli(argv, capsys):
    """``main(argv)``: (exit code, stdout, stderr); argparse errors exit with 2."""
    try:
        code = cli.main(argv)
    except SystemExit as exit_info:
        code = exit_info.code
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """{"straight": 20 steps in one go, "at12": interrupted (Ctrl-C) at step 12 (not a multiple
    of log_every=5; last/ holds 10 and 12, best/ 10), "resumed": a copy of at12 resumed to 20}."""
    root = tmp_path_factory.mktemp("runs")
    silent = dict(progress=False, log=lambda _: None)
    loop.run(CFG, root / "straight", **silent)

    def ctrl_c(step, metrics):
        if step == 12:
            os.kill(os.getpid(), signal.SIGINT)

    assert loop.run(CFG, root / "at12", on_step=ctrl_c, **silent).status == "interrupted"
    shutil.copytree(root / "at12", root / "resumed")
    assert loop.run(CFG, root / "resumed", resume=True, **silent).status == "done"
    return {name: root / name for name in ("straight", "at12", "resumed")}


@pytest.fixture
def at12(runs, tmp_path):
    """A fresh copy of the run interrupted at step 12."""
    return pathlib.Path(shutil.copytree(runs["at12"], tmp_path / "run"))


# --------------------------------------------------------------------------------------------
# Resume exactness


def test_a_run_resumed_off_the_log_interval_logs_what_a_straight_run_logs(runs):
    straight, resumed = _records(runs["straight"]), _records(runs["resumed"])
    assert [r["step"] for r in resumed if r["kind"] == "train"] == [5, 10, 15, 20]
    assert len(straight) == len(resumed)
    for a, b in zip(straight, resumed, strict=True):  # record 15 averages steps 11..15
        assert a.keys() == b.keys() and a["kind"] == b["kind"] and a["step"] == b["step"]
        for key in a:
            if isinstance(a[key], float):
                assert math.isclose(a[key], b[key], rel_tol=1e-6, abs_tol=1e-7), (a, b, key)
    window = checkpoints.restore(runs["at12"]).meta["log_window"]
    assert len(window["records"]) == 2  # steps 11 and 12 travel in the checkpoint


# --------------------------------------------------------------------------------------------
# One run per directory


def test_a_new_run_in_a_non_empty_run_dir_is_refused(at12, capsys):
    before = _snapshot(at12)
    code, _, err = _cli([*QUIET, "--run-dir", str(at12)], capsys)
    assert code == 2 and f"run directory {at12} is not empty" in err
    assert "--resume" in err and "--overwrite" in err
    assert _snapshot(at12) == before


def test_overwrite_moves_the_old_run_aside(at12, capsys):
    code, out, _ = _cli([*QUIET, "--overwrite", "--stop-at", "1", "--run-dir", str(at12)],
                        capsys)
    assert code == 0
    (old,) = at12.parent.glob("run.old-*")
    assert f"moved the old run in {at12} to {old}" in out
    assert checkpoints.saved_steps(old) == [10, 12]  # the old run, untouched
    assert checkpoints.saved_steps(at12) == [1]  # the new run alone
    assert [r["step"] for r in _records(at12)] == [0, 1]
    assert not (at12 / rundir.LOCK_NAME).exists()


def test_resume_refuses_changes_to_the_model_without_touching_the_run(at12, capsys):
    before = _snapshot(at12)
    for override, field in (("model.dim=64", "model.dim"), ("lr=0.5", "lr"),
                            ("seed=3", "seed"), ("data=endless", "data")):
        code, _, err = _cli(["--resume", "--run-dir", str(at12), "--set", override], capsys)
        assert code == 2 and f"--resume cannot change {field}" in err, err
    assert _snapshot(at12) == before
    with pytest.raises(ValueError, match="model_kind"):
        loop.run(dataclasses.replace(CFG, family="mlp"), at12, resume=True)
    assert _snapshot(at12) == before


def test_a_live_lock_keeps_a_second_process_out(at12, capsys):
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (at12 / rundir.LOCK_NAME).write_text(f"{sleeper.pid} {socket.gethostname()}\n")
        before = _snapshot(at12)
        code, _, err = _cli(["--resume", "--run-dir", str(at12)], capsys)
        assert code == 2 and f"in use by process {sleeper.pid}" in err
        assert _snapshot(at12) == before
    finally:
        sleeper.kill()
        sleeper.wait()


def test_a_stale_lock_is_taken_over_and_every_lock_is_released(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (tmp_path / rundir.LOCK_NAME).write_text(f"{dead.pid} {socket.gethostname()}\n")
    said = []
    lock = rundir.RunLock(tmp_path, said.append)
    assert said == [f"Took over the stale lock {tmp_path / rundir.LOCK_NAME} of process "
                    f"{dead.pid}, which is no longer running."]
    with pytest.raises(ValueError, match=f"in use by process {os.getpid()}"):
        rundir.RunLock(tmp_path)  # held: also within one process
    lock.release()
    assert list(tmp_path.iterdir()) == []
    with rundir.claim(tmp_path / "new", resume=False):
        assert (tmp_path / "new" / rundir.LOCK_NAME).exists()
    assert not (tmp_path / "new").exists()  # created by the claim, nothing written: removed


def test_a_run_dir_that_cannot_hold_a_run_is_a_value_error(tmp_path, monkeypatch, capsys):
    a_file = tmp_path / "file"
    a_file.write_text("x")
    for path, fragment in ((a_file, "is a file"), (a_file / "run", "which is a file")):
        code, _, err = _cli([*QUIET, "--run-dir", str(path)], capsys)
        assert code == 2 and fragment in err
        with pytest.raises(ValueError, match=fragment):
            loop.run(CFG, path)
    monkeypatch.setattr(os, "access", lambda *args, **kwargs: False)  # as for a non-root user
    with pytest.raises(ValueError, match="not writable"):
        loop.run(CFG, tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_a_half_written_metrics_line_does_not_block_resume(at12):
    metrics = at12 / "metrics.jsonl"
    with metrics.open("a") as file:
        file.write('{"kind": "train", "step": 13, "lo')
    said = []
    result = loop.run(CFG, at12, resume=True, stop_at=13, progress=False, log=said.append)
    assert result.status == "stopped"
    assert any(f"Dropped the half-written last line of {metrics}" in line for line in said)
    assert [r["step"] for r in _records(at12)][-1] == 13


def test_a_bad_metrics_line_inside_the_file_is_named_before_anything_is_written(at12):
    lines = (at12 / "metrics.jsonl").read_text().splitlines()
    lines[1] = "not json"
    (at12 / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    before = _snapshot(at12)
    with pytest.raises(ValueError, match=f"{at12 / 'metrics.jsonl'} line 2"):
        loop.run(CFG, at12, resume=True)
    assert _snapshot(at12) == before


# --------------------------------------------------------------------------------------------
# Integrity of checkpoints


def _flip_bytes(step_dir, count=64):
    """XOR ``count`` bytes in the middle of the largest data file of a saved step."""
    data = max((p for p in (step_dir / "state").rglob("*") if p.is_file() and p.parent.name == "d"),
               key=lambda p: p.stat().st_size)
    raw = bytearray(data.read_bytes())
    middle = len(raw) // 2
    raw[middle:middle + count] = bytes(b ^ 0xFF for b in raw[middle:middle + count])
    data.write_bytes(bytes(raw))


def test_a_damaged_newest_step_names_the_intact_one_and_from_step_resumes_it(at12, capsys):
    _flip_bytes(at12 / "checkpoints" / "last" / "12")
    before = _snapshot(at12)
    code, _, err = _cli(["--resume", "--run-dir", str(at12)], capsys)
    assert code == 2 and str(at12 / "checkpoints" / "last" / "12") in err
    assert "The newest intact checkpoint is step 10" in err
    assert f"--resume --run-dir {at12} --from-step 10" in err and "step=10)" in err
    with pytest.raises(ValueError, match="newest intact checkpoint is step 10"):
        load(at12, which="latest")
    assert load(at12, step=10).step == 10
    assert _snapshot(at12) == before
    code, out, _ = _cli(["--resume", "--run-dir", str(at12), "--from-step", "10", "--stop-at",
                         "11", "--no-progress"], capsys)
    assert code == 0 and "Moved the later checkpoints (steps [12]) aside" in out
    assert checkpoints.saved_steps(at12) == [10, 11]
    assert [r["step"] for r in _records(at12) if r["kind"] == "train"] == [5, 10, 11]


def test_a_non_finite_state_is_not_saved_and_stops_the_run(tmp_path, monkeypatch):
    objective, step_fn, eval_fn = loop.compiled_functions(CFG)

    def blows_up_at_10(state, scenes):  # finite loss, but the new params hold NaN (lr=1e30)
        state, metrics = step_fn(state, scenes)
        if int(state.step) == 10:
            state = state.replace(params=jax.tree.map(lambda x: x * jnp.nan, state.params))
        return state, metrics

    monkeypatch.setattr(loop, "compiled_functions",
                        lambda cfg, mesh=None: loop.Compiled(objective, blows_up_at_10,
                                                              eval_fn))
    said = []
    cfg = dataclasses.replace(CFG, ckpt_every=5)
    result = loop.run(cfg, tmp_path, progress=False, log=said.append)
    assert result.status == "nan" and result.step == 10 and result.state is None
    assert any("refusing to save step 10" in line and "params/" in line for line in said)
    assert checkpoints.saved_steps(tmp_path) == [5]
    assert np.isfinite(load(tmp_path, which="latest").params["query_pos"]).all()


def test_a_full_disk_stops_with_one_short_message(at12, monkeypatch, capsys):
    def full_disk(*args, **kwargs):
        for _ in range(100):
            print("RuntimeError: Event loop is closed", file=sys.stderr)
        raise ValueError("RESOURCE_EXHAUSTED: Failed writing: No space left on device "
                         "[os_error_code='28']")

    monkeypatch.setattr(ocp.CheckpointManager, "save", full_disk)
    code, _, err = _cli(["--resume", "--run-dir", str(at12), "--stop-at", "13",
                         "--no-progress"], capsys)
    assert code == cli.EXIT_WRITE_FAILED
    assert err.count("\n") == 1 and "No space left on device" in err
    assert "Event loop" not in err and f"--resume --run-dir {at12}" in err
    assert checkpoints.saved_steps(at12) == [10, 12]
    assert not (at12 / rundir.LOCK_NAME).exists()


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
        [sys.executable, "-u", "-c", launch, *QUIET, "--run-dir", str(tmp_path / "run")],
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


def test_resume_says_it_replaces_a_damaged_config_json(at12):
    """``--resume`` replaced a damaged config.json with the checkpoint's config silently."""
    from flowmaps_jax.training import resume

    for damage in ("{not json", "[1, 2]", '{"model": 3}'):
        (at12 / "config.json").write_text(damage)
        lines = []
        cfg = resume.resume_config(at12, None, log=lines.append)
        assert cfg == CFG and len(lines) == 1, lines
        assert lines[0].startswith(f"{at12 / 'config.json'} is unreadable (")
        assert "resuming with the config saved in the checkpoint" in lines[0]
    (at12 / "config.json").unlink()  # missing: nothing to say
    lines = []
    assert resume.resume_config(at12, None, log=lines.append) == CFG and not lines
