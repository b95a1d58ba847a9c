"""``python -m flowmaps_jax.data`` and the recorded files under hostile input (issue 57):

* ``--out``: an existing folder is replaced only with ``--overwrite`` (moved aside), a link there
  is refused, and every command writes aside and renames, so a late refusal or a full disk
  leaves nothing half-written (class 2);
* input that used to be accepted quietly is refused or named (class 4).
"""

from __future__ import annotations

import errno
import os

import pytest
from support import error_line, run_cli
from test_recorded import tiny_environment

from flowmaps_jax.data.__main__ import main
from flowmaps_jax.recorded import Recorded, load_recorded, save_recorded
from flowmaps_jax.recorded.flowmaps2026 import export_flowmaps2026


def _world(tmp_path, *names: str):
    path = tmp_path / "world"
    save_recorded(Recorded(tuple(tiny_environment(n) for n in names)), path)
    return path


def _tree(path) -> dict:
    """Every file under ``path`` -> its bytes (links not followed)."""
    return {os.path.relpath(os.path.join(here, f), path): open(os.path.join(here, f), "rb").read()
            for here, _, files in os.walk(path) for f in files}


# ---------------------------------------------------------------------------- class 2: --out


def test_an_existing_world_is_replaced_only_with_overwrite(tmp_path, capsys):
    world = _world(tmp_path, "env0", "env1")
    authors = tmp_path / "authors"
    export_flowmaps2026(load_recorded(world), authors)
    target = _world(tmp_path / "t", "env0", "env1", "env2")  # three environments
    before = _tree(target)
    for argv in (["import-flowmaps2026", str(authors)],
                 ["from-homes", "--homes", "1", "--hours", "4"],
                 ["export-flowmaps2026", str(world)]):
        code, _, err = run_cli(main, [*argv, "--out", str(target), "--no-progress"], capsys)
        assert code == 2, argv
        assert "--out" in error_line(err) and "--overwrite" in err, err
        assert _tree(target) == before
    code, out, _ = run_cli(main, ["import-flowmaps2026", str(authors), "--out", str(target),
                                  "--overwrite", "--no-progress"], capsys)
    assert code == 0 and "moved the old" in out
    assert load_recorded(target).names() == ("env0", "env1")  # not env2 of the old world
    old = [p for p in target.parent.iterdir() if p.name.startswith("world.old-")]
    assert len(old) == 1 and _tree(old[0]) == before
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
