"""Checkpoint store: round trip, last-k + best retention, checksums and finiteness verified on
restore, older steps by number, clear errors on bad directories and failed writes."""

import errno
import gc
import json
import logging
import pathlib
import shutil
import sys

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
import pytest

from flowmaps_jax.store import checkpoints, integrity
from flowmaps_jax.store.checkpoint_store import CheckpointSaveError, CheckpointStore
from flowmaps_jax.store.integrity import NonFiniteStateError
from flowmaps_jax.training import objectives
from flowmaps_jax.training import state as train_state
from flowmaps_jax.training.config import get_preset
from flowmaps_jax.training.resume import load_config

# orbax leaves un-awaited read coroutines behind after a failed restore (tests below damage
# checkpoints on purpose); they surface as "unraisable exception" warnings, possibly during a
# later test of this module.
pytestmark = pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")

CFG = get_preset("smoke")
# A stand-in model: a tiny params pytree is enough to exercise the whole TrainState.
OBJECTIVE = objectives.Objective(
    init=lambda key: {"dense": {"w": jax.random.normal(key, (3, 4)), "b": jnp.zeros(4)}},
    loss=None)


def _state_at(step: int) -> train_state.TrainState:
    state = train_state.init_state(CFG, jax.random.PRNGKey(1), OBJECTIVE)
    params = jax.tree.map(lambda x: x + step, state.params)
    return state.replace(step=jnp.asarray(step, jnp.int32), params=params,
                         ema_params=jax.tree.map(lambda x: 0.5 * x, params))


def _target():
    return train_state.abstract_state(CFG, OBJECTIVE)


def _assert_same(a, b):
    leaves_a, tree_a = jax.tree.flatten(a)
    leaves_b, tree_b = jax.tree.flatten(b)
    assert tree_a == tree_b
    for x, y in zip(leaves_a, leaves_b, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.fixture
def saved(tmp_path):
    """A checkpoint dir with steps 1..4 saved (keep 2) and a best at step 2 (val 0.5)."""
    root = tmp_path / "checkpoints"
    with CheckpointStore(root, keep_last=2) as store:
        for step in range(1, 5):
            store.save(_state_at(step), CFG.to_dict())
            if step in (2, 3):
                store.save_if_best(_state_at(step), CFG.to_dict(), {2: 0.5, 3: 0.7}[step])
    return root


def test_round_trip_restores_every_field(saved):
    state, config = checkpoints.restore(saved, _target())[:2]
    assert isinstance(state, train_state.TrainState)
    _assert_same(state, _state_at(4))
    assert config == CFG.to_dict()
    assert load_config(saved) == CFG


def test_keeps_last_k_and_the_best_even_when_it_falls_out(saved):
    assert sorted(int(p.name) for p in (saved / "last").iterdir()) == [3, 4]
    best = checkpoints.restore(saved, _target(), which="best").state
    assert int(best.step) == 2  # step 3 had a worse validation loss and step 2 left last-k
    _assert_same(best, _state_at(2))


def test_best_is_replaced_only_by_a_lower_loss_and_survives_reopening(saved):
    with CheckpointStore(saved, keep_last=2) as store:
        assert store.best_val_loss == 0.5
        assert not store.save_if_best(_state_at(5), CFG.to_dict(), 0.6)
        assert not store.save_if_best(_state_at(5), CFG.to_dict(), float("nan"))
        assert store.save_if_best(_state_at(6), CFG.to_dict(), 0.25)
        assert store.best_step() == 6 and store.best_val_loss == 0.25
    assert sorted(int(p.name) for p in (saved / "best").iterdir()) == [6]


def test_saving_the_same_step_twice_is_harmless(tmp_path):
    with CheckpointStore(tmp_path, keep_last=1) as store:
        store.save(_state_at(3), CFG.to_dict())
        store.save(_state_at(3), CFG.to_dict())
        assert store.latest_step() == 3


def test_run_directory_resolves_to_its_checkpoints(saved):
    state = checkpoints.restore(saved.parent, _target()).state
    assert int(state.step) == 4


def test_load_config_of_best_and_bad_choice(saved):
    assert load_config(saved, "best") == CFG
    with pytest.raises(ValueError, match="which"):
        load_config(saved, "newest")


def test_unfinished_temporary_save_is_ignored(saved):
    partial = saved / "last" / "9.orbax-checkpoint-tmp-1234"
    (partial / "state").mkdir(parents=True)
    (partial / "state" / "junk").write_text("half written")
    state = checkpoints.restore(saved, _target()).state
    assert int(state.step) == 4


def test_missing_directory(tmp_path):
    with pytest.raises(ValueError, match=str(tmp_path / "nope")):
        checkpoints.restore(tmp_path / "nope", _target())


def test_directory_without_checkpoints(tmp_path):
    (tmp_path / "somefile").write_text("x")
    with pytest.raises(ValueError, match="not a checkpoint directory"):
        checkpoints.restore(tmp_path, _target())
    (tmp_path / "last").mkdir()
    with pytest.raises(ValueError, match="no finished save"):
        checkpoints.restore(tmp_path, _target())
    with pytest.raises(ValueError, match="best"):
        checkpoints.restore(tmp_path, _target(), which="best")


def _truncate_data_files(step_dir):
    for path in (step_dir / "state").rglob("*"):
        if path.is_file() and "d" in path.relative_to(step_dir / "state").parts[:1]:
            path.write_bytes(b"")


@pytest.mark.parametrize("damage, fragment", [
    (lambda d: shutil.rmtree(d / "state"), "incomplete"),
    (lambda d: (d / "state" / "manifest.ocdbt").unlink(), "corrupt"),
    (lambda d: (d / "state" / "_METADATA").unlink(), "corrupt"),
    (_truncate_data_files, "corrupt"),
    (lambda d: (d / "config" / "metadata").write_text("{not json"), "corrupt"),
])
def test_damaged_checkpoint_gives_value_error_naming_the_path(saved, damage, fragment):
    step_dir = saved / "last" / "4"
    damage(step_dir)
    with pytest.raises(ValueError, match=fragment) as err:
        checkpoints.restore(saved, _target())
    assert str(step_dir) in str(err.value)
    gc.collect()  # orbax's leftover coroutines (see pytestmark) are collected here


def test_mismatched_model_gives_value_error(saved):
    wrong = objectives.Objective(init=lambda key: {"dense": {"w": jnp.zeros((5, 4)),
                                                           "b": jnp.zeros(4)}}, loss=None)
    with pytest.raises(ValueError, match="does not match"):
        checkpoints.restore(saved, train_state.abstract_state(CFG, wrong))
    gc.collect()


def test_keep_last_must_be_positive(tmp_path):
    with pytest.raises(ValueError, match="keep_last"):
        CheckpointStore(tmp_path, keep_last=0)


# --------------------------------------------------------------------------------------------
# Integrity: checksums, finiteness, older steps


def test_every_save_carries_checksums_of_every_array_and_the_config(saved):
    restored = checkpoints.restore(saved, _target())
    names = {integrity.leaf_name(path) for path, _ in
             jax.tree_util.tree_flatten_with_path(_state_at(4))[0]}
    assert set(restored.meta["checksums"]) == names and "params/dense/w" in names
    assert restored.meta["config_sha256"] and restored.step == 4
    raw = checkpoints.restore(saved)  # a raw pytree verifies against the same names
    assert int(raw.state["step"]) == 4


def _edit_json(path, edit):
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


@pytest.mark.parametrize("damage, fragment", [
    (lambda d: _edit_json(d / "meta" / "metadata",
                          lambda m: m["checksums"].update({"params/dense/w": "0" * 64})),
     "fails its checksums: 1 of"),
    (lambda d: _edit_json(d / "config" / "metadata", lambda c: c.update(lr=0.5)),
     "stored config differs"),
    (lambda d: shutil.rmtree(d / "meta"), "missing ['meta']"),
    (lambda d: (d / "_CHECKPOINT_METADATA").unlink(), "_CHECKPOINT_METADATA"),
    (lambda d: _edit_json(d / "meta" / "metadata", lambda m: m["layout"].pop()),
     "layout that does not match its packed bytes"),
    (lambda d: _edit_json(d / "meta" / "metadata", lambda m: m["layout"][0].__setitem__(2, -1)),
     "unreadable layout"),
    (lambda d: _edit_json(d / "meta" / "metadata", lambda m: m.pop("layout")), "no layout"),
])
def test_damaged_newest_step_names_the_newest_intact_one(saved, damage, fragment):
    damage(saved / "last" / "4")
    with pytest.raises(ValueError, match="The newest intact checkpoint is step 3") as err:
        checkpoints.restore(saved, _target())
    assert fragment in str(err.value) and str(saved / "last" / "4") in str(err.value)
    assert f"load({str(saved)!r}, step=3)" in str(err.value)
    assert "--from-step 3" in str(err.value)  # saved lives in a run directory's checkpoints/
    _assert_same(checkpoints.restore(saved, _target(), step=3).state, _state_at(3))
    gc.collect()


def test_a_step_is_restored_by_number_from_last_or_best(saved):
    assert checkpoints.saved_steps(saved) == [2, 3, 4]
    restored = checkpoints.restore(saved, _target(), step=2)  # only in best/
    assert restored.path == saved / "best" / "2"
    _assert_same(restored.state, _state_at(2))
    assert load_config(saved, step=2) == CFG
    with pytest.raises(ValueError, match=r"step 7 is not saved .*\[2, 3, 4\]"):
        checkpoints.restore(saved, _target(), step=7)
    with pytest.raises(ValueError, match="step must be an int"):
        checkpoints.restore(saved, _target(), step="3")


def _poisoned(part: str):
    state = _state_at(5)
    tree = jax.tree.map(lambda x: x.at[0].set(jnp.nan) if x.ndim else x, getattr(state, part))
    return state.replace(**{part: tree})


@pytest.mark.parametrize("part", ["params", "ema_params", "opt_state"])
def test_non_finite_state_is_never_saved(tmp_path, part):
    with CheckpointStore(tmp_path, keep_last=2) as store:
        with pytest.raises(NonFiniteStateError, match=f"step 5.*{part}/"):
            store.save(_poisoned(part), CFG.to_dict())
        with pytest.raises(NonFiniteStateError, match="NaN or inf"):
            store.save_if_best(_poisoned(part), CFG.to_dict(), 0.1)
        assert store.latest_step() is None and store.best_step() is None
    assert not any((tmp_path / "last").iterdir()) and not any((tmp_path / "best").iterdir())


def test_non_finite_state_on_disk_is_never_loaded(tmp_path, monkeypatch):
    with monkeypatch.context() as patch:  # write one as an older version could have
        checksums = integrity.state_checksums
        patch.setattr(integrity, "state_checksums",  # the writer's check finds nothing
                      lambda state: (checksums(state)[0], []))
        with CheckpointStore(tmp_path, keep_last=2) as store:
            store.save(_poisoned("opt_state"), CFG.to_dict())
    with pytest.raises(ValueError, match=r"NaN or inf values in opt_state/1/0/mu/dense/b"):
        checkpoints.restore(tmp_path, _target())
    with pytest.raises(ValueError, match="No other saved step is intact"):
        checkpoints.restore(tmp_path)


def test_steps_saved_before_checksums_still_restore_but_are_checked_for_nan(tmp_path):
    def legacy_save(step, state):
        manager = ocp.CheckpointManager(tmp_path / "last", item_names=("state", "config"))
        manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                                   config=ocp.args.JsonSave(CFG.to_dict())))
        manager.wait_until_finished()
        manager.close()

    legacy_save(3, _state_at(3))
    restored = checkpoints.restore(tmp_path, _target())
    assert restored.meta is None
    _assert_same(restored.state, _state_at(3))
    legacy_save(5, _poisoned("params"))
    with pytest.raises(ValueError, match=r"NaN or inf.*newest intact checkpoint is step 3"):
        checkpoints.restore(tmp_path, _target())


def test_a_state_is_one_packed_array_and_steps_of_one_array_per_leaf_still_restore(tmp_path):
    """A save stores the state as one array of bytes (orbax's time grows with the number of
    arrays); a step of the earlier format (one array per leaf, meta format 1) restores into a
    target and as raw dicts to the same arrays."""
    with CheckpointStore(tmp_path / "new", keep_last=2) as store:
        store.save(_state_at(3), CFG.to_dict())
    stored = ocp.StandardCheckpointHandler().metadata(tmp_path / "new" / "last" / "3" / "state")
    assert list(stored) == ["packed"] and len(jax.tree.leaves(stored)) == 1
    old = tmp_path / "old" / "last"
    manager = ocp.CheckpointManager(old, item_names=checkpoints.ITEMS)
    meta = {**integrity.describe_state(_state_at(3), CFG.to_dict()), "format": 1}
    manager.save(3, args=ocp.args.Composite(state=ocp.args.StandardSave(_state_at(3)),
                                            config=ocp.args.JsonSave(CFG.to_dict()),
                                            meta=ocp.args.JsonSave(meta)))
    manager.wait_until_finished()
    manager.close()
    for root in (tmp_path / "new", old.parent):
        _assert_same(checkpoints.restore(root, _target()).state, _state_at(3))
    raw_new, raw_old = (checkpoints.restore(root).state for root in (tmp_path / "new", old.parent))
    for part in ("step", "params", "ema_params"):
        _assert_same(raw_new[part], raw_old[part])
    layout = tmp_path / "new" / "last" / "3" / "meta" / "metadata"
    _edit_json(layout, lambda m: m["layout"][1].__setitem__(0, m["layout"][0][0]))
    with pytest.raises(ValueError, match="the name step twice"):
        checkpoints.restore(tmp_path / "new")
    with pytest.raises(ValueError, match="does not match the model: arrays"):
        checkpoints.restore(tmp_path / "new", _target())


def test_set_aside_moves_later_steps_out_of_the_way(saved):
    moved_to, moved = checkpoints.set_aside(saved, 2)
    assert moved == [3, 4] and sorted(p.name for p in (moved_to / "last").iterdir()) == ["3", "4"]
    assert checkpoints.saved_steps(saved) == [2]
    assert checkpoints.set_aside(saved, 2) == (None, [])


# --------------------------------------------------------------------------------------------
# Failed writes


def test_a_failed_write_is_one_short_error_and_leaves_no_partial_save(saved, monkeypatch,
                                                                       capsys):
    def full_disk(manager, step, *args, **kwargs):
        partial = pathlib.Path(str(manager.directory)) / f"{step}.orbax-checkpoint-tmp"
        (partial / "state").mkdir(parents=True)
        for _ in range(50):  # what orbax and tensorstore print when a write fails
            print("RuntimeError: Event loop is closed", file=sys.stderr)
        logging.getLogger("absl").error("RESOURCE_EXHAUSTED: Failed writing")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(ocp.CheckpointManager, "save", full_disk)
    with CheckpointStore(saved, keep_last=2) as store:
        with pytest.raises(CheckpointSaveError) as err:
            store.save(_state_at(5), CFG.to_dict())
        assert err.value.errno == errno.ENOSPC
        assert str(err.value) == (f"could not save checkpoint step 5 in {saved / 'last'}: "
                                  f"No space left on device")
        with pytest.raises(CheckpointSaveError, match=r"step 6 in .*best"):
            store.save_if_best(_state_at(6), CFG.to_dict(), 0.1)
    assert capsys.readouterr().err == ""
    assert sorted(p.name for p in (saved / "last").iterdir()) == ["3", "4"]
    assert int(checkpoints.restore(saved, _target()).state.step) == 4


def test_output_of_a_successful_save_is_not_swallowed(tmp_path, monkeypatch, capsys):
    original = ocp.CheckpointManager.save

    def chatty(manager, *args, **kwargs):
        print("a warning worth seeing", file=sys.stderr)
        return original(manager, *args, **kwargs)

    monkeypatch.setattr(ocp.CheckpointManager, "save", chatty)
    with CheckpointStore(tmp_path) as store:
        store.save(_state_at(1), CFG.to_dict())
    assert "a warning worth seeing" in capsys.readouterr().err


@pytest.mark.parametrize("bad", [None, 123, b"/tmp"])
def test_checkpoint_dir_must_be_a_path(bad):
    with pytest.raises(ValueError, match="checkpoint_dir must be a path"):
        checkpoints.restore(bad)
