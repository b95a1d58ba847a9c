"""A run directory belongs to one run: a new run never writes into another's folder, a lock
keeps a second process out, nothing is written through a symbolic link, every check comes before
the first write, and what is damaged, non-finite or unwritable stops the run with one line.

The runs are copies of the session's 2-D smoke run stopped (Ctrl-C) at step 12 (``at12``,
tests/conftest.py); new runs use the smoke preset without the routine diagnostic.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import pathlib
import shutil
import socket
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
import pytest
from support import error_line, only_error_line, run_cli, unsaved_run

from flowmaps_jax import export as export_cli
from flowmaps_jax.predictor import load
from flowmaps_jax.store import checkpoints, rundir
from flowmaps_jax.store.checkpoint_store import CheckpointStore
from flowmaps_jax.training import cli as train_cli
from flowmaps_jax.training import loop, resume
from flowmaps_jax.training.config import get_preset

# A damaged checkpoint makes orbax leave un-awaited coroutines behind ("unraisable" warnings).
pytestmark = pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")

SMOKE = get_preset("smoke")  # at12's config (tests/conftest.py)
CFG = dataclasses.replace(SMOKE, routine_envs=0)  # new runs
QUIET = ["--preset", "smoke", "--set", "routine_envs=0", "--no-progress"]


_cli, _error_line = run_cli, error_line  # tests/support.py


_one_line = only_error_line  # tests/support.py


def _unsaved_run(run_dir: pathlib.Path, cfg=CFG) -> pathlib.Path:
    return unsaved_run(run_dir, cfg.to_dict())


TIMING = ("steps_per_sec", "samples_per_sec")


def _records(run_dir):
    lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    return [{k: v for k, v in json.loads(line).items() if k not in TIMING} for line in lines]


def _snapshot(run_dir):
    """Every file under run_dir with its bytes (to check that nothing was rewritten)."""
    return {str(p.relative_to(run_dir)): p.read_bytes()
            for p in sorted(run_dir.rglob("*")) if p.is_file()}


# --------------------------------------------------------- checks before writes


def test_resume_into_a_checkpoint_directory_is_refused(tmp_path, capsys):
    ckpt = tmp_path / "run" / "checkpoints"
    (ckpt / "last" / "10").mkdir(parents=True)
    (ckpt / "best").mkdir()
    before = sorted(p.name for p in ckpt.rglob("*"))
    code, _, err = _cli(train_cli.main, ["--resume", "--run-dir", str(ckpt), "--no-progress"],
                        capsys)
    assert code == 2 and "is a checkpoint directory" in _one_line(err)
    assert sorted(p.name for p in ckpt.rglob("*")) == before


def test_a_run_without_checkpoint_starts_again(tmp_path):
    """Killed before its first save: --resume starts it again from step 0, and so does a new
    run without --overwrite; a config.json that is not the checkpoints' is refused."""
    silent = dict(progress=False, log=lambda _: None)
    resumed = _unsaved_run(tmp_path / "resumed")
    result = train_cli.run(CFG, resumed, resume=True, stop_at=1, **silent)
    assert result.status == "stopped" and result.step == 1
    records = [json.loads(line) for line in (resumed / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records] == [0, 1]  # the old run's record is gone
    assert (resumed / "checkpoints" / "last" / "1").is_dir()

    fresh = _unsaved_run(tmp_path / "fresh")
    outside = tmp_path / "outside.png"
    outside.write_bytes(b"keep")
    (fresh / "routine_curve.png").symlink_to(outside)
    logs = []
    assert train_cli.run(CFG, fresh, stop_at=1, progress=False, log=logs.append).step == 1
    assert any("saved no checkpoint" in line for line in logs)
    assert outside.read_bytes() == b"keep" and not (fresh / "routine_curve.png").exists()

    # A config.json of another model does not supply steps (or anything) on --resume.
    other = dataclasses.replace(CFG, model=dataclasses.replace(CFG.model, dim=64), steps=999)
    (resumed / "config.json").write_text(json.dumps(other.to_dict()))
    args = train_cli.build_parser().parse_args(["--resume", "--run-dir", str(resumed)])
    with pytest.raises(ValueError, match="is not the config of the run's checkpoints"):
        train_cli.resolve_config(args)


def test_resume_of_a_run_with_nothing_to_start_from(tmp_path, capsys):
    run_dir = tmp_path / "run"
    (run_dir / "checkpoints" / "last").mkdir(parents=True)
    code, _, err = _cli(train_cli.main, ["--resume", "--run-dir", str(run_dir)], capsys)
    assert code == 2 and "no checkpoint and no config.json" in _one_line(err)


# -------------------------------------------------------------- untrusted files


def test_no_write_through_a_symlink_in_a_run_dir(tmp_path):
    outside = tmp_path / "outside.txt"
    outside.write_text("keep")
    run_dir = tmp_path / "run"
    (run_dir / "checkpoints" / "last" / "10").mkdir(parents=True)
    (run_dir / "routine_curve.png").symlink_to(outside)
    with pytest.raises(ValueError, match=r"routine_curve.png. is a symbolic link"):
        with rundir.claim(run_dir, resume=True, log=lambda _: None):
            pass
    link = tmp_path / "metrics.jsonl"
    link.symlink_to(outside)
    with pytest.raises(ValueError, match="symbolic link"):
        rundir.open_append(link)
    (tmp_path / "config.json.tmp").symlink_to(outside)
    rundir.write_atomic(tmp_path / "config.json.tmp".removesuffix(".tmp"), "new")
    with pytest.raises(ValueError, match="symbolic link"):  # refused, never followed
        rundir.write_atomic(link, b"replaced")
    assert outside.read_text() == "keep" and link.is_symlink()
    assert (tmp_path / "config.json").read_text() == "new"


@pytest.mark.parametrize("preset", ["/../../../tmp/x", "../x", "a/b", ".hidden", "<script>", ""])
def test_preset_must_be_a_plain_name(tmp_path, capsys, monkeypatch, preset):
    monkeypatch.chdir(tmp_path)
    code, _, err = _cli(train_cli.main, [*QUIET, "--set", f"preset={preset}"], capsys)
    assert code == 2 and "preset must be a plain name" in _one_line(err)
    assert list(tmp_path.iterdir()) == []


# -------------------------------------------------------- small inconsistencies


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs /proc")
def test_run_dir_that_cannot_be_created_is_a_usage_error(capsys):
    code, _, err = _cli(train_cli.main, [*QUIET, "--run-dir", "/proc/x/run"], capsys)
    assert code == 2 and "run_dir" in _one_line(err)


def test_overwrite_of_the_current_directory(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "notes.txt").write_text("mine")
    for run_dir in (".", str(tmp_path), ".."):
        code, _, err = _cli(train_cli.main, [*QUIET, "--overwrite", "--run-dir", run_dir], capsys)
        assert code == 2 and "current directory or holds it" in _one_line(err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_disk_full_is_one_line_and_exit_74(tmp_path, capsys, monkeypatch):
    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(train_cli, "run", full)
    code, _, err = _cli(train_cli.main, [*QUIET, "--run-dir", str(tmp_path / "r")], capsys)
    assert code == 74 and "No space left on device" in _one_line(err)


# --------------------------------------------------------- no link in a run dir


def _elsewhere(tmp_path) -> pathlib.Path:
    """Someone else's checkpoint folder, holding its own steps 3/ and 7/."""
    other = tmp_path / "someone-else"
    for step in ("3", "7"):
        (other / step).mkdir(parents=True)
        (other / step / "data").write_text(f"step {step}")
    return other


@pytest.mark.parametrize("sub", ["last", "best"])
def test_resume_through_a_linked_checkpoint_folder_is_refused_and_deletes_nothing(
        at12, tmp_path, capsys, sub):
    other = _elsewhere(tmp_path)
    for step in (at12 / "checkpoints" / sub).iterdir():  # the run's steps now live there
        shutil.move(step, other / step.name)
    (at12 / "checkpoints" / sub).rmdir()
    (at12 / "checkpoints" / sub).symlink_to(other)
    before = _snapshot(other)
    code, _, err = _cli(train_cli.main, ["--resume", "--run-dir", str(at12), "--steps", "40",
                                         "--no-progress"], capsys)
    line = _error_line(err)
    assert code == 2 and "symbolic link" in line and str(at12 / "checkpoints" / sub) in line
    assert _snapshot(other) == before  # its 3/ and 7/ are still there, no 30/ or 40/ written


@pytest.mark.parametrize("name", ["checkpoints/last/12", "checkpoints/best/10/state",
                                  "metrics.jsonl", "config.json", "checkpoints"])
def test_resume_refuses_a_link_anywhere_in_the_run(at12, tmp_path, capsys, name):
    target = tmp_path / "target"
    shutil.move(at12 / name, target)
    (at12 / name).symlink_to(target)
    before = _snapshot(target) if target.is_dir() else target.read_bytes()
    code, _, err = _cli(train_cli.main, ["--resume", "--run-dir", str(at12), "--no-progress"],
                        capsys)
    line = _error_line(err)
    assert code == 2 and "symbolic link" in line and str(at12 / name) in line, err
    assert (_snapshot(target) if target.is_dir() else target.read_bytes()) == before


def test_loading_and_exporting_refuse_a_linked_step(at12, tmp_path, capsys):
    target = tmp_path / "target"
    shutil.move(at12 / "checkpoints" / "last" / "12", target)
    (at12 / "checkpoints" / "last" / "12").symlink_to(target)
    with pytest.raises(ValueError, match=r"last/12' is a symbolic link"):
        checkpoints.restore(at12, which="latest")
    code, _, err = _cli(export_cli.main, ["--checkpoint", str(at12), "--name", "flowmaps"],
                        capsys)
    assert code == 2 and "is a symbolic link" in _error_line(err)
    assert not (at12 / "export").exists()


def test_the_checkpoint_writer_and_a_new_run_refuse_a_link_inside(tmp_path):
    root = tmp_path / "ckpt"
    (root / "last").mkdir(parents=True)
    _elsewhere(tmp_path)
    (root / "last" / "3").symlink_to(tmp_path / "someone-else" / "3")
    with pytest.raises(ValueError, match=r"last/3' is a symbolic link"):
        CheckpointStore(root, keep_last=1)
    run_dir = tmp_path / "run"
    (run_dir / "checkpoints").mkdir(parents=True)
    (run_dir / "checkpoints" / "best").symlink_to(tmp_path / "someone-else")
    with pytest.raises(ValueError, match=r"checkpoints/best' is a symbolic link"):
        with rundir.claim(run_dir, resume=True, log=lambda _: None):
            pass
    with pytest.raises(ValueError, match="not empty"):  # a new run is refused there anyway
        with rundir.claim(run_dir, resume=False, log=lambda _: None):
            pass
    (run_dir / "checkpoints" / "best").unlink()  # leftovers of a run that saved nothing
    (run_dir / "checkpoints" / "last").mkdir()
    (run_dir / "config.json").symlink_to(tmp_path / "someone-else" / "3" / "data")
    said = []
    with rundir.claim(run_dir, resume=False, log=said.append):  # removed as links, then used
        assert not (run_dir / "config.json").exists() and "saved no checkpoint" in said[0]
    assert sorted(p.name for p in (tmp_path / "someone-else").iterdir()) == ["3", "7"]


# -------------------------------------------------------- One run per directory


def test_a_new_run_in_a_non_empty_run_dir_is_refused(at12, capsys):
    before = _snapshot(at12)
    code, _, err = _cli(train_cli.main, [*QUIET, "--run-dir", str(at12)], capsys)
    assert code == 2 and f"run directory {at12} is not empty" in err
    assert "--resume" in err and "--overwrite" in err
    assert _snapshot(at12) == before


def test_overwrite_moves_the_old_run_aside(at12, capsys):
    code, out, _ = _cli(train_cli.main, [*QUIET, "--overwrite", "--stop-at", "1", "--run-dir",
                                         str(at12)], capsys)
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
        code, _, err = _cli(train_cli.main, ["--resume", "--run-dir", str(at12), "--set",
                                             override], capsys)
        assert code == 2 and f"--resume cannot change {field}" in err, err
    assert _snapshot(at12) == before
    with pytest.raises(ValueError, match="model_kind"):
        loop.run(dataclasses.replace(SMOKE, family="mlp"), at12, resume=True)
    assert _snapshot(at12) == before


def test_a_live_lock_keeps_a_second_process_out(at12, capsys):
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (at12 / rundir.LOCK_NAME).write_text(f"{sleeper.pid} {socket.gethostname()}\n")
        before = _snapshot(at12)
        code, _, err = _cli(train_cli.main, ["--resume", "--run-dir", str(at12)], capsys)
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
        code, _, err = _cli(train_cli.main, [*QUIET, "--run-dir", str(path)], capsys)
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
    result = loop.run(SMOKE, at12, resume=True, stop_at=13, progress=False, log=said.append)
    assert result.status == "stopped"
    assert any(f"Dropped the half-written last line of {metrics}" in line for line in said)
    assert [r["step"] for r in _records(at12)][-1] == 13


def test_a_bad_metrics_line_inside_the_file_is_named_before_anything_is_written(at12):
    lines = (at12 / "metrics.jsonl").read_text().splitlines()
    lines[1] = "not json"
    (at12 / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    before = _snapshot(at12)
    with pytest.raises(ValueError, match=f"{at12 / 'metrics.jsonl'} line 2"):
        loop.run(SMOKE, at12, resume=True)
    assert _snapshot(at12) == before


# ----------------------------------------------------- Integrity of checkpoints


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
    code, _, err = _cli(train_cli.main, ["--resume", "--run-dir", str(at12), "--stop-at", "13",
                         "--no-progress"], capsys)
    assert code == train_cli.EXIT_WRITE_FAILED
    assert err.count("\n") == 1 and "No space left on device" in err
    assert "Event loop" not in err and f"--resume --run-dir {at12}" in err
    assert checkpoints.saved_steps(at12) == [10, 12]
    assert not (at12 / rundir.LOCK_NAME).exists()


def test_resume_says_it_replaces_a_damaged_config_json(at12):
    """``--resume`` replaced a damaged config.json with the checkpoint's config silently."""

    for damage in ("{not json", "[1, 2]", '{"model": 3}'):
        (at12 / "config.json").write_text(damage)
        lines = []
        cfg = resume.resume_config(at12, None, log=lines.append)
        assert cfg == SMOKE and len(lines) == 1, lines
        assert lines[0].startswith(f"{at12 / 'config.json'} is unreadable (")
        assert "resuming with the config saved in the checkpoint" in lines[0]
    (at12 / "config.json").unlink()  # missing: nothing to say
    lines = []
    assert resume.resume_config(at12, None, log=lines.append) == SMOKE and not lines
