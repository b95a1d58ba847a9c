"""A new user's first dataset (issue 56, items 3 and 4 and its "other friction"): ``python -m
flowmaps_jax.data validate``, the authors' layout named on ``--data``, integer dtypes of
``location``, one default split with a warning for few environments and a time split, a search
start that does not depend on the receptacle list's order, a recorded run's printed config."""

from __future__ import annotations

import dataclasses
import io
import pathlib
import zipfile

import numpy as np
import pytest

from flowmaps_jax.data.__main__ import main as data_main
from flowmaps_jax.recorded.format import Environment, Recorded, load_recorded, save_recorded
from flowmaps_jax.training import loop
from flowmaps_jax.training.config import (
    format_config,
    homes_smoke_preset,
    recorded_homes_preset,
    recorded_smoke_preset,
)
from flowmaps_jax.worlds import recorded as rw

DOCS = pathlib.Path(__file__).resolve().parents[1] / "docs"


def _box(x0, y0, x1, y1, h=0.8):
    return [[x, y, z] for z in (0.0, h) for x, y in ((x0, y0), (x1, y0), (x1, y1), (x0, y1))]


def _env(name: str, hours: int = 72, seed: int = 0) -> Environment:
    """3 receptacles in a row, 2 objects moving among them, a third of the hours unseen."""
    rng = np.random.default_rng(seed)
    location = rng.integers(0, 3, (hours, 2))
    location[rng.random((hours, 2)) < 0.3] = -1
    return Environment(
        name=name, receptacle_ids=("Sofa|1", "Table|2", "Shelf|3"),
        receptacle_classes=("Sofa", "Table", "Shelf"), receptacle_texts=("sofa", "table", "shelf"),
        receptacle_room=np.asarray([0, 0, 1], np.int32),
        receptacle_corners=np.asarray([_box(0, 0, 1, 1), _box(2, 0, 3, 1), _box(7, 0, 8, 1)],
                                      np.float32),
        object_ids=("Book|1", "Mug|2"), object_classes=("Book", "Mug"),
        object_texts=("book", "mug"), allowed=np.ones((2, 3), bool),
        hours=np.arange(hours, dtype=np.int64), location=location.astype(np.int32),
        room_classes=("living_room", "office"),
        room_boxes=np.asarray([[0, 0, 5, 2], [5, 0, 9, 2]], np.float32),
        door_rooms=np.asarray([[0, 1]], np.int32), door_positions=np.asarray([[5, 1]], np.float32))


def _dataset(path, count: int = 3, **kw) -> pathlib.Path:
    save_recorded(Recorded(tuple(_env(f"home{e}", seed=e, **kw) for e in range(count))), path)
    return path


def test_validate_prints_a_one_screen_summary(tmp_path, capsys):
    assert data_main(["validate", str(_dataset(tmp_path / "d", 5))]) == 0
    out = capsys.readouterr().out
    assert len(out.splitlines()) <= 24
    for text in ("5 environments, 72 hours, 2 objects, 3 receptacles", "% of the object-hours",
                 "hours spanned (first to last): 72 (3.0 days", "object classes: Book, Mug",
                 "room classes: living_room, office", "rooms in all, doors in all",
                 "stored walking distances in 0 of 5", "val_fraction=0.1", "train (3): ",
                 "warning: val 1 and test 1 environments", "time_fraction=0.25"):
        assert text in out, text


def test_validate_refuses_a_bad_dataset_with_one_line(tmp_path, capsys):
    path = _dataset(tmp_path / "d", 1)
    (path / "home0" / "arrays.npz").write_bytes(b"not a zip")
    assert data_main(["validate", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "arrays.npz" in err[0]


def test_the_authors_layout_names_the_importer(tmp_path, capsys):
    env = tmp_path / "authors" / "train" / "env0"
    env.mkdir(parents=True)
    (env / "scan_merged.parquet").write_bytes(b"")
    with pytest.raises(ValueError, match=r"import-flowmaps2026 .*authors --out"):
        load_recorded(tmp_path / "authors")
    assert data_main(["validate", str(tmp_path / "authors")]) == 2
    assert "import-flowmaps2026" in capsys.readouterr().err
    (tmp_path / "other").mkdir()
    with pytest.raises(ValueError, match=r"no recorded\.json\)$"):
        load_recorded(tmp_path / "other")  # no hint where it does not apply


@pytest.mark.parametrize("dtype", [np.int64, np.int16, np.uint8])
def test_location_of_any_integer_dtype_that_fits_is_accepted(tmp_path, dtype):
    env = _env("home0")
    location = np.where(env.location < 0, 0, env.location).astype(dtype)
    path = tmp_path / "d"
    save_recorded(Recorded((dataclasses.replace(env, location=location),)), path)
    loaded = load_recorded(path).environments[0]
    assert loaded.location.dtype == np.int32
    np.testing.assert_array_equal(loaded.location, location)
    # a file written by another tool with numpy's default int64 loads too
    with zipfile.ZipFile(path / "home0" / "arrays.npz") as z:
        arrays = {n[:-4]: np.load(io.BytesIO(z.read(n))) for n in z.namelist()}
    np.savez(path / "home0" / "arrays.npz", **{**arrays, "location": env.location.astype(
        np.int64), "hours": env.hours.astype(np.int32)})
    loaded = load_recorded(path).environments[0]
    assert loaded.location.dtype == np.int32 and loaded.hours.dtype == np.int64


def test_location_out_of_the_int32_range_is_refused(tmp_path):
    env = _env("home0")
    far = env.location.astype(np.int64)
    far[0, 0] = 2 ** 40
    with pytest.raises(ValueError, match="location: holds 1099511627776, outside the range of "
                                         "int32"):
        save_recorded(Recorded((dataclasses.replace(env, location=far),)), tmp_path / "d")
    with pytest.raises(ValueError, match="location: has shape"):
        save_recorded(Recorded((dataclasses.replace(env, location=far.astype(float)),)),
                      tmp_path / "d")


def test_one_default_split_in_every_recipe_and_the_docs():
    fractions = {(c.val_fraction, c.test_fraction, c.time_fraction)
                 for c in (recorded_smoke_preset(), recorded_homes_preset())}
    assert fractions == {(0.1, 0.1, 0.0)}
    assert "default 10 % / 10 %, in every recipe" in (DOCS / "protocol.md").read_text()


@pytest.mark.parametrize("count, fractions, warned", [
    (10, (0.1, 0.1, 0.0), "val 1 and test 1 environments"),
    (40, (0.1, 0.1, 0.0), None),
    (2, (0.1, 0.1, 0.0), "val 0 and test 0 environments"),
    (40, (0.05, 0.1, 0.0), "val 2 environments"),
    (10, (0.0, 0.0, 0.25), None),   # validation and test by time: every home
    (10, (0.0, 0.1, 0.25), None),   # test by environment and by time
])
def test_few_held_out_environments_draw_one_warning_line(count, fractions, warned):
    names = [f"home{i}" for i in range(count)]
    split = rw.split_environments(names, *fractions[:2], seed=0)
    text = rw.describe_split(Recorded(tuple(_Named(n) for n in names)), split, fractions[2])
    lines = [line for line in text.splitlines() if "warning" in line]
    assert len(lines) == (warned is not None)
    if warned:
        assert warned in lines[0] and "--set time_fraction=0.25" in lines[0]


@dataclasses.dataclass(frozen=True)
class _Named:
    name: str


def test_a_time_split_validates_and_tests_on_the_last_hours_of_every_home(tmp_path):
    recorded = load_recorded(_dataset(tmp_path / "d", 3))
    config = rw.homes_config_of(recorded)
    split = (0.0, 0.0, 0.25, 0)
    parts = {p: rw.part_of(recorded, config, rw.split(recorded, split), p) for p in rw.SPLITS}
    for part, (start, stop) in {"train": (0, 54), "val": (54, 63), "test": (63, 72)}.items():
        assert parts[part].num_homes == 3
        assert list(np.asarray(parts[part].start)) == [start] * 3, part
        assert list(np.asarray(parts[part].stop)) == [stop] * 3, part
    assert rw.split(recorded, split)["val"][0] == (0, 1, 2)
    # with validation environments the whole held-out quarter tests, as before
    test = rw.part_of(recorded, config, rw.split(recorded, (0.2, 0.0, 0.25, 0)), "test")
    assert list(np.asarray(test.start)) == [54, 54]


def _permuted(env: Environment, order) -> Environment:
    """``env`` with its receptacle list in ``order``."""
    order = np.asarray(order)
    back = np.argsort(order)
    pick = lambda values: tuple(values[i] for i in order)  # noqa: E731
    return dataclasses.replace(
        env, receptacle_ids=pick(env.receptacle_ids),
        receptacle_classes=pick(env.receptacle_classes),
        receptacle_texts=pick(env.receptacle_texts), receptacle_room=env.receptacle_room[order],
        receptacle_corners=env.receptacle_corners[order], allowed=env.allowed[:, order],
        location=np.where(env.location >= 0, back[np.maximum(env.location, 0)], -1).astype(
            np.int32))


def test_the_search_start_does_not_depend_on_the_receptacle_order():
    from flowmaps_jax.evaluation.realised import start_distance

    env = _env("home0")
    orders = [(0, 1, 2), (2, 0, 1), (1, 2, 0)]
    recorded = Recorded(tuple(_permuted(env, o) for o in orders))
    homes = rw.recorded_homes(recorded, rw.homes_config_of(recorded)).homes
    start = np.asarray(start_distance(homes))
    by_id = [dict(zip([env.receptacle_ids[i] for i in o], start[e], strict=True))
             for e, o in enumerate(orders)]
    assert by_id[0] == by_id[1] == by_id[2]
    assert by_id[0]["Table|2"] == 0.0  # the middle receptacle: nearest all the others


def test_a_recorded_run_prints_only_what_applies_to_it():
    recorded = format_config(recorded_smoke_preset())
    for absent in ("homes.regime", "routine_probs", "homes.preference_move", "chunk_homes",
                   "val_homes"):
        assert absent not in recorded, absent
    assert "homes.num_hours" in recorded and "val_fraction" in recorded
    assert "homes.regime" in format_config(homes_smoke_preset())  # the homes world's own
    assert "next" not in loop.postfix({"loss": 1.0}, None, None, routine_on=False)
    assert loop.postfix({"loss": 1.0}, 0.5, None, routine_on=True)["next"] == "-"
