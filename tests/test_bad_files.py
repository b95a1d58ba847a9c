"""Untrusted files: shipped weights and their sealed JSON, ``.npz`` members and sizes, JSON depth,
and recorded datasets (values that used to be accepted quietly, ids blamed on the file that
lists them) are refused with a ``ValueError`` naming the file, never read wrongly.
"""

from __future__ import annotations

import io
import json
import os
import pathlib
import re
import shutil
import zipfile

import jax
import numpy as np
import pytest
from test_recorded import tiny_environment

from flowmaps_jax import predictor, resources, untrusted_files
from flowmaps_jax.flowsim.homes import HomesConfig, generate_homes, load_homes, save_homes
from flowmaps_jax.recorded import Recorded
from flowmaps_jax.recorded.flowmaps2026 import export_flowmaps2026
from flowmaps_jax.store import pretrained, reseal, rundir
from flowmaps_jax.training import resume
from flowmaps_jax.untrusted_files import parse_json, read_json

# -------------------------------------------------------------- shipped weights


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


# --------------------------------------------------------------- untrusted .npz


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


# --------------------------------------------------------------- a sealed model


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


# --------------------------------------------------------------- untrusted JSON


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


# ------------------------------------------------------- quietly accepted input


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


# ------------------------------------------------------------------ wrong words


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
