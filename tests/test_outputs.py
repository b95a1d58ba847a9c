"""What a command writes: every output is checked up front (a link, a file or a folder in the
way, a folder that cannot be made), written aside and renamed (never half an output), the
packaged weights are never overwritten unless their folder is named, and a full disk is one
line with exit code 74.
"""

from __future__ import annotations

import errno
import hashlib
import inspect
import os
import pathlib

import jax
import pytest
from support import error_line, only_error_line, run_cli
from test_recorded import tiny_environment

from flowmaps_jax import atomic_files, export
from flowmaps_jax import export as export_cli
from flowmaps_jax.atomic_files import write_files
from flowmaps_jax.data.__main__ import main
from flowmaps_jax.evaluation import cli as eval_cli
from flowmaps_jax.evaluation import report as eval_report
from flowmaps_jax.flowsim import FlowSimConfig
from flowmaps_jax.flowsim.homes import HomesConfig, generate_homes, save_homes
from flowmaps_jax.flowsim.homes.export import schema_path
from flowmaps_jax.recorded import Recorded, load_recorded, save_recorded
from flowmaps_jax.recorded.flowmaps2026 import export_flowmaps2026
from flowmaps_jax.search import cli as search_cli
from flowmaps_jax.search import report as search_report
from flowmaps_jax.store import pretrained, rundir
from flowmaps_jax.training import runlog

_cli, _error_line = run_cli, error_line  # tests/support.py


_one_line = only_error_line  # tests/support.py


"""Per class: one entry per reproduction tried, True when it behaved (reported at the end)."""


def _outside(tmp_path) -> pathlib.Path:
    target = tmp_path / "elsewhere.txt"
    target.write_text("keep")
    return target


def _world(tmp_path, *names: str):
    path = tmp_path / "world"
    save_recorded(Recorded(tuple(tiny_environment(n) for n in names)), path)
    return path


def _files(path) -> dict:
    """Every file under ``path`` -> its bytes (links not followed)."""
    return {os.path.relpath(os.path.join(here, f), path): open(os.path.join(here, f), "rb").read()
            for here, _, files in os.walk(path) for f in files}


# ----------------------------------------------------- evaluate and search CLIs


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


# ------------------------------------------------------ no write through a link


@pytest.mark.parametrize("name", ["search.json", "search.md", "episodes.png"])
def test_search_refuses_a_link_at_an_output_name(tmp_path, capsys, name):
    target, out = _outside(tmp_path), tmp_path / "runs" / "x"
    out.mkdir(parents=True)
    (out / name).symlink_to(target)
    argv = ["--checkpoint", "pretrained:flowmaps", "--num-envs", "1", "--out", str(out)]
    code, _, err = _cli(search_cli.main, argv + ([] if name.endswith("png") else
                                                ["--no-figures"]), capsys)
    ok = code == 2 and "symbolic link" in _error_line(err) and target.read_text() == "keep"
    assert ok, (code, err)


@pytest.mark.parametrize("name", ["results.json", "results.md", "kl.png"])
def test_evaluate_refuses_a_link_at_an_output_name(tmp_path, capsys, name):
    target, out = _outside(tmp_path), tmp_path / "runs" / "x"
    out.mkdir(parents=True)
    (out / name).symlink_to(target)
    argv = ["--checkpoint", "pretrained:flowmaps", "--num-envs", "1", "--out", str(out)]
    code, _, err = _cli(eval_cli.main, argv + ([] if name.endswith("png") else
                                              ["--no-figures"]), capsys)
    ok = code == 2 and "symbolic link" in _error_line(err) and target.read_text() == "keep"
    assert ok, (code, err)


def test_every_writer_refuses_a_link_and_writes_through_a_rename(tmp_path):
    target = _outside(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    results = {"protocol": {}, "rows": {}}
    for name, write in (("results.json", eval_report.write_report),
                        ("search.json", search_report.write_report)):
        (out / name).symlink_to(target)
        with pytest.raises(ValueError, match="symbolic link"):
            write(results, out)
        (out / name).unlink()
    link = out / "file.bin"
    link.symlink_to(target)
    with pytest.raises(ValueError, match="symbolic link"):
        atomic_files.write_file(link, b"new")
    with pytest.raises(ValueError, match="symbolic link"):
        rundir.write_atomic(link, "new")  # train's writer is the same one
    import matplotlib.pyplot as plt

    figure = plt.figure()
    (out / "plot.png").symlink_to(target)
    with pytest.raises(ValueError, match="symbolic link"):
        atomic_files.save_figure(figure, out / "plot.png")
    plt.close(figure)
    # a link planted at the temporary name is removed, never followed
    (out / "fine.txt.tmp").symlink_to(target)
    atomic_files.write_file(out / "fine.txt", "written")
    assert (out / "fine.txt").read_text() == "written" and not (out / "fine.txt.tmp").exists()
    # a folder the writer creates is made component by component; a file in the way is named
    (out / "afile").write_text("x")
    with pytest.raises(ValueError, match="not a directory"):
        atomic_files.make_output_dir("--out", out / "afile" / "sub")
    assert atomic_files.make_output_dir("--out", out / "a" / "b").is_dir()
    ok = target.read_text() == "keep"
    assert ok


def test_save_scenes_and_export_refuse_a_link(tmp_path):
    from flowmaps_jax.export import export_pretrained
    from flowmaps_jax.flowsim.scenes import save_scenes, validation_split

    target = _outside(tmp_path)
    (tmp_path / "scenes.npz").symlink_to(target)
    config = FlowSimConfig()
    with pytest.raises(ValueError, match="symbolic link"):
        save_scenes(tmp_path / "scenes.npz", validation_split(config, num_envs=1), config)
    shipped = tmp_path / "shipped"
    shipped.mkdir()
    (shipped / "mlp.json").symlink_to(target)
    with pytest.raises(ValueError, match="symbolic link"):  # before the checkpoint is read
        export_pretrained(tmp_path / "no-such-run", "mlp", shipped)
    ok = target.read_text() == "keep"
    assert ok


# --------------------------------------------------------- the packaged weights


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


# ---------------------------------------------------------------------- outputs


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


# ------------------------------------------------------------------------ --out


def test_an_existing_world_is_replaced_only_with_overwrite(tmp_path, capsys):
    world = _world(tmp_path, "env0", "env1")
    authors = tmp_path / "authors"
    export_flowmaps2026(load_recorded(world), authors)
    target = _world(tmp_path / "t", "env0", "env1", "env2")  # three environments
    before = _files(target)
    for argv in (["import-flowmaps2026", str(authors)],
                 ["from-homes", "--homes", "1", "--hours", "4"],
                 ["export-flowmaps2026", str(world)]):
        code, _, err = run_cli(main, [*argv, "--out", str(target), "--no-progress"], capsys)
        assert code == 2, argv
        assert "--out" in error_line(err) and "--overwrite" in err, err
        assert _files(target) == before
    code, out, _ = run_cli(main, ["import-flowmaps2026", str(authors), "--out", str(target),
                                  "--overwrite", "--no-progress"], capsys)
    assert code == 0 and "moved the old" in out
    assert load_recorded(target).names() == ("env0", "env1")  # not env2 of the old world
    old = [p for p in target.parent.iterdir() if p.name.startswith("world.old-")]
    assert len(old) == 1 and _files(old[0]) == before
    assert sorted(p.name for p in target.parent.iterdir()) == ["world", old[0].name]


def test_a_link_at_out_is_refused_by_every_command(tmp_path, capsys):
    world = _world(tmp_path, "env0")
    export_flowmaps2026(load_recorded(world), tmp_path / "authors")
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "elsewhere")
    for argv in (["import-flowmaps2026", str(tmp_path / "authors")],
                 ["export-flowmaps2026", str(world)],
                 ["from-homes", "--homes", "1", "--hours", "4"]):
        for extra in ([], ["--overwrite"]):
            code, _, err = run_cli(main, [*argv, *extra, "--out", str(tmp_path / "link"),
                                          "--no-progress"], capsys)
            assert code == 2, argv
            assert "is a symbolic link" in error_line(err) and "--out" in err, err
    assert not any((tmp_path / "elsewhere").iterdir())
    assert (tmp_path / "link").is_symlink()


@pytest.mark.parametrize("failure", [ValueError("refused late"),
                                     OSError(errno.ENOSPC, "No space left on device")])
def test_a_late_failure_leaves_nothing_half_written(tmp_path, capsys, monkeypatch, failure):
    """Export wrote one environment at a time: a refusal or a full disk at the third left the
    first two (and lookup.json) behind. Now nothing is left, and an empty --out stays empty."""
    from flowmaps_jax.recorded import flowmaps2026

    world = _world(tmp_path, "env0", "env1", "env2")
    real, calls = flowmaps2026.export_files, []

    def failing(env):
        calls.append(env.name)
        if len(calls) == 3:
            raise failure
        return real(env)

    monkeypatch.setattr(flowmaps2026, "export_files", failing)
    (tmp_path / "empty").mkdir()
    for out in ("empty", "new"):
        calls.clear()
        code, _, err = run_cli(main, ["export-flowmaps2026", str(world), "--out",
                                      str(tmp_path / out), "--no-progress"], capsys)
        assert code == (2 if isinstance(failure, ValueError) else 74)
        assert str(failure.args[-1]) in error_line(err)
    assert not any((tmp_path / "empty").iterdir()) and not (tmp_path / "new").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty", "world"]  # no temporary
    # and the same for a recorded world written by import
    monkeypatch.setattr(flowmaps2026, "export_files", real)
    export_flowmaps2026(load_recorded(world), tmp_path / "authors")
    monkeypatch.setattr("flowmaps_jax.data.__main__.save_recorded",
                        lambda *a: (_ for _ in ()).throw(OSError(errno.ENOSPC, "disk full")))
    code, _, err = run_cli(main, ["import-flowmaps2026", str(tmp_path / "authors"), "--out",
                                  str(tmp_path / "w2"), "--no-progress"], capsys)
    assert code == 74 and "disk full" in error_line(err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["authors", "empty", "world"]
