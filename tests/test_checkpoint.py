"""Checkpoint store: round trip, last-k + best retention, clear errors on bad directories."""

import gc
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from flowmaps_jax import checkpoint, training
from flowmaps_jax.config import get_preset

CFG = get_preset("smoke")
# A stand-in model: a tiny params pytree is enough to exercise the whole TrainState.
OBJECTIVE = training.Objective(
    init=lambda key: {"dense": {"w": jax.random.normal(key, (3, 4)), "b": jnp.zeros(4)}},
    loss=None)


def _state_at(step: int) -> training.TrainState:
    state = training.init_state(CFG, jax.random.PRNGKey(1), OBJECTIVE)
    params = jax.tree.map(lambda x: x + step, state.params)
    return state.replace(step=jnp.asarray(step, jnp.int32), params=params,
                         ema_params=jax.tree.map(lambda x: 0.5 * x, params))


def _target():
    return training.abstract_state(CFG, OBJECTIVE)


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
    with checkpoint.CheckpointStore(root, keep_last=2) as store:
        for step in range(1, 5):
            store.save(_state_at(step), CFG.to_dict())
            if step in (2, 3):
                store.save_if_best(_state_at(step), CFG.to_dict(), {2: 0.5, 3: 0.7}[step])
    return root


def test_round_trip_restores_every_field(saved):
    state, config = checkpoint.restore_latest(saved, _target())
    assert isinstance(state, training.TrainState)
    _assert_same(state, _state_at(4))
    assert config == CFG.to_dict()
    assert checkpoint.load_config(saved) == CFG


def test_keeps_last_k_and_the_best_even_when_it_falls_out(saved):
    assert sorted(int(p.name) for p in (saved / "last").iterdir()) == [3, 4]
    best, _ = checkpoint.restore_best(saved, _target())
    assert int(best.step) == 2  # step 3 had a worse validation loss and step 2 left last-k
    _assert_same(best, _state_at(2))


def test_best_is_replaced_only_by_a_lower_loss_and_survives_reopening(saved):
    with checkpoint.CheckpointStore(saved, keep_last=2) as store:
        assert store.best_val_loss == 0.5
        assert not store.save_if_best(_state_at(5), CFG.to_dict(), 0.6)
        assert not store.save_if_best(_state_at(5), CFG.to_dict(), float("nan"))
        assert store.save_if_best(_state_at(6), CFG.to_dict(), 0.25)
        assert store.best_step() == 6 and store.best_val_loss == 0.25
    assert sorted(int(p.name) for p in (saved / "best").iterdir()) == [6]


def test_saving_the_same_step_twice_is_harmless(tmp_path):
    with checkpoint.CheckpointStore(tmp_path, keep_last=1) as store:
        store.save(_state_at(3), CFG.to_dict())
        store.save(_state_at(3), CFG.to_dict())
        assert store.latest_step() == 3


def test_run_directory_resolves_to_its_checkpoints(saved):
    state, _ = checkpoint.restore_latest(saved.parent, _target())
    assert int(state.step) == 4


def test_load_config_of_best_and_bad_choice(saved):
    assert checkpoint.load_config(saved, "best") == CFG
    with pytest.raises(ValueError, match="which"):
        checkpoint.load_config(saved, "newest")


def test_unfinished_temporary_save_is_ignored(saved):
    partial = saved / "last" / "9.orbax-checkpoint-tmp-1234"
    (partial / "state").mkdir(parents=True)
    (partial / "state" / "junk").write_text("half written")
    state, _ = checkpoint.restore_latest(saved, _target())
    assert int(state.step) == 4


def test_missing_directory(tmp_path):
    with pytest.raises(ValueError, match=str(tmp_path / "nope")):
        checkpoint.restore_latest(tmp_path / "nope", _target())


def test_directory_without_checkpoints(tmp_path):
    (tmp_path / "somefile").write_text("x")
    with pytest.raises(ValueError, match="not a checkpoint directory"):
        checkpoint.restore_latest(tmp_path, _target())
    (tmp_path / "last").mkdir()
    with pytest.raises(ValueError, match="no finished save"):
        checkpoint.restore_latest(tmp_path, _target())
    with pytest.raises(ValueError, match="best"):
        checkpoint.restore_best(tmp_path, _target())


def _truncate_data_files(step_dir):
    for path in (step_dir / "state").rglob("*"):
        if path.is_file() and "d" in path.relative_to(step_dir / "state").parts[:1]:
            path.write_bytes(b"")


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
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
        checkpoint.restore_latest(saved, _target())
    assert str(step_dir) in str(err.value)
    gc.collect()  # see test_mismatched_model_gives_value_error


# orbax leaves un-awaited read coroutines behind after a failed restore; collect them here
# so the resulting "unraisable exception" warnings stay with this test.
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_mismatched_model_gives_value_error(saved):
    wrong = training.Objective(init=lambda key: {"dense": {"w": jnp.zeros((5, 4)),
                                                           "b": jnp.zeros(4)}}, loss=None)
    with pytest.raises(ValueError, match="does not match"):
        checkpoint.restore_latest(saved, training.abstract_state(CFG, wrong))
    gc.collect()


def test_keep_last_must_be_positive(tmp_path):
    with pytest.raises(ValueError, match="keep_last"):
        checkpoint.CheckpointStore(tmp_path, keep_last=0)
