"""One load per run (issue 55): a ``--data`` run reads, digests and splits its dataset once, and
evaluate reads the run's stored config once and the data once."""

from __future__ import annotations

import collections

import jax
import pytest

from flowmaps_jax import evaluate, train
from flowmaps_jax.flowsim.homes import HomesConfig, generate_homes
from flowmaps_jax.recorded.format import save_recorded
from flowmaps_jax.recorded.from_homes import from_homes
from flowmaps_jax.store import checkpoints
from flowmaps_jax.worlds import recorded as rw

CONFIG = HomesConfig(regime="mixed", num_hours=72,
                     rooms=("kitchen", "living_room", "bedroom", "bathroom"),
                     objects_per_home=(4, 6))


@pytest.fixture
def counted(monkeypatch):
    """Calls of the data's read, digest and split and of the stored config's read, counted (and
    nothing read before: as in a fresh process)."""
    calls = collections.Counter()

    def counting(module, name):
        real = getattr(module, name)

        def wrapper(*args, **kwargs):
            calls[name] += 1
            return real(*args, **kwargs)

        monkeypatch.setattr(module, name, wrapper)

    for name in ("load_recorded", "content_digest", "split_environments"):
        counting(rw, name)
    counting(checkpoints, "stored_config")
    return calls


def test_a_data_run_and_its_evaluation_read_digest_and_split_once(tmp_path, counted):
    data, run = tmp_path / "data", tmp_path / "run"
    save_recorded(from_homes(generate_homes(jax.random.key(0), CONFIG, 5), CONFIG,
                             mask_fraction=0.3, seed=0), data)
    assert train.main(["--data", str(data), "--preset", "smoke", "--run-dir", str(run),
                       "--no-progress"]) == 0
    assert counted == {"load_recorded": 1, "content_digest": 1, "split_environments": 1}
    counted.clear()
    rw._LOADED.clear()  # evaluate in a process of its own
    assert evaluate.main(["--checkpoint", str(run), "--out", str(tmp_path / "eval"),
                          "--queries", "4", "--no-figures", "--no-progress"]) == 0
    assert counted == {"load_recorded": 1, "content_digest": 1, "split_environments": 1,
                       "stored_config": 1}
