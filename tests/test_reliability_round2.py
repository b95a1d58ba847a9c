"""Reliability, round 2 (issue 19): every check before the first write, sizes bounded by one
resource estimate, garbage priors and weights refused, untrusted files read safely, outputs
checked up front, and one line with exit code 74 on a full disk.

Every refusal here happens before any model runs: the tests are fast. The few that train use
the smoke preset without the routine diagnostic (the compiled functions of the other training
tests) and stop after one step.
"""

from __future__ import annotations

import dataclasses
import errno
import io
import json
import os
import pathlib
import zipfile

import jax
import numpy as np
import pytest
from support import run_cli

from flowmaps_jax import resources, untrusted_files
from flowmaps_jax import validation as v
from flowmaps_jax.store import rundir
from flowmaps_jax.training import cli as train_cli
from flowmaps_jax.training.config import apply_overrides, check_run_resources, get_preset

CFG = dataclasses.replace(get_preset("smoke"), routine_envs=0)
QUIET = ["--preset", "smoke", "--set", "routine_envs=0", "--no-progress"]


_cli = run_cli  # tests/support.py


def _one_line(err: str) -> str:
    """The error line of stderr, which holds nothing else but argparse's usage lines."""
    lines = [line for line in err.strip().splitlines() if line.strip()]
    errors = [i for i, line in enumerate(lines) if "error:" in line]
    assert errors and errors[-1] == len(lines) - 1, err
    assert len(errors) == 1 and "Traceback" not in err, err
    assert errors[0] == 0 or lines[0].startswith("usage:"), err
    return lines[-1]


def _unsaved_run(run_dir: pathlib.Path, cfg=CFG) -> pathlib.Path:
    """What a run leaves when it is killed before its first checkpoint."""
    (run_dir / "checkpoints" / "last" / "10.orbax-checkpoint-tmp-1").mkdir(parents=True)
    (run_dir / "checkpoints" / "best").mkdir()
    (run_dir / "config.json").write_text(json.dumps(cfg.to_dict()))
    (run_dir / "metrics.jsonl").write_text('{"kind": "train", "step": 5, "loss": 9.0}\n')
    return run_dir


# ------------------------------------------------------------------ class 2: one resource budget


@pytest.mark.parametrize("override, field", [
    ("queries_per_scene=100000000", "queries_per_scene"),
    ("model.dim=65536", "model.dim"),
    ("val_batches=100000000", "val_batches"),
    ("routine_samples=1000000000", "routine_samples"),
    ("batch_size=100000000", "batch_size"),
    ("train_envs=2000000000", "train_envs"),
    ("model.cdit_blocks=100000", "model.cdit_blocks"),
])
def test_train_sizes_refused_before_anything_is_written(tmp_path, capsys, override, field):
    run_dir = tmp_path / "run"
    code, _, err = _cli(train_cli.main, ["--preset", "smoke", "--no-progress", "--run-dir",
                                         str(run_dir), "--set", override], capsys)
    assert code == 2
    line = _one_line(err)
    assert field in line and "GB" in line and resources.MAX_BYTES_ENV in line
    assert not run_dir.exists()


def test_resume_with_a_size_over_budget_keeps_config_json(tmp_path, capsys):
    run_dir = _unsaved_run(tmp_path / "run", get_preset("smoke"))
    before = (run_dir / "config.json").read_bytes()
    code, _, err = _cli(train_cli.main, ["--resume", "--run-dir", str(run_dir), "--steps", "40",
                                         "--set", "routine_samples=1000000000", "--no-progress"],
                        capsys)
    assert code == 2 and "routine_samples=1000000000" in _one_line(err)
    assert (run_dir / "config.json").read_bytes() == before


def test_budget_env_variables(monkeypatch):
    cfg = apply_overrides(CFG, ["val_batches=1000"])
    check_run_resources(cfg)
    monkeypatch.setenv(resources.MAX_BYTES_ENV, "1M")
    with pytest.raises(ValueError, match=r"val_batches=1000 .* more than the 0.001 GB"):
        check_run_resources(cfg)
    monkeypatch.setenv(resources.MAX_BYTES_ENV, "64Gi")
    assert resources.memory_limit() == 64 * 2**30
    monkeypatch.setenv(resources.MAX_BYTES_ENV, "lots")
    with pytest.raises(ValueError, match=resources.MAX_BYTES_ENV):
        resources.memory_limit()
    monkeypatch.delenv(resources.MAX_BYTES_ENV)
    monkeypatch.setenv(resources.MAX_FLOPS_ENV, "1e6")
    with pytest.raises(ValueError, match=r"a train step .* floating-point operations"):
        check_run_resources(CFG)
    monkeypatch.delenv(resources.MAX_FLOPS_ENV)
    assert resources.flops_limit() == resources.DEFAULT_MAX_FLOPS
    with pytest.raises(ValueError, match="budget"):
        resources.check_resources("x=3", flops=resources.DEFAULT_MAX_FLOPS + 1)


def test_every_preset_fits_the_default_budget():
    for name in ("smoke", "cpu", "paper"):
        check_run_resources(get_preset(name))


# ------------------------------------------------------------------ class 1: checks before writes


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


# ------------------------------------------------------------------ class 4: untrusted files


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


# ------------------------------------------------------------------ class 6: small inconsistencies


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


# ------------------------------------------------------------------ evaluate and search CLIs

from flowmaps_jax import export, predictor  # noqa: E402
from flowmaps_jax.evaluation import cli as eval_cli  # noqa: E402
from flowmaps_jax.search import cli as search_cli  # noqa: E402
from flowmaps_jax.search import episodes as E  # noqa: E402
from flowmaps_jax.store import pretrained  # noqa: E402

MODELS = ["--checkpoint", "pretrained:flowmaps", "--baseline", "pretrained:mlp"]


@pytest.mark.parametrize("argv, named", [
    (["--kl-draws", "1000000000"], "--kl-draws 1000000000"),
    (["--samples", "1000000000"], "--samples 1000000000"),
    (["--samples", "25,1000000000"], "--samples 1000000000"),
    (["--num-steps", "1000000000"], "--num-steps 1000000000"),
    (["--logp-steps", "1000000000"], "--logp-steps 1000000000"),
    (["--num-envs", "100000000"], "100000000 environments"),
    (["--kl-draws", "100000", "--chunk-envs", "200"], "--chunk-envs"),
])
def test_evaluate_sizes_are_refused_up_front(tmp_path, capsys, argv, named):
    out = tmp_path / "out"
    code, _, err = _cli(eval_cli.main, [*MODELS, "--out", str(out), *argv], capsys)
    line = _one_line(err)
    assert code == 2 and named in line and ("GB" in line or "floating-point operations" in line)
    assert not out.exists()


@pytest.mark.parametrize("argv, named", [
    (["--budget", "1000000000"], "budget=1000000000"),
    (["--times-per-env", "100000000"], "--times-per-env 100000000"),
    (["--samples", "100000000"], "samples=100000000"),
    (["--num-envs", "1000000", "--horizons", "1,2,3,4,5,6,7"], "7 --horizons"),
])
def test_search_sizes_are_refused_up_front(tmp_path, capsys, argv, named):
    out = tmp_path / "out"
    code, _, err = _cli(search_cli.main, [*MODELS, "--out", str(out), *argv], capsys)
    assert code == 2 and named in _one_line(err)
    assert not out.exists()


@pytest.mark.parametrize("main", [eval_cli.main, search_cli.main])
def test_negative_seed_and_bad_out_are_usage_errors(tmp_path, capsys, main):
    code, _, err = _cli(main, [*MODELS, "--out", str(tmp_path / "o"), "--seed", "-1"], capsys)
    assert code == 2 and "--seed must be an int in 0..4294967295" in _one_line(err)
    afile = tmp_path / "file"
    afile.write_text("x")
    for out in (afile, afile / "under"):
        code, _, err = _cli(main, [*MODELS, "--out", str(out)], capsys)
        assert code == 2 and "--out" in _one_line(err)


def _enospc(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


def test_disk_full_in_evaluate_search_and_export(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(eval_cli, "run_evaluation", _enospc)
    monkeypatch.setattr("flowmaps_jax.flowsim.scenes.validation_split", lambda *a, **k: _Envs())
    code, _, err = _cli(eval_cli.main, [*MODELS, "--out", str(tmp_path / "e")], capsys)
    assert code == 74 and "No space left on device" in _one_line(err)

    monkeypatch.setattr(search_cli, "validation_split", lambda *a, **k: None)
    monkeypatch.setattr(search_cli.pr, "run_search", lambda *a, **k: ({}, {}, None))
    monkeypatch.setattr(search_cli, "write_report", _enospc)
    code, _, err = _cli(search_cli.main, [*MODELS, "--out", str(tmp_path / "s"),
                                          "--no-figures"], capsys)
    assert code == 74 and "No space left on device" in _one_line(err)

    monkeypatch.setattr(export, "export_pretrained", _enospc)
    code, _, err = _cli(export.main, ["--checkpoint", "x", "--name", "mlp", "--out",
                                          str(tmp_path / "p")], capsys)
    assert code == 74 and "No space left on device" in _one_line(err)


class _Envs:
    num_envs = 1


def test_pretrained_out_that_is_a_file(tmp_path, capsys):
    afile = tmp_path / "file"
    afile.write_text("x")
    code, _, err = _cli(export.main, ["--checkpoint", str(tmp_path), "--name", "mlp",
                                          "--out", str(afile)], capsys)
    assert code == 2 and "--out" in _one_line(err) and afile.read_text() == "x"


# ------------------------------------------------------------------ class 3: garbage priors


@pytest.fixture(scope="module")
def search_set(small_scenes, flowsim_config):
    scenes = jax.tree_util.tree_map(lambda a: a[:4], small_scenes)
    return E.build_search_set(scenes, flowsim_config, jax.random.key(3))


@pytest.mark.parametrize("garbage, match", [
    (np.nan, "NaN or inf"), (np.inf, "NaN or inf"), (-1.0, "negative"), (0.0, "sum to 1"),
    (0.5, "sum to 1")])
def test_make_episodes_refuses_garbage_priors(search_set, garbage, match):
    probs = np.asarray(E.exact_tables(search_set)).copy()
    E.make_episodes(search_set, probs)
    if garbage == 0.5:
        probs[1, 2] *= 0.5  # not normalised
    else:
        probs[1, 2] = garbage  # NaN, inf, negative everywhere, or all zero
    with pytest.raises(ValueError, match=f"table_probs .*{match}|table_probs {match}"):
        E.make_episodes(search_set, probs)


class _NaNModel:
    name, kind, source = "diverged", "flowmaps", "test"

    def sample(self, tokens, queries, num_samples, key):
        return np.full((*np.shape(queries.descriptor), num_samples, 4), np.nan, np.float32)


def test_a_model_with_nan_samples_gets_no_search_numbers(search_set):
    with pytest.raises(ValueError, match=r"diverged .*non-finite samples"):
        E.predictor_tables(_NaNModel(), search_set, 4, jax.random.key(0), progress=False)


def test_run_episodes_budget_is_bounded(search_set):
    episodes, _ = E.make_episodes(search_set, E.exact_tables(search_set))
    for call in (lambda: E.run_episodes(episodes, "greedy", budget=10**9),
                 lambda: E.expected_outcomes(episodes, E.truth_probs(search_set), "optimal",
                                             budget=10**8)):
        with pytest.raises(ValueError, match=r"budget=10+ looks .* GB"):
            call()


# ------------------------------------------------------------------ class 3/4: shipped weights


def _copy_weights(tmp_path, name="mlp", edit=None, meta_edit=None):
    """A copy of the shipped weights ``name`` in tmp_path, its arrays changed by ``edit`` and
    its .json by ``meta_edit``, resealed (the SHA-256 and the seal updated) as an attacker would."""
    src = pretrained.PRETRAINED_DIR
    with np.load(src / f"{name}.npz") as data:
        arrays = {k: data[k] for k in data.files}
    if edit:
        edit(arrays)
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    raw = buffer.getvalue()
    meta = json.loads((src / f"{name}.json").read_text())
    meta["sha256"] = __import__("hashlib").sha256(raw).hexdigest()
    if meta_edit:
        meta_edit(meta)
    meta["seal"] = pretrained.seal(meta, raw)
    (tmp_path / f"{name}.npz").write_bytes(raw)
    (tmp_path / f"{name}.json").write_text(json.dumps(meta))
    return tmp_path


def _first_key(arrays):
    return sorted(arrays)[0]


def test_weights_loader_refuses_nan_extra_members_and_bad_metadata(tmp_path):
    ok = tmp_path / "ok"
    ok.mkdir()
    _copy_weights(ok)
    assert predictor.load_pretrained("mlp", ok).step >= 0

    def nan(arrays):
        arrays[_first_key(arrays)].flat[0] = np.nan

    def extra(arrays):
        arrays["bomb"] = np.zeros(10, np.float32)

    def reshaped(arrays):
        key = _first_key(arrays)
        arrays[key] = np.zeros((*arrays[key].shape, 2), np.float32)

    def pickled(arrays):
        key = _first_key(arrays)
        arrays[key] = np.array([object()] * 2, dtype=object)

    cases = [(nan, None, "NaN or inf"), (extra, None, "unexpected member 'bomb.npy'"),
             (reshaped, None, "expected shape"), (pickled, None, "Python objects"),
             (None, lambda m: m.update(step="<script>"), "step must be an int.*'<script>'"),
             (None, lambda m: m.update(step=True), "step"),
             (None, lambda m: m.update(name="flowmaps"), "json name must be one of"),
             (None, lambda m: m.update(kind="flowmaps"), "names kind")]
    for i, (edit, meta_edit, match) in enumerate(cases):
        folder = tmp_path / str(i)
        folder.mkdir()
        _copy_weights(folder, edit=edit, meta_edit=meta_edit)
        with pytest.raises(ValueError, match=match):
            predictor.load_pretrained("mlp", folder)


# ------------------------------------------------------------------ class 4: untrusted .npz


def _zip(path, members: dict[str, bytes]):
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return path


def _npy(array) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def test_read_npz_checks_members_and_sizes_before_decompressing(tmp_path):
    good = _zip(tmp_path / "good.npz", {"a.npy": _npy(np.arange(4))})
    assert untrusted_files.read_npz("f", good, allowed=["a"])["a"].tolist() == [0, 1, 2, 3]
    with pytest.raises(ValueError, match=r"unexpected member 'b.npy'"):
        untrusted_files.read_npz("f", _zip(tmp_path / "x.npz", {"a.npy": _npy(np.arange(4)),
                                                  "b.npy": _npy(np.zeros(3))}), allowed=["a"])
    with pytest.raises(ValueError, match=r"unexpected member 'notes.txt'"):
        untrusted_files.read_npz("f", _zip(tmp_path / "t.npz", {"notes.txt": b"hi"}))
    zeros = _zip(tmp_path / "zeros.npz", {"a.npy": _npy(np.zeros(2_000_000, np.uint8))})
    assert zeros.stat().st_size < 20_000  # 2 MB of zeros compress to almost nothing
    with pytest.raises(ValueError, match=r"declares 0.002 GB .* not reading it"):
        untrusted_files.read_npz("f", zeros, max_bytes=1_000_000)
    buffer = io.BytesIO()  # a header claiming 8 GB, and no data
    np.lib.format.write_array_header_1_0(buffer, {"descr": "<f8", "fortran_order": False,
                                                  "shape": (10**9,)})
    header = buffer.getvalue()
    with pytest.raises(ValueError, match="header claims 8000000000 bytes"):
        untrusted_files.read_npz("f", _zip(tmp_path / "liar.npz", {"a.npy": header}))
    with pytest.raises(ValueError, match="missing arrays"):
        untrusted_files.read_npz("f", good, required=["a", "b"])


def test_load_scenes_refuses_unknown_members_and_oversize(tmp_path, small_scenes,
                                                           flowsim_config, monkeypatch):
    from flowmaps_jax.flowsim.scenes import load_scenes, save_scenes

    scenes = jax.tree_util.tree_map(lambda a: a[:2], small_scenes)
    path = tmp_path / "scenes.npz"
    save_scenes(path, scenes, flowsim_config)
    load_scenes(path)
    with zipfile.ZipFile(path, "a") as archive:
        archive.writestr("extra.npy", _npy(np.zeros(1000, np.uint8)))
    with pytest.raises(ValueError, match=r"load_scenes: .*unexpected member 'extra.npy'"):
        load_scenes(path)
    save_scenes(path, scenes, flowsim_config)
    monkeypatch.setenv(resources.MAX_BYTES_ENV, "1K")
    with pytest.raises(ValueError, match="not reading it"):
        load_scenes(path)


# ------------------------------------------------------------------ names


def test_plain_names():
    for good in ("cpu", "smoke-2", "paper_v1.2", "a+b"):
        assert v.check_plain_name("preset", good) == good
    for bad in ("", "..", "a/b", "/x", ".x", "a..b", "<script>", "a b", "x" * 65, 3, None):
        with pytest.raises(ValueError, match="preset must be a plain name"):
            v.check_plain_name("preset", bad)
