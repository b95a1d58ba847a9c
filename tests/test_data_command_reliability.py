"""``python -m flowmaps_jax.data`` and the recorded files under hostile input (issue 57):

* ``--out``: an existing folder is replaced only with ``--overwrite`` (moved aside), a link there
  is refused, and every command writes aside and renames, so a late refusal or a full disk
  leaves nothing half-written (class 2);
* input that used to be accepted quietly is refused or named (class 4).
"""

from __future__ import annotations

import errno
import json
import os
import re
import shutil

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


# ------------------------------------------------------------ class 4: quietly accepted input


def _authors(tmp_path, extras: bool = False):
    """Two environments in the authors' layout (without flowmaps_recorded.json unless
    ``extras``)."""
    root = tmp_path / "authors"
    export_flowmaps2026(Recorded((tiny_environment("env0"), tiny_environment("env1"))), root)
    if not extras:
        for env in ("env0", "env1"):
            (root / env / "flowmaps_recorded.json").unlink()
    return root


def _import_error(root) -> str:
    from flowmaps_jax.recorded.flowmaps2026 import import_flowmaps2026

    with pytest.raises(ValueError) as info:
        import_flowmaps2026(root)
    return str(info.value)


def test_a_linked_folder_under_the_root_is_refused_not_skipped(tmp_path):
    """A linked environment folder was skipped with no word: the world had one environment."""
    root = _authors(tmp_path)
    (root / "env1").rename(tmp_path / "away")
    (root / "env1").symlink_to(tmp_path / "away")
    assert re.match(rf"^{re.escape(str(root / 'env1'))}: \(folder\): is a symbolic link",
                    _import_error(root))
    (root / "env1").unlink()  # a link to a folder holding environment folders, deeper down
    (tmp_path / "deeper").mkdir()
    (tmp_path / "away").rename(tmp_path / "deeper" / "env1")
    (root / "sub").mkdir()
    (root / "sub" / "more").symlink_to(tmp_path / "deeper")
    assert "sub/more: (folder): is a symbolic link" in _import_error(root)


@pytest.mark.parametrize("file,change,message", [
    ("receptacles_oobb.json", lambda d: d["Sofa|1"].update(cornerPoints=[[True, False, True]] * 8),
     r"receptacles_oobb.json: Sofa\|1.cornerPoints: must be 8 finite"),
    ("receptacles_oobb.json", lambda d: d["Sofa|1"].update(cornerPoints=[["1", "2", "3"]] * 8),
     r"receptacles_oobb.json: Sofa\|1.cornerPoints: must be 8 finite"),
    ("flowmaps_recorded.json", lambda d: d.update(distance=[[False] * 3] * 3),
     "flowmaps_recorded.json: distance: must be an R x R list of numbers")])
def test_true_false_and_text_are_not_numbers_in_json(tmp_path, file, change, message):
    """Corner points of true/false were read as 1.0 / 0.0 (and texts as numbers)."""
    root = _authors(tmp_path, extras=file == "flowmaps_recorded.json")
    path = root / "env0" / file
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))
    assert re.search(message, _import_error(root))


@pytest.mark.parametrize("column", ["aabb_cornerPoints", "rotation", "assignment"])
def test_boolean_parquet_columns_are_numbers_only_for_the_assignment(tmp_path, column):
    import pyarrow as pa
    import pyarrow.parquet as pq

    from flowmaps_jax.recorded.flowmaps2026 import import_flowmaps2026

    root = _authors(tmp_path)
    path = root / "env0" / "scan_merged.parquet"
    table = pq.read_table(path)
    kind = table.schema.field(column).type
    bool_kind, inner = pa.bool_(), kind
    sizes = []
    while pa.types.is_fixed_size_list(inner):
        sizes.append(inner.list_size)
        inner = inner.value_type
    for size in reversed(sizes):
        bool_kind = pa.list_(bool_kind, size)
    values = table.column(column).cast(bool_kind)
    pq.write_table(table.set_column(table.column_names.index(column), column, values), path)
    if column == "assignment":  # a one-hot row of true/false is one of 1/0
        assert import_flowmaps2026(root).names() == ("env0", "env1")
    else:
        assert re.search(rf"scan_merged.parquet: {column}: holds bool, not numbers",
                         _import_error(root))


@pytest.mark.parametrize("names", [("scan_1", "scan_01"), ("scan_0", "scan_000")])
def test_two_scan_pieces_of_the_same_number_are_refused(tmp_path, names):
    """scan_1 and scan_01 were both read as piece 1: every hour twice."""
    root = _authors(tmp_path)
    folder = root / "env0"
    for name in names:
        shutil.copy(folder / "scan_merged.parquet", folder / f"{name}.parquet")
    (folder / "scan_merged.parquet").unlink()
    first, second = sorted(names)
    assert re.match(rf"^{re.escape(str(folder))}: \(folder\): {first}.parquet and "
                    rf"{second}.parquet are both scan piece", _import_error(root))


# ---------------------------------------------------------------------------- class 5: wrong words


@pytest.mark.parametrize("where", ["scan_merged.parquet", "scan_1.parquet"])
@pytest.mark.parametrize("kind", ["fifo", "folder"])
def test_a_scan_file_that_is_not_a_file_is_named(tmp_path, where, kind):
    """A FIFO at scan_merged.parquet said "need at least one array to concatenate"."""
    root = _authors(tmp_path)
    folder = root / "env0"
    (folder / "scan_merged.parquet").rename(folder / "scan_0.parquet")
    target = folder / where
    os.mkfifo(target) if kind == "fifo" else target.mkdir()
    assert _import_error(root) == f"{target}: (file): not a regular file"


@pytest.mark.parametrize("file,old,new", [
    ("receptacle_names.json", "Sofa|1", "Sofa|\u0001"),
    ("pickupable_names.json", "Mug|2", "Mug|" + "x" * 300)])
def test_a_bad_id_is_blamed_on_the_file_that_lists_it(tmp_path, file, old, new):
    """A non-printable receptacle id was blamed on pickupable_to_receptacle.json."""
    root = _authors(tmp_path)
    for path in (root / "env0").glob("*.json"):
        path.write_text(path.read_text().replace(json.dumps(old), json.dumps(new)))
    index = json.loads((root / "env0" / file).read_text()).index(new)
    assert _import_error(root).startswith(f"{root / 'env0' / file}: [{index}]: must be a "
                                          f"non-empty printable string")
