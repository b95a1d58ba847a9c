"""Sizes read from files go through the shared budget (``flowmaps_jax.resources``) before
anything is allocated, and a refusal is one line naming the file and the size: JSON text,
``.npz`` arrays, recorded worlds (objects x receptacles, walking distances through doors, all
environments together), the authors' parquet scans and their export.

Small files in tmp_path, with ``FLOWMAPS_MAX_BYTES`` set low where a refusal is wanted."""

from __future__ import annotations

import io
import json
import pathlib
import tracemalloc

import numpy as np
import pytest
from test_recorded import ASSIGNMENT, tiny_environment, write_authors_environment, write_lookup

from flowmaps_jax.recorded import Recorded, load_recorded, save_recorded
from flowmaps_jax.recorded.flowmaps2026 import export_flowmaps2026, import_flowmaps2026
from flowmaps_jax.recorded.format import ENVIRONMENT_FILE, INDEX_FILE
from flowmaps_jax.untrusted_files import parse_json, read_npz


def _world(tmp_path, count: int = 1, **changes) -> pathlib.Path:
    path = tmp_path / "world"
    save_recorded(Recorded(tuple(tiny_environment(f"env{i}", **changes)
                                 for i in range(count))), path)
    return path


def test_json_depth_check_is_linear_in_escaped_quotes(tmp_path):
    # an unterminated string of escaped quotes: the old pre-check retried from every quote
    world = _world(tmp_path)
    (world / INDEX_FILE).write_text('["' + 'a\\"' * 50_000)  # 150 KB: minutes before
    with pytest.raises(ValueError, match=r"recorded\.json.*not valid JSON"):
        load_recorded(world)
    with pytest.raises(ValueError, match="not valid JSON"):
        parse_json("f", '"\\"' * 50_000)
    # an unterminated string runs to the end (one pass): the parser names it
    with pytest.raises(ValueError, match=r"not valid JSON \(Unterminated string"):
        parse_json("f", '["' + "[" * 100)
    # strings are still skipped, and nesting after them still counted
    assert parse_json("f", '{"a": "[[\\"]]", "b": [[1]]}') == {"a": '[["]]', "b": [[1]]}
    with pytest.raises(ValueError, match="nested 100 levels deep"):
        parse_json("f", '["\\"", ' + "[" * 99 + "]" * 99 + "]")


def test_objects_x_receptacles_is_sized_before_it_is_allocated(tmp_path, monkeypatch):
    world = _world(tmp_path)
    file = world / "env0" / ENVIRONMENT_FILE
    data = json.loads(file.read_text())
    data["receptacles"] = [{"id": f"R|{i}", "class": "R", "text": "r", "room": None}
                           for i in range(3000)]
    data["objects"] = [{"id": f"O|{i}", "class": "O", "text": "o", "allowed": [0]}
                       for i in range(3000)]
    file.write_text(json.dumps(data))
    monkeypatch.setenv("FLOWMAPS_MAX_BYTES", "1M")
    with pytest.raises(ValueError, match=r"environment\.json: 3000 objects x 3000 receptacles "
                                         r"would need about 0\.009 GB"):
        load_recorded(world)
    # the authors' layout: the same matrix from its name lists
    root = tmp_path / "authors"
    root.mkdir()
    write_lookup(root)
    write_authors_environment(root / "env0", objects=[f"Book|{i}" for i in range(2000)],
                              assignment=np.zeros((5, 2000, 3), np.int64))
    monkeypatch.setenv("FLOWMAPS_MAX_BYTES", "5000")
    with pytest.raises(ValueError, match=r"pickupable_names\.json: 2000 objects x 3 "
                                         r"receptacles would need"):
        import_flowmaps2026(root)


def test_npz_totals_are_checked_first_and_the_data_read_once(tmp_path, monkeypatch):
    # three environments that each fit, and together do not
    world = _world(tmp_path, 3)
    load_recorded(world)
    monkeypatch.setenv("FLOWMAPS_MAX_BYTES", "1000")
    with pytest.raises(ValueError, match=r"env[12]/arrays\.npz (declares|holds) .* GB of "
                                         r"arrays, more than"):
        load_recorded(world)
    monkeypatch.delenv("FLOWMAPS_MAX_BYTES")
    # read once, into the array: the peak is about the array, not twice it
    big = np.zeros(2_000_000, np.float32)  # 8 MB
    buffer = io.BytesIO()
    np.savez_compressed(buffer, a=big, f=np.asfortranarray(np.arange(6.0).reshape(2, 3)),
                        b=np.arange(3, dtype=">i4"))
    tracemalloc.start()
    arrays = read_npz("f", io.BytesIO(buffer.getvalue()))
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 1.5 * big.nbytes
    np.testing.assert_array_equal(arrays["f"], np.arange(6.0).reshape(2, 3))
    assert arrays["b"].dtype == np.dtype(">i4") and arrays["b"].tolist() == [0, 1, 2]


def _rooms(doors: int, **changes):
    """Three rooms in a row, receptacles 0, 1 in room 0 and 2 in room 2; ``doors`` doors."""
    fields = dict(receptacle_room=np.asarray([0, 0, 2], np.int32),
                  room_classes=("a", "b", "c"),
                  room_boxes=np.asarray([[0, 0, 2, 1], [2, 0, 4, 1], [4, 0, 6, 1]], np.float32),
                  door_rooms=np.tile(np.asarray([[0, 1]], np.int32), (doors, 1)),
                  door_positions=np.tile(np.asarray([[2.0, 0.5]], np.float32), (doors, 1)))
    fields.update(changes)
    return tiny_environment("env0", **fields)


def test_walking_distances_through_doors_are_bounded_and_exact(tmp_path, monkeypatch):
    # two doors in a row: 0 -> (2, 0.5) -> (4, 0.5) -> 2 (the Dijkstra over doors)
    env = _rooms(2, door_rooms=np.asarray([[0, 1], [1, 2]], np.int32),
                 door_positions=np.asarray([[2.0, 0.5], [4.0, 0.5]], np.float32))
    walk = env.walking_distance()  # centres (0.5, 0.5) and (2.5, 0.5): 1.5 + 2 + 1.5
    assert walk[0, 2] == pytest.approx(5.0) and walk[2, 0] == pytest.approx(5.0)
    assert walk[0, 1] == pytest.approx(1.0)
    # 3,000 doors: refused up front under a small budget, naming the file and the count
    save_recorded(Recorded((_rooms(3000),)), tmp_path / "doors")
    monkeypatch.setenv("FLOWMAPS_MAX_BYTES", "10M")
    with pytest.raises(ValueError, match=r"environment\.json: walking distances between 3 "
                                         r"receptacles through 3000 doors would need"):
        load_recorded(tmp_path / "doors")
    with pytest.raises(ValueError, match=r"environment 'env0': walking distances .* 3000 doors"):
        _rooms(3000).walking_distance()


def test_parquet_is_sized_by_its_values_not_its_encoded_bytes(tmp_path, monkeypatch):
    root = tmp_path / "authors"
    root.mkdir()
    write_lookup(root)
    write_authors_environment(root / "env0",
                              assignment=np.zeros((20_000, *ASSIGNMENT.shape[1:]), np.int64))
    monkeypatch.setenv("FLOWMAPS_MAX_BYTES", "10M")  # the file holds 1.1 M zeros: 27 MB read
    with pytest.raises(ValueError, match=r"scan_merged\.parquet: 20000 rows of 1120000 values "
                                         r"would need about 0\.0269 GB"):
        import_flowmaps2026(root)
    monkeypatch.delenv("FLOWMAPS_MAX_BYTES")
    import pyarrow.parquet as pq

    def short_of_memory(*args, **kwargs):
        raise MemoryError
    monkeypatch.setattr(pq, "read_table", short_of_memory)  # a ulimit: not a "broken file"
    with pytest.raises(ValueError, match=r"scan_merged\.parquet: \(file\): not enough memory "
                                         r"to read 20000 rows of 1120000 values"):
        import_flowmaps2026(root)


def test_export_checks_every_environment_before_writing_any(tmp_path, monkeypatch):
    gap = np.asarray([0, 1, 2, 1_000_000], np.int64)  # a gap: a million hourly rows
    world = Recorded((tiny_environment("env0"), tiny_environment("env1", hours=gap)))
    monkeypatch.setenv("FLOWMAPS_MAX_BYTES", "400M")  # what is built: 0.636 GB at the peak
    with pytest.raises(ValueError, match=r"exporting 'env1' \(1000001 hourly rows x 2 objects\) "
                                         r"would need about 0\.636 GB"):
        export_flowmaps2026(world, tmp_path / "out")
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_queries_on_recorded_data_are_sized_as_on_flowsim_homes(tmp_path):
    # the check FlowSim homes' evaluate and search run, on a recorded world's own sizes (the
    # recorded evaluate and search call it before any query is drawn)
    from flowmaps_jax.evaluation.receptacle_protocol import check_query_size
    from flowmaps_jax.worlds.recorded import homes_config_of

    config = homes_config_of(load_recorded(_world(tmp_path, 3)))
    check_query_size(config, 3, 8, 8)
    with pytest.raises(ValueError, match=r"--num-envs 3 x --queries 100000000000 would need "
                                         r"about .* GB, more than"):
        check_query_size(config, 3, 10**11, 8)
