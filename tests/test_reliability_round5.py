"""Reliability, round 5 (issue 48, item 2): each reproduction of the hostile trial, and at least
one other member of its class.

1. runs: nothing in a run directory is followed through a symbolic link (any depth);
2. packaged weights: nothing overwrites them unless their folder is named;
3. stored models: a pretrained ``.json`` is sealed with its ``.npz``;
4. untrusted JSON: its depth is bounded (a ``ValueError`` naming the file);
5. outputs: checked up front, and never half an output;
6. damaged checkpoints: one line, nothing else on the terminal;
7. config types: numpy scalars become Python numbers;
8. minor: ``int_list``, an int field given a non-integer text, a subnormal positive real;
9. numerics: the frequent kernel cannot underflow, homes lengths are bounded, a reference
   posterior that does not sum to 1 is never scored;
10. ill-posed queries: every table method refuses an object absent from its map, or twice in it;
11. silent wrong answers: non-finite or absurd homes are refused, a traced out-of-range object
    index gives NaNs;
12. sizes: homes training refuses every size before its run directory is written;
13. raw errors and tracing: ``ValueError`` naming the argument, and one line under ``jax.jit``.

Trainings use the smoke preset without the routine diagnostic (they share the compilation of
the other training tests).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import inspect
import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support import error_line, run_cli

from flowmaps_jax import export as export_cli
from flowmaps_jax.atomic_files import write_files
from flowmaps_jax.evaluation import cli as eval_cli
from flowmaps_jax.evaluation.receptacle_scores import posterior_scores
from flowmaps_jax.flowsim import FlowSimConfig, generate, habits, scene_tokens
from flowmaps_jax.flowsim.homes import HomesConfig, generate_homes, load_homes, save_homes
from flowmaps_jax.flowsim.homes.export import schema_path
from flowmaps_jax.flowsim.homes.posterior import (
    homes_history_posterior,
    homes_posterior,
    transition_matrix,
)
from flowmaps_jax.flowsim.homes.queries import HomesQueries
from flowmaps_jax.flowsim.kernels import distance_weights
from flowmaps_jax.model import ModelConfig, init_params
from flowmaps_jax.model.homes_family import HomesModelConfig
from flowmaps_jax.predictor import Predictor, load_pretrained
from flowmaps_jax.search import cli as search_cli
from flowmaps_jax.store import checkpoints, pretrained, reseal, rundir
from flowmaps_jax.store.checkpoint_store import CheckpointStore
from flowmaps_jax.tables import table_probabilities
from flowmaps_jax.tokens import OBJECT, Queries
from flowmaps_jax.training import cli as train_cli
from flowmaps_jax.training import loop, resume, runlog
from flowmaps_jax.training.config import HomesTrainConfig, TrainConfig, apply_overrides, get_preset
from flowmaps_jax.untrusted_files import parse_json, read_json
from flowmaps_jax.validation.scalars import int_list

# A damaged checkpoint makes orbax leave un-awaited coroutines behind ("unraisable" warnings).
pytestmark = pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")

CFG = dataclasses.replace(get_preset("smoke"), routine_envs=0)
SILENT = dict(progress=False, log=lambda _: None)
SRC = pathlib.Path(__file__).resolve().parents[1] / "src"


_cli, _error_line = run_cli, error_line  # tests/support.py


@pytest.fixture(scope="module")
def interrupted(tmp_path_factory):
    """A run interrupted (Ctrl-C) at step 12: last/ holds 10 and 12, best/ 10."""
    run_dir = tmp_path_factory.mktemp("r5") / "at12"

    def ctrl_c(step, metrics):
        if step == 12:
            os.kill(os.getpid(), signal.SIGINT)

    assert loop.run(CFG, run_dir, on_step=ctrl_c, **SILENT).status == "interrupted"
    return run_dir


@pytest.fixture
def at12(interrupted, tmp_path):
    """A fresh copy of the run interrupted at step 12."""
    return pathlib.Path(shutil.copytree(interrupted, tmp_path / "run"))


def _tree(folder: pathlib.Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


# ------------------------------------------------------------- class 1: no link in a run dir


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
    before = _tree(other)
    code, _, err = _cli(train_cli.main, ["--resume", "--run-dir", str(at12), "--steps", "40",
                                         "--no-progress"], capsys)
    line = _error_line(err)
    assert code == 2 and "symbolic link" in line and str(at12 / "checkpoints" / sub) in line
    assert _tree(other) == before  # its 3/ and 7/ are still there, no 30/ or 40/ written


@pytest.mark.parametrize("name", ["checkpoints/last/12", "checkpoints/best/10/state",
                                  "metrics.jsonl", "config.json", "checkpoints"])
def test_resume_refuses_a_link_anywhere_in_the_run(at12, tmp_path, capsys, name):
    target = tmp_path / "target"
    shutil.move(at12 / name, target)
    (at12 / name).symlink_to(target)
    before = _tree(target) if target.is_dir() else target.read_bytes()
    code, _, err = _cli(train_cli.main, ["--resume", "--run-dir", str(at12), "--no-progress"],
                        capsys)
    line = _error_line(err)
    assert code == 2 and "symbolic link" in line and str(at12 / name) in line, err
    assert (_tree(target) if target.is_dir() else target.read_bytes()) == before


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


# ------------------------------------------------------------- class 2: the packaged weights


def _package_digests() -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(pretrained.PRETRAINED_DIR.iterdir()) if p.is_file()}


def test_export_without_out_writes_into_the_run_not_the_package(at12, capsys):
    before = _package_digests()
    code, out, err = _cli(export_cli.main, ["--checkpoint", str(at12), "--name", "flowmaps"],
                          capsys)
    assert code == 0, err
    assert (at12 / "export" / "flowmaps.npz").is_file()
    assert (at12 / "export" / "flowmaps.json").is_file()
    assert _package_digests() == before
    assert str(at12 / "export") in out
    assert pretrained.read_weights("flowmaps", at12 / "export").step == 10  # best


def test_no_writer_of_weights_defaults_to_the_package_folder(capsys):
    parameter = inspect.signature(pretrained.export_pretrained).parameters["directory"]
    assert parameter.default is inspect.Parameter.empty
    result = runlog.RunResult(status="done", step=20, state=None,
                              run_dir=pathlib.Path("runs/x"),
                              checkpoint_dir=pathlib.Path("runs/x/checkpoints"),
                              best_val_loss=1.0, best_step=20)
    lines = []
    runlog.print_summary(result, 20, 20, lines.append)
    advice = [line for line in lines if "flowmaps_jax.export" in line]
    assert len(advice) == 1 and "--checkpoint runs/x" in advice[0]
    assert "runs/x/export" in advice[0] and "--out" not in advice[0].split("(")[0]


# ------------------------------------------------------------- class 3: a sealed model


def _copy_shipped(tmp_path, name="flowmaps") -> pathlib.Path:
    folder = tmp_path / "weights"
    folder.mkdir(exist_ok=True)
    for suffix in (".npz", ".json"):
        shutil.copy(pretrained.PRETRAINED_DIR / f"{name}{suffix}", folder)
    return folder


def _canonical(meta: dict) -> str:
    return json.dumps(meta, sort_keys=True)


def test_a_flipped_bit_in_the_model_section_never_loads_another_model(tmp_path):
    folder = _copy_shipped(tmp_path)
    path = folder / "flowmaps.json"
    original = path.read_bytes()
    start = original.index(b'"max_frequency"')
    end = original.index(b"\n", start)
    positions = list(range(start, end))[:12]  # the key and its value: 12 bytes, 96 flips
    refused = loaded_same = 0
    for position in positions:
        for bit in range(8):
            flipped = bytearray(original)
            flipped[position] ^= 1 << bit
            path.write_bytes(bytes(flipped))
            try:
                weights = pretrained.read_weights("flowmaps", folder)
            except ValueError:
                refused += 1
                continue
            assert _canonical(weights.meta) == _canonical(json.loads(original)), position
            loaded_same += 1
    assert refused + loaded_same == 96 and refused >= 90, (refused, loaded_same)
    path.write_bytes(original)
    assert pretrained.read_weights("flowmaps", folder).spec.model.max_frequency == 1000.0


@pytest.mark.parametrize("field,value", [("step", 1), ("note", "x"), ("kind", "mlp"),
                                         ("which", "latest")])
def test_any_changed_field_of_the_json_is_refused(tmp_path, field, value):
    folder = _copy_shipped(tmp_path)
    meta = json.loads((folder / "flowmaps.json").read_text())
    meta[field] = value
    (folder / "flowmaps.json").write_text(json.dumps(meta, indent=2) + "\n")
    with pytest.raises(ValueError, match=r"pretrained 'flowmaps'.*(damaged|names kind)"):
        pretrained.read_weights("flowmaps", folder)


def test_an_unsealed_json_is_refused_and_resealed_once_without_touching_the_weights(tmp_path):
    folder = _copy_shipped(tmp_path, "mlp")
    meta = json.loads((folder / "mlp.json").read_text())
    del meta["seal"]
    (folder / "mlp.json").write_text(json.dumps(meta, indent=2) + "\n")
    npz = (folder / "mlp.npz").read_bytes()
    with pytest.raises(ValueError, match=r"not sealed.*flowmaps_jax.store.reseal"):
        pretrained.read_weights("mlp", folder)
    assert reseal.reseal(folder) == {"mlp": "sealed"}
    assert (folder / "mlp.npz").read_bytes() == npz
    assert (folder / "mlp.json").read_bytes() == (pretrained.PRETRAINED_DIR / "mlp.json"
                                                  ).read_bytes()
    assert reseal.reseal(folder) == {"mlp": "already sealed"}
    pretrained.read_weights("mlp", folder)
    data = bytearray(npz)  # damaged weights are not sealed
    data[len(data) // 2] ^= 1
    (folder / "mlp.npz").write_bytes(bytes(data))
    meta = json.loads((folder / "mlp.json").read_text())
    del meta["seal"]
    (folder / "mlp.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="not sealing damaged weights"):
        reseal.reseal(folder)


def test_every_shipped_model_is_sealed():
    for name in pretrained.NAMES:
        meta = json.loads((pretrained.PRETRAINED_DIR / f"{name}.json").read_text())
        assert meta["seal"]["format"] == pretrained.SEAL_FORMAT
        pretrained.check_seal(name, meta,
                              (pretrained.PRETRAINED_DIR / f"{name}.npz").read_bytes())


# ------------------------------------------------------------- class 4: untrusted JSON


DEEP = "[" * 50_000 + "]" * 50_000


def test_a_deep_note_in_a_pretrained_json_is_a_value_error(tmp_path):
    folder = _copy_shipped(tmp_path)
    text = (folder / "flowmaps.json").read_text().replace('"note": ""', f'"note": {DEEP}')
    assert text != (folder / "flowmaps.json").read_text()
    (folder / "flowmaps.json").write_text(text)
    with pytest.raises(ValueError, match=r"flowmaps.json is nested \d+ levels deep"):
        pretrained.read_weights("flowmaps", folder)
    with pytest.raises(ValueError, match=r"nested \d+ levels"):
        pretrained.describe("flowmaps", folder)


def test_a_deep_config_json_on_resume_is_a_value_error_or_ignored(at12, tmp_path):
    (at12 / "config.json").write_text(DEEP)
    # a run with a checkpoint: the checkpoint's config (config.json only adds --steps etc.)
    assert resume.resume_config(at12, None) == resume.load_config(at12 / "checkpoints")
    unsaved = tmp_path / "unsaved"  # a run that saved no checkpoint: config.json is all
    unsaved.mkdir()
    (unsaved / "config.json").write_text(DEEP)
    with pytest.raises(ValueError, match=r"config.json.*nested \d+ levels"):
        resume.resume_config(unsaved, None)


def test_a_deep_metrics_line_is_named(at12):
    path = at12 / "metrics.jsonl"
    lines = path.read_text().splitlines()
    path.write_text("\n".join([lines[0], DEEP, *lines[1:]]) + "\n")
    with pytest.raises(ValueError, match=r"metrics.jsonl line 2 is not a metrics record.*"
                                         r"nested \d+ levels"):
        rundir.kept_records(at12, 12, lambda _: None)
    path.write_text("\n".join([*lines, DEEP]) + "\n")  # a last line: dropped, with a message
    said = []
    assert rundir.kept_records(at12, 12, said.append) == [
        line for line in lines if json.loads(line).get("step", 0) <= 12]
    assert "Dropped the half-written last line" in said[0]


def test_a_deep_config_json_in_a_homes_file_is_a_value_error(tmp_path):
    config = HomesConfig(regime="mixed", num_hours=48)
    path = tmp_path / "homes.npz"
    save_homes(path, generate_homes(jax.random.key(0), config, 1), config)
    with np.load(path) as file:
        arrays = {k: file[k] for k in file.files}
    for member in ("config_json", "schema_json"):
        bad = tmp_path / f"{member}.npz"
        np.savez(bad, **{**arrays, member: np.asarray(DEEP)})
        with pytest.raises(ValueError, match=rf"load_homes: .*{member} is nested \d+ levels"):
            load_homes(bad)


def test_the_json_reader_counts_only_brackets_outside_strings(tmp_path):
    assert parse_json("x", '{"a": "[[[[[[", "b": [1, {"c": "\\"]]]"}]}') == {
        "a": "[[[[[[", "b": [1, {"c": '"]]]'}]}
    path = tmp_path / "deep.json"
    path.write_text('{"a": ' + "[" * 65 + "]" * 65 + "}")
    with pytest.raises(ValueError, match=r"deep.json.*nested 66 levels deep"):
        read_json("config", path)
    path.write_bytes(b'{"a": "\xff"}')
    with pytest.raises(ValueError, match="not UTF-8"):
        read_json("config", path)


# ------------------------------------------------------------- class 5: outputs


def test_export_with_a_directory_at_its_json_leaves_nothing(at12, tmp_path, capsys):
    out = tmp_path / "out"
    (out / "flowmaps.json").mkdir(parents=True)
    code, _, err = _cli(export_cli.main, ["--checkpoint", str(at12), "--name", "flowmaps",
                                          "--out", str(out)], capsys)
    assert code == 2 and "is a directory" in _error_line(err)
    assert sorted(p.name for p in out.iterdir()) == ["flowmaps.json"]


@pytest.mark.parametrize("out", ["/proc/x", "/proc"])
@pytest.mark.parametrize("command", ["export", "evaluate", "search"])
def test_an_output_that_cannot_be_created_is_refused_up_front(at12, capsys, command, out):
    main = {"export": export_cli.main, "evaluate": eval_cli.main, "search": search_cli.main}
    argv = {"export": ["--checkpoint", str(at12), "--name", "flowmaps"],
            "evaluate": ["--checkpoint", "pretrained:flowmaps", "--num-envs", "1"],
            "search": ["--checkpoint", "pretrained:flowmaps", "--num-envs", "1"]}[command]
    code, printed, err = _cli(main[command], [*argv, "--out", out], capsys)
    assert code == 2 and repr(out) in _error_line(err) and "cannot be" in err, err
    assert "Evaluating" not in printed and not (at12 / "export").exists()


@pytest.mark.parametrize("command,name", [("evaluate", "results.json"),
                                          ("search", "search.md")])
def test_a_directory_at_an_output_file_is_refused_up_front(tmp_path, capsys, command, name):
    main = {"evaluate": eval_cli.main, "search": search_cli.main}[command]
    (tmp_path / "out" / name).mkdir(parents=True)
    argv = ["--checkpoint", "pretrained:flowmaps", "--num-envs", "1", "--no-figures",
            "--out", str(tmp_path / "out")]
    code, out, err = _cli(main, argv, capsys)
    assert code == 2 and name in _error_line(err) and "is a directory" in err
    assert "Evaluating" not in out and sorted(p.name for p in (tmp_path / "out").iterdir()
                                              ) == [name]


def test_save_homes_writes_both_files_or_neither_and_refuses_no_homes(tmp_path):
    config = HomesConfig(regime="mixed", num_hours=48)
    homes = generate_homes(jax.random.key(0), config, 1)
    path = tmp_path / "homes.npz"
    schema_path(path).mkdir()
    with pytest.raises(ValueError, match=r"schema file .*is a directory"):
        save_homes(path, homes, config)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["homes.schema.json"]
    with pytest.raises(ValueError, match="0 homes"):
        save_homes(tmp_path / "none.npz", jax.tree.map(lambda a: a[:0], homes), config)
    assert not (tmp_path / "none.npz").exists()


def test_write_files_renames_only_when_every_file_is_written(tmp_path, monkeypatch):
    (tmp_path / "b").mkdir()
    with pytest.raises(ValueError, match="is a directory"):
        write_files({tmp_path / "a": "1", tmp_path / "b": "2"})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b"]
    real_replace = os.replace
    calls = []

    def full_disk_on_second_write(src, dst):
        calls.append(dst)
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", full_disk_on_second_write)
    write_files({tmp_path / "c": "3", tmp_path / "d": b"4"})
    assert [pathlib.Path(c).name for c in calls] == ["c", "d"]
    assert not list(tmp_path.glob("*.tmp"))


# ------------------------------------------------------------- class 6: damaged checkpoints


def _damage(step_dir: pathlib.Path, how: str) -> None:
    state = step_dir / "state"
    if how == "no data folder":
        shutil.rmtree(state / "ocdbt.process_0")
    elif how == "a data file gone":
        data = max((state / "ocdbt.process_0" / "d").iterdir(), key=lambda p: p.stat().st_size)
        data.unlink()
    elif how == "no index":
        for index in (state / "d").iterdir():
            index.unlink()


def test_resume_of_a_step_without_its_data_folder_prints_one_line(at12):
    _damage(at12 / "checkpoints" / "last" / "12", "no data folder")
    env = {**os.environ, "PYTHONPATH": f"{SRC}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    done = subprocess.run([sys.executable, "-m", "flowmaps_jax.train", "--resume", "--run-dir",
                           str(at12), "--steps", "30", "--no-progress"], env=env,
                          capture_output=True, text=True, timeout=300)
    errors = [line for line in done.stderr.splitlines() if "error:" in line]
    noise = [line for line in done.stderr.splitlines()
             if not line.startswith(("usage:", " ")) and "error:" not in line]
    assert done.returncode == 2 and len(errors) == 1 and not noise, done.stderr[-3000:]
    assert "last/12" in errors[0] and "state/ocdbt.process_0" in errors[0]
    assert "newest intact checkpoint is step 10" in errors[0]
    assert "Exception ignored" not in done.stderr and "TensorStore" not in done.stderr


@pytest.mark.parametrize("how", ["no data folder", "a data file gone", "no index"])
def test_a_damaged_step_is_one_line_and_nothing_else_on_the_terminal(at12, capfd, how):
    _damage(at12 / "checkpoints" / "last" / "12", how)
    capfd.readouterr()
    with pytest.raises(ValueError) as info:
        checkpoints.restore(at12, which="latest")
    message = str(info.value)
    assert "\n" not in message and len(message) < 1000 and "TensorStore" not in message
    assert "last/12" in message and "newest intact checkpoint is step 10" in message
    captured = capfd.readouterr()
    assert captured.err == "" and captured.out == "", captured.err[-2000:]


def test_evaluate_of_a_damaged_step_prints_one_line(at12, capfd):
    _damage(at12 / "checkpoints" / "last" / "12", "a data file gone")
    capfd.readouterr()
    code = eval_cli.main(["--checkpoint", str(at12), "--which", "latest", "--num-envs", "1",
                          "--no-figures", "--out", str(at12 / "eval")])
    err = capfd.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err[-2000:]
    assert "last/12" in err and "step 10" in err


# ------------------------------------------------------------- class 7: config types


@pytest.mark.parametrize("make", [
    lambda: TrainConfig(batch_size=np.int64(8), lr=np.float32(1e-3), clip_norm=np.float64(1)),
    lambda: HomesTrainConfig(lr=np.float32(1e-3), steps=np.int32(1000)),
    lambda: HomesModelConfig(dim=np.int64(32), max_frequency=np.float32(8.0)),
    lambda: ModelConfig(dim=np.array(16), heads=np.int8(2), condition_on_dtau=np.bool_(True)),
    lambda: FlowSimConfig(num_furniture=np.int64(10), object_frac=np.float32(0.375)),
    lambda: HomesConfig(num_hours=np.int64(48)),
])
def test_config_dataclasses_hold_python_numbers(make):
    config = make()
    values = dataclasses.asdict(config)
    json.dumps(values)
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        assert not isinstance(value, (np.generic, np.ndarray)), (field.name, type(value))
    if hasattr(config, "to_dict"):
        json.dumps(config.to_dict())


# ------------------------------------------------------------- class 8: minor


@pytest.mark.parametrize("text", ["1,,2", "1,2,", ",1", "\u0661,2", "1,\uff12", "1.0,2", ""])
def test_int_list_refuses_what_set_refuses(text):
    with pytest.raises(argparse.ArgumentTypeError):
        int_list(text)


def test_int_list_still_reads_integers():
    assert int_list("1,4,16") == [1, 4, 16] and int_list(" 2, -3 ") == [2, -3]


@pytest.mark.parametrize("override,field", [("seed=1.0000000000000001", "seed"),
                                            ("steps=20.5", "steps"),
                                            ("clip_norm=1e-320", "clip_norm"),
                                            ("lr=1e-45", "lr")])
def test_set_refuses_a_value_the_field_would_lose(override, field):
    with pytest.raises(ValueError, match=rf"\({field}\): {field} must be"):
        apply_overrides(CFG, [override])


def test_set_still_reads_integers_written_as_reals():
    config = apply_overrides(CFG, ["steps=1e4", "seed=8.0", "clip_norm=1e-30"])
    assert (config.steps, config.seed, config.clip_norm) == (10_000, 8, 1e-30)
    with pytest.raises(ValueError, match=r"clip_norm must be > 0.0 and at least"):
        HomesTrainConfig(clip_norm=1e-320)


# ------------------------------------------------------------- class 9: numerics

HOMES = HomesConfig(num_hours=96)


def _frequent(length: float) -> HomesConfig:
    return HomesConfig(regime="frequent", frequent_length=length, num_hours=96)


@pytest.mark.parametrize("length", [0.1, 1e-3, 3.0])  # 0.1: the reproduction (rows lost mass)
def test_the_frequent_posterior_keeps_its_mass_at_any_accepted_length(length):
    config = _frequent(length)
    homes = generate_homes(jax.random.key(0), config, 2)
    for e in range(2):
        home = homes.home(e)
        for i in np.flatnonzero(np.asarray(home.object_valid)):
            p = np.asarray(homes_posterior(home, int(i), 3, 90, config))
            assert abs(p.sum() - 1.0) < 1e-4, (length, e, i, p.sum())
            t = np.asarray(transition_matrix(home, int(i), 3, config))
            allowed = np.asarray(home.object_allowed[i])
            np.testing.assert_allclose(t[allowed].sum(-1), 1.0, atol=1e-5)


def test_the_distance_kernel_is_unchanged_to_the_bit_where_it_did_not_underflow():
    distance = jax.random.uniform(jax.random.key(3), (6, 6)) * 20.0
    others = ~np.eye(6, dtype=bool)
    others[:, 5] = False  # a place the object may not stand on
    plain = jnp.where(others, jnp.exp(-distance / 3.0), 0.0)
    weight, total = distance_weights(others, distance, 3.0)
    np.testing.assert_array_equal(weight, plain)
    np.testing.assert_array_equal(total, plain.sum(-1, keepdims=True))


@pytest.mark.parametrize("length", [1e-3, 1e-2])
def test_the_distance_kernel_keeps_its_rows_where_the_exponentials_underflow(length):
    distance = jnp.asarray([[0.0, 2.0, 3.0], [2.0, 0.0, 2.0], [3.0, 2.0, 0.0]], jnp.float32)
    others = ~np.eye(3, dtype=bool)
    weight, total = distance_weights(others, distance, length)
    kernel = np.asarray(weight / total)
    np.testing.assert_allclose(kernel.sum(-1), 1.0)
    np.testing.assert_allclose(kernel[0], [0.0, 1.0, 0.0])  # all to the nearest place
    np.testing.assert_allclose(kernel[1], [0.5, 0.0, 0.5])  # two equally near


def test_the_2d_dynamic_habit_moves_at_a_short_length():
    centres = jnp.asarray([[0.1, 0.1], [0.9, 0.9], [0.1, 0.9], [0.0, 0.0]], jnp.float32)
    matrix = np.asarray(habits._dynamic_matrix(3, centres, 0.5, 1e-3))  # 3 places, 1 padding
    np.testing.assert_allclose(matrix[:3].sum(-1), 1.0, atol=1e-6)
    assert matrix[0, 0] == 0.5 and matrix[0, 2] == 0.5  # moves to its nearest place
    with pytest.raises(ValueError, match="dynamic_length"):
        FlowSimConfig(dynamic_length=1e-45)


@pytest.mark.parametrize("kwargs,field", [
    (dict(frequent_length=1e-30), "frequent_length"),
    (dict(frequent_length=1e308), "frequent_length"),
    (dict(home_width=(1e308, 1e308)), "home_width"),  # the reproduction: infinite homes
    (dict(home_depth=(8.0, 1e300)), "home_depth"),
    (dict(door_width=1e30), "door_width"),
    (dict(wall_margin=1e300), "wall_margin"),
])
def test_homes_config_bounds_its_real_valued_sizes(kwargs, field):
    with pytest.raises(ValueError, match=field):
        HomesConfig(**kwargs)


def test_a_class_size_beyond_the_bound_is_refused():
    big = dataclasses.replace(HOMES.object_classes[0], size=(1e308, 0.1, 0.1))
    with pytest.raises(ValueError, match="object_classes"):
        HomesConfig(object_classes=(big, *HOMES.object_classes[1:]))


def test_a_reference_posterior_that_lost_mass_is_never_scored():
    q = np.array([[0.5, 0.5, 0.0], [0.0, 0.0, 0.0]], np.float32)  # row 1 lost its mass
    allowed = np.array([[True, True, False], [True, True, True]])
    with pytest.raises(ValueError, match=r"q: the reference posterior's row \(1,\) sums to 0"):
        posterior_scores(q, q, allowed)
    with pytest.raises(ValueError, match="reference posterior"):
        posterior_scores(q[:1], np.array([[np.nan, 1.0, 0.0]], np.float32), allowed[:1])
    assert float(posterior_scores(q[:1], q[:1], allowed[:1])["kl"][0]) == 0.0


# ------------------------------------------------------------- class 10: ill-posed queries

TABLES_MODEL = ModelConfig(dim=16, encoder_layers=1, cdit_blocks=1, heads=2, mlp_ratio=2,
                           dropout=0.0, head="mixture")


@pytest.fixture(scope="module")
def scene_model():
    """A mixture-head FlowMaps from init, two FlowSim maps and one query of each."""
    sim = FlowSimConfig()
    scenes = generate(jax.random.key(0), 2, sim)
    tokens = jax.tree.map(np.asarray, scene_tokens(scenes, np.arange(2), np.array([0, 5]), sim))
    is_object = (tokens.kind[0] == OBJECT) & tokens.mask[0]
    objects = [int(d) for d in tokens.descriptor[0][is_object]]
    queries = Queries(descriptor=np.array([[objects[0]], [objects[0]]], np.int32),
                      tau_q=np.array([[3], [9]], np.int32))
    model = Predictor.from_params(init_params(jax.random.key(1), TABLES_MODEL), TABLES_MODEL)
    return model, tokens, queries, objects


def _ill_posed(tokens, objects, how: str):
    """The maps with the first queried object (scene 0) absent, or present twice."""
    slot = {d: i for i, (d, k) in enumerate(zip(tokens.descriptor[0], tokens.kind[0], strict=True))
            if k == OBJECT}
    if how == "absent":
        mask = tokens.mask.copy()
        mask[0, slot[objects[0]]] = False
        return tokens.replace(mask=mask)
    descriptor = tokens.descriptor.copy()
    descriptor[0, slot[objects[1]]] = objects[0]
    return tokens.replace(descriptor=descriptor)


_TABLE_CALLS = {
    "table_weights": lambda m, t, q: m.table_weights(t, q),
    "weights": lambda m, t, q: m.table_probabilities(t, q, 4, jax.random.key(0),
                                                     method="weights"),
    "samples": lambda m, t, q: m.table_probabilities(t, q, 4, jax.random.key(0)),
    "tables.weights": lambda m, t, q: table_probabilities(m, t, q, 0, None, method="weights"),
}


@pytest.mark.parametrize("how", ["absent", "twice"])
@pytest.mark.parametrize("call", sorted(_TABLE_CALLS))
def test_every_table_method_refuses_an_ill_posed_query_alike(scene_model, how, call):
    model, tokens, queries, objects = scene_model
    found = 0 if how == "absent" else 2
    with pytest.raises(ValueError, match=rf"queries\.descriptor\[0, 0\] must name exactly one "
                                         rf"object token of its map .*; found {found}"):
        _TABLE_CALLS[call](model, _ill_posed(tokens, objects, how), queries)


def test_the_table_methods_still_answer_a_well_posed_query(scene_model):
    model, tokens, queries, _ = scene_model
    weights = np.asarray(model.table_weights(tokens, queries))
    np.testing.assert_allclose(weights.sum(-1), 1.0, atol=1e-5)
    np.testing.assert_array_equal(_TABLE_CALLS["weights"](model, tokens, queries), weights)


# ------------------------------------------------------------- class 11: silent wrong answers


@pytest.fixture(scope="module")
def homes_model():
    """The packaged homes model, two short homes and three queries in each."""
    homes = generate_homes(jax.random.key(1), HOMES, 2)
    queries = HomesQueries(object_index=np.zeros((2, 3), np.int32),
                           tau=np.full((2, 3), 30, np.int32), tau_q=np.full((2, 3), 40, np.int32))
    return load_pretrained("flowmaps-homes"), homes, queries


_HOMES_CALLS = {
    "probabilities": lambda m, h, q: m.probabilities(h, q, HOMES),
    "sample": lambda m, h, q: m.sample(h, q, 2, jax.random.key(0), 2, config=HOMES),
}


@pytest.mark.parametrize("call", sorted(_HOMES_CALLS))
@pytest.mark.parametrize("field,change,message", [
    ("receptacle_box", lambda a: a.at[0, 0, 0].set(np.nan), "contains NaN or inf"),
    ("receptacle_distance", lambda a: a * 1e30, "must lie in"),
    ("home_size", lambda a: a.at[1, 0].set(np.inf), "contains NaN or inf"),
    ("room_box", lambda a: a * 1e6, "must lie in"),
])
def test_a_homes_model_refuses_non_finite_or_absurd_homes(homes_model, call, field, change,
                                                         message):
    model, homes, queries = homes_model
    bad = homes.replace(**{field: change(getattr(homes, field))})
    with pytest.raises(ValueError, match=rf"homes\.{field} {message}"):
        _HOMES_CALLS[call](model, bad, queries)


def test_a_homes_model_still_answers_valid_homes(homes_model):
    model, homes, queries = homes_model
    p = np.asarray(model.probabilities(homes, queries, HOMES))
    np.testing.assert_allclose(p.sum(-1), 1.0, atol=1e-5)


@pytest.fixture(scope="module")
def full_home():
    """A home whose 15 object slots are all used."""
    config = HomesConfig(num_hours=96, objects_per_home=(15, 15))
    home = generate_homes(jax.random.key(2), config, 1).home(0)
    assert bool(np.all(home.object_valid))
    return config, home


@pytest.mark.parametrize("index", [-1, 15, 1000])
def test_a_traced_object_index_out_of_range_gives_nans(full_home, index):
    config, home = full_home
    posterior = jax.jit(lambda i: homes_posterior(home, i, 3, 10, config))
    history = jax.jit(lambda i: homes_history_posterior(home, i, 30, 40, 24, config))
    matrix = jax.jit(lambda i: transition_matrix(home, i, 3, config))
    for fn in (posterior, history, matrix):
        assert np.all(np.isnan(np.asarray(fn(index)))), fn
    assert abs(float(posterior(14).sum()) - 1.0) < 1e-5  # the last slot still answers
    assert not np.any(np.isnan(np.asarray(matrix(14))))


def test_a_traced_hour_out_of_range_gives_nans(full_home):
    config, home = full_home
    matrix = jax.jit(lambda hour: transition_matrix(home, 0, hour, config))
    assert np.all(np.isnan(np.asarray(matrix(config.num_hours - 1))))
    assert np.all(np.isnan(np.asarray(matrix(-1))))
    assert not np.any(np.isnan(np.asarray(matrix(config.num_hours - 2))))


# ------------------------------------------------------------- class 12: sizes (homes training)


@pytest.mark.parametrize("overrides,field", [
    (["model.dim=65536", "model.heads=1"], "model.dim"),
    (["homes.max_vocabulary=1000000000"], "max_vocabulary"),
    (["queries_per_home=100000000"], "queries_per_scene"),
    (["homes.num_hours=1048576"], "num_hours"),
    (["homes.max_tokens=100000"], "max_tokens"),
    (["homes.max_tokens=1000000000"], "max_tokens"),
    (["model.encoder_layers=65536"], "model.encoder_layers"),
    (["chunk_homes=100000000"], "chunk_homes"),
    (["val_homes=100000000"], "val_homes"),
    (["val_batches=100000000"], "val_batches"),
    # other members of the class
    (["val_batches=1000000", "val_homes=4000000"], "val_batches"),
    (["model.weight_blocks=1000"], "model.weight_blocks"),
    (["model.cdit_blocks=65536"], "model.cdit_blocks"),
    (["batch_size=100000000"], "batch_size"),
    (["model.dim=4096", "model.mlp_ratio=4096"], "model.mlp_ratio"),
    (["homes.frequent_length=1e-30"], "frequent_length"),
])
def test_homes_training_refuses_a_size_before_writing_the_run(tmp_path, capsys, overrides,
                                                              field):
    run_dir = tmp_path / "run"
    argv = ["--preset", "homes-smoke", "--run-dir", str(run_dir)]
    for override in overrides:
        argv += ["--set", override]
    code, _, err = _cli(train_cli.main, argv, capsys)
    assert code == 2, err
    assert field in _error_line(err)
    assert not run_dir.exists()


# ------------------------------------------------------------- class 13: raw errors, tracing


@pytest.mark.parametrize("rooms", [(["kitchen"],) * 6, ({"kitchen": 1},) * 6, "kitchen"])
def test_homes_config_refuses_unhashable_room_names(rooms):
    with pytest.raises(ValueError, match="rooms must be a non-empty tuple of room type names"):
        HomesConfig(rooms=rooms)


@pytest.mark.parametrize("call", sorted(_HOMES_CALLS))
def test_a_homes_model_refuses_no_queries_and_no_homes(homes_model, call):
    model, homes, queries = homes_model
    none = jax.tree.map(lambda a: a[:, :0], queries)
    with pytest.raises(ValueError, match=r"queries must hold at least one query per home"):
        _HOMES_CALLS[call](model, homes, none)
    with pytest.raises(ValueError, match=r"homes must hold at least one home; got 0"):
        _HOMES_CALLS[call](model, jax.tree.map(lambda a: a[:0], homes),
                           jax.tree.map(lambda a: a[:0], queries))


def _one_line_tracing_error(fn, *args):
    with pytest.raises(ValueError, match=r"takes concrete arrays.*outside jax\.jit") as info:
        fn(*args)
    assert "\n" not in str(info.value)


def test_a_homes_model_under_jit_says_it_takes_concrete_arrays(homes_model):
    model, homes, queries = homes_model
    _one_line_tracing_error(jax.jit(lambda h: model.probabilities(h, queries, HOMES)), homes)
    _one_line_tracing_error(jax.jit(lambda q: model.probabilities(homes, q, HOMES)), queries)
    _one_line_tracing_error(
        jax.jit(lambda k: model.sample(homes, queries, 2, k, 2, config=HOMES)), jax.random.key(0))


def test_a_scene_model_under_jit_says_it_takes_concrete_arrays(scene_model):
    model, tokens, queries, _ = scene_model
    _one_line_tracing_error(jax.jit(model.table_weights), tokens, queries)
    _one_line_tracing_error(jax.jit(lambda t: model.sample(t, queries, 2, jax.random.key(0))),
                            tokens)
    _one_line_tracing_error(jax.jit(lambda k: model.sample(tokens, queries, 2, k)),
                            jax.random.key(0))
    _one_line_tracing_error(jax.vmap(lambda d: model.validate(tokens, queries.replace(
        descriptor=d))), np.stack([queries.descriptor] * 2))
    _one_line_tracing_error(jax.jit(lambda t: model.table_probabilities(
        t, queries, 2, jax.random.key(0))), tokens)
