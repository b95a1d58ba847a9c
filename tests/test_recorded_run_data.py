"""A recorded run and its data (issue 57):

* what ``evaluate`` and ``search`` score on ``--data`` (class 1): they name the environments and
  say whether the run trained on any of them (by content, through the run's ``data_digest``),
  and refuse the run's own data folder once it no longer matches that digest (its split would
  mix training environments into the test part);
* ``--resume`` repeating the original command's own ``--data`` / ``--preset`` works, another
  is refused; ``--set data_digest=...`` is not a setting (class 5)."""

from __future__ import annotations

import dataclasses
import re
import shutil

import jax
import pytest

from flowmaps_jax.evaluation.realised import evaluation_part
from flowmaps_jax.flowsim.homes import HomesConfig, generate_homes
from flowmaps_jax.recorded.format import Recorded, load_recorded, save_recorded
from flowmaps_jax.recorded.from_homes import from_homes
from flowmaps_jax.training.config import recorded_config
from flowmaps_jax.worlds import recorded as rw

CONFIG = HomesConfig(regime="mixed", num_hours=72,
                     rooms=("kitchen", "living_room", "bedroom", "bathroom"),
                     objects_per_home=(4, 6))


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """(the run's data folder, its environments, the stored config, its split by name):
    5 homes, split 1 test / 1 val / 3 train."""
    path = tmp_path_factory.mktemp("scoring") / "data"
    recorded = from_homes(generate_homes(jax.random.key(1), CONFIG, 5), CONFIG)
    save_recorded(recorded, path)
    cfg = recorded_config("smoke", str(path))
    split = rw.split_environments(recorded.names(), cfg.val_fraction, cfg.test_fraction,
                                  cfg.split_seed)
    names = {part: [recorded.names()[i] for i in index] for part, index in split.items()}
    assert len(names["train"]) == 3 and len(names["test"]) == 1
    return path, recorded, cfg.to_dict(), names


def _part(stored, recorded, path):
    return evaluation_part(recorded, recorded_config("smoke", str(path)).homes, stored,
                           str(path))[1:3]


def test_the_runs_own_folder_changed_since_it_trained_is_refused(world, tmp_path):
    """Two environments appended to the run's folder: its 'held-out test part' took in an
    environment the run trained on, with no word. Now a refusal naming the folder."""
    path, recorded, stored, names = world
    own = tmp_path / "own"
    shutil.copytree(path, own)
    stored = dict(stored, data=str(own))
    what, _ = _part(stored, load_recorded(own), own)
    assert what.startswith(f"the run's held-out test part (1 environments: {names['test'][0]}")
    extra = from_homes(generate_homes(jax.random.key(9), CONFIG, 2), CONFIG, names=["new0",
                                                                                  "new1"])
    save_recorded(Recorded(recorded.environments + extra.environments), own)
    with pytest.raises(ValueError, match=rf"^{re.escape(str(own))} changed since the run "
                                         r"trained on it .*data_digest"):
        _part(stored, load_recorded(own), own)
    # one environment changed in place, none added: the same
    env0 = recorded.environments[0]
    save_recorded(Recorded((dataclasses.replace(env0, location=env0.location[::-1].copy()),
                            *recorded.environments[1:])), own)
    with pytest.raises(ValueError, match="changed since the run trained on it"):
        _part(stored, load_recorded(own), own)


def test_a_copy_holding_training_environments_says_so(world, tmp_path):
    """A copy holding two training environments was scored as 'all 2 environments' with no
    word; now each environment is named and the ones the run trained on are said."""
    _path, recorded, stored, names = world
    by_name = dict(zip(recorded.names(), recorded.environments, strict=True))
    cases = {"two_train": names["train"][:2], "held_out": names["test"] + names["val"],
             "mixed": names["train"][2:] + names["test"]}
    for folder, chosen in cases.items():
        save_recorded(Recorded(tuple(by_name[n] for n in chosen)), tmp_path / folder)
        what, envs = _part(stored, load_recorded(tmp_path / folder), tmp_path / folder)
        assert what.startswith(f"all 2 environments ({', '.join(chosen)}); ") and len(envs) == 2
        trained = [n for n in chosen if n in names["train"]]
        assert what.endswith(f"the run trained on {len(trained)} of them "
                             f"({', '.join(trained)}): not held out" if trained
                             else "the run trained on none of them"), what


def test_whether_the_run_trained_on_them_is_said_even_when_unknown(world, tmp_path):
    _path, recorded, stored, _names = world
    save_recorded(Recorded(recorded.environments[:1]), tmp_path / "one")
    one = load_recorded(tmp_path / "one")
    gone = dict(stored, data=str(tmp_path / "nothing"))
    assert _part(gone, one, tmp_path / "one")[0].endswith(
        f"is not known: its data {tmp_path / 'nothing'} is gone or changed")
    homes_run = {k: v for k, v in stored.items() if k not in ("data", "data_digest")}
    assert _part(homes_run, one, tmp_path / "one")[0].endswith(
        "the run trained on generated FlowSim homes, none of them")
    assert _part({}, one, tmp_path / "one")[0].endswith(  # pretrained:NAME: no run config
        "whether the model trained on any of them is not recorded with it")


def _resolve(argv, monkeypatch, saved=None):
    from flowmaps_jax.training import cli, resume

    if saved is not None:  # the run's saved config, without training one
        monkeypatch.setattr(resume, "resume_config", lambda *a, **k: saved)
    return cli.resolve_config(cli.build_parser().parse_args(argv))[0]


def test_resume_repeating_the_original_data_and_preset_works(world, tmp_path, monkeypatch):
    """``--resume`` with the run's own unchanged --data and --preset said "cannot change"."""
    path, recorded, _stored, _names = world
    saved = recorded_config("smoke", str(path))
    run = ["--run-dir", str(tmp_path / "run"), "--resume"]
    for again in (["--data", str(path)], ["--preset", "smoke", "--data", str(path)],
                  ["--preset", "smoke"], ["--data", f"{path}/../{path.name}"]):
        assert _resolve([*run, *again], monkeypatch, saved) == saved, again
    save_recorded(Recorded(recorded.environments[:1]), tmp_path / "other")
    for other, flag in ((["--data", str(tmp_path / "other")], "--data"),
                        (["--preset", "homes"], "--preset"), (["--preset", "cpu"], "--preset")):
        with pytest.raises(ValueError, match=f"^{flag} cannot change on --resume"):
            _resolve([*run, *other], monkeypatch, saved)


def test_the_data_digest_and_path_are_not_settings(world, tmp_path, monkeypatch):
    """``--set data_digest=abc`` on a new run trained, then said the data "changed since the
    run began"."""
    path, _recorded, _stored, _names = world
    for argv in (["--data", str(path), "--set", "data_digest=abc"],
                 ["--preset", "smoke", "--set", "data_digest=abc"],
                 ["--data", str(path), "--set", f"data={tmp_path}"]):
        with pytest.raises(ValueError, match=r"^--set data(_digest)?: not a setting"):
            _resolve([*argv, "--run-dir", str(tmp_path / "run")], monkeypatch)
