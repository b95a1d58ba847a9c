"""Reliability, round 4 (issue 36): each reproduction of the hostile trial, and at least one
other member of its class.

1. no command writes through a symbolic link (one writer: a temporary file and a rename);
2. a resumed run writes the records of a run never stopped, whichever save a kill fell between;
3./4. every size goes through the one resource estimate (``num_steps``, ``freq_bands``, every
   numeric config field that scales memory or work);
5. traceable checks: traced out-of-range inputs give NaN, never another input's answer;
6./8. habit checks, in the order that names the real error;
7./9. config validation and run directories: one-line usage errors (exit code 2).

Trainings use the smoke preset without the routine diagnostic (they share the compilation of
the other training tests).
"""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib
import typing

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support import TINY, error_line, run_cli, synthetic_queries, synthetic_tokens

from flowmaps_jax import atomic_files, resources
from flowmaps_jax import model as model_lib
from flowmaps_jax import validation as v
from flowmaps_jax.evaluation import cli as eval_cli
from flowmaps_jax.evaluation import report as eval_report
from flowmaps_jax.flowsim import FlowSimConfig, exact_posterior, habits, transition_matrix
from flowmaps_jax.flowsim.generate import LayoutError
from flowmaps_jax.model import ModelConfig
from flowmaps_jax.predictor import Predictor
from flowmaps_jax.search import cli as search_cli
from flowmaps_jax.search import report as search_report
from flowmaps_jax.store import checkpoints, rundir
from flowmaps_jax.store.checkpoint_store import CheckpointStore
from flowmaps_jax.tables import table_probabilities
from flowmaps_jax.training import cli as train_cli
from flowmaps_jax.training import loop
from flowmaps_jax.training.config import (
    TrainConfig,
    apply_overrides,
    check_run_resources,
    get_preset,
)

CFG = dataclasses.replace(get_preset("smoke"), routine_envs=0)
QUIET = ["--preset", "smoke", "--set", "routine_envs=0", "--no-progress"]
TIMING = ("steps_per_sec", "samples_per_sec")
SILENT = dict(progress=False, log=lambda _: None)
TRIES: dict[str, list[bool]] = {}
"""Per class: one entry per reproduction tried, True when it behaved (reported at the end)."""


def _tally(cls: str, ok: bool) -> None:
    TRIES.setdefault(cls, []).append(bool(ok))


@pytest.fixture(autouse=True)
def _budget(monkeypatch):
    """The same memory budget on every machine (16 GB), so the huge values are huge here too."""
    monkeypatch.setenv(resources.MAX_BYTES_ENV, "16G")


_cli, _error_line = run_cli, error_line  # tests/support.py


def _outside(tmp_path) -> pathlib.Path:
    target = tmp_path / "elsewhere.txt"
    target.write_text("keep")
    return target


# ------------------------------------------------------------- class 1: no write through a link


@pytest.mark.parametrize("name", ["search.json", "search.md", "episodes.png"])
def test_search_refuses_a_link_at_an_output_name(tmp_path, capsys, name):
    target, out = _outside(tmp_path), tmp_path / "runs" / "x"
    out.mkdir(parents=True)
    (out / name).symlink_to(target)
    argv = ["--checkpoint", "pretrained:flowmaps", "--num-envs", "1", "--out", str(out)]
    code, _, err = _cli(search_cli.main, argv + ([] if name.endswith("png") else
                                                ["--no-figures"]), capsys)
    ok = code == 2 and "symbolic link" in _error_line(err) and target.read_text() == "keep"
    _tally("1 links", ok)
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
    _tally("1 links", ok)
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
    _tally("1 links", ok)
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
    _tally("1 links", ok)
    assert ok


# ------------------------------------------------------------- class 2: resume replays exactly


class _Killed(BaseException):
    """A kill -9 between two saves (nothing after it runs)."""


def _records(run_dir):
    return [{k: val for k, val in json.loads(line).items() if k not in TIMING}
            for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    """(run dir of a run never stopped, the saves it made in order)."""
    saves = []
    original = CheckpointStore._write

    def write(self, manager, step, *args, **kwargs):
        original(self, manager, step, *args, **kwargs)
        saves.append((pathlib.Path(str(manager.directory)).name, step))

    mp = pytest.MonkeyPatch()
    mp.setattr(CheckpointStore, "_write", write)
    try:
        run_dir = tmp_path_factory.mktemp("r4") / "straight"
        loop.run(CFG, run_dir, **SILENT)
    finally:
        mp.undo()
    assert saves == [("best", 10), ("last", 10), ("best", 20), ("last", 20)]
    return run_dir, saves


@pytest.mark.parametrize("kill_after", [0, 1, 2, 3, 4])
def test_a_run_killed_between_any_two_saves_resumes_to_the_same_records(
        straight, tmp_path, monkeypatch, kill_after):
    """kill_after: the saves done before the kill (0: killed at step 7, before any save; 3:
    the issue's case, best/20 saved and last/20 not)."""
    reference, _ = straight
    done = []
    original = CheckpointStore._write

    def write(self, manager, step, *args, **kwargs):
        original(self, manager, step, *args, **kwargs)
        done.append(step)
        if len(done) == kill_after:
            raise _Killed

    def on_step(step, metrics):
        if kill_after == 0 and step == 7:
            raise _Killed

    run_dir = tmp_path / "run"
    with monkeypatch.context() as mp:
        mp.setattr(CheckpointStore, "_write", write)
        with pytest.raises(_Killed):
            loop.run(CFG, run_dir, on_step=on_step, **SILENT)
    result = loop.run(CFG, run_dir, resume=True, **SILENT)
    ok = result.status == "done" and _records(run_dir) == _records(reference) \
        and checkpoints.saved_steps(run_dir, "best") == [20] \
        and result.best_step == 20
    _tally("2 resume", ok)
    assert ok, (_records(run_dir), _records(reference))


# ------------------------------------------------------------- class 3/4: the resource estimate


@pytest.fixture(scope="module")
def tiny():
    predictor = Predictor.from_params(model_lib.init_params(jax.random.key(0), TINY), TINY)
    tokens = synthetic_tokens(0)
    return predictor, tokens, synthetic_queries(tokens, 2)


@pytest.mark.parametrize("num_steps", [10**6, 10**9])
def test_sample_refuses_a_huge_num_steps_up_front(tiny, num_steps):
    predictor, tokens, queries = tiny
    with pytest.raises(ValueError, match=f"num_steps={num_steps}") as info:
        predictor.sample(tokens, queries, 4, jax.random.key(0), num_steps=num_steps)
    _tally("3 sizes", "\n" not in str(info.value))


def test_every_size_argument_of_the_public_api_refuses_a_huge_value(tiny):
    predictor, tokens, queries = tiny
    key = jax.random.key(0)
    x = np.full((2, 2, 1, 4), 0.5, np.float32)
    calls = {
        "num_samples": lambda: predictor.sample(tokens, queries, 10**12, key),
        "num_steps (log_prob)": lambda: predictor.log_prob(tokens, queries, x, num_steps=10**7),
        "num_steps (accurate)": lambda: predictor.sample(tokens, queries, 1, key,
                                                         num_steps=10**6, method="accurate"),
        "table_probabilities num_samples": lambda: table_probabilities(
            predictor, tokens, queries, 10**12, key),
        "generate num_envs": lambda: __import__("flowmaps_jax.flowsim", fromlist=["x"]).generate(
            key, 10**12, FlowSimConfig()),
    }
    for what, call in calls.items():
        with pytest.raises(ValueError) as info:
            call()
        ok = "\n" not in str(info.value)
        _tally("3 sizes", ok)
        assert ok, what


def test_freq_bands_is_counted_by_the_estimate(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, _, err = _cli(train_cli.main, ["--preset", "smoke", "--no-progress", "--set",
                                         "model.freq_bands=100000"], capsys)
    ok = code == 2 and "model.freq_bands=100000" in _error_line(err) \
        and list(tmp_path.iterdir()) == []
    _tally("4 config sizes", ok)
    assert ok, err


# Integer fields of the configs that do not scale memory or work, and why.
NOT_SIZES = {
    "steps": "not bounded: a run stops and resumes between steps",
    "seed": "a seed", "log_every": "an interval", "val_every": "an interval",
    "ckpt_every": "an interval", "keep_last": "checkpoints kept on disk, not memory or work",
    "short_horizon_max": "a cap on sampled horizons",
    "flowsim.layout_budget": "a cap on redraws: generation stops as soon as layouts fit",
    "routine_envs": "capped at val_envs (counted there)",
    "model.weight_blocks": "used by the mixture head only (counted for it)",
}


def _int_fields(cls, prefix=""):
    hints = typing.get_type_hints(cls)
    for field in dataclasses.fields(cls):
        hint = hints[field.name]
        if field.name in ("model", "flowsim"):
            sub = ModelConfig if field.name == "model" else FlowSimConfig
            yield from _int_fields(sub, f"{field.name}.")
        elif "int" in str(hint) and "bool" not in str(hint):
            yield prefix + field.name


def test_every_size_field_of_the_configs_refuses_a_huge_value():
    fields = sorted(set(_int_fields(TrainConfig)))
    assert "model.freq_bands" in fields and "flowsim.max_tokens" in fields
    tried = 0
    for name in fields:
        if name in NOT_SIZES:
            continue
        try:
            # the smoke preset with its routine diagnostic on (routine_samples counts there)
            check_run_resources(apply_overrides(get_preset("smoke"), {name: 10**9}))
        except ValueError as err:
            ok = "\n" not in str(err) and name.split(".")[-1] in str(err)
        else:
            ok = False
        tried += 1
        _tally("4 config sizes", ok)
        assert ok, name
    assert tried >= 20


# ------------------------------------------------------------- class 5: checks under jit


def test_exact_posterior_under_jit_gives_nan_for_out_of_range_inputs():
    posterior = jax.jit(lambda k, s, h: exact_posterior(k, s, h))
    assert np.all(np.isnan(posterior(3, 7, 1)))  # the issue: slot 1's answer before
    assert np.all(np.isnan(posterior(0, 0, 1)))  # the issue: [1, 0, ...] before
    assert np.all(np.isnan(posterior(3, 1, 25)))  # a horizon past T - 1: no longer clipped
    np.testing.assert_array_equal(posterior(3, 1, 2), exact_posterior(3, 1, 2))
    batch = posterior(np.array([3, 3]), np.array([1, 5]), np.array([2, 2]))
    assert not np.any(np.isnan(batch[0])) and np.all(np.isnan(batch[1]))  # row by row
    jitter = jax.jit(lambda t: exact_posterior(3, 1, 2, dynamics="schedule_jitter", tau=t))
    assert np.all(np.isnan(jitter(19))) and not np.any(np.isnan(jitter(5)))
    assert np.all(np.isnan(jax.jit(transition_matrix)(0)))
    for bad in (lambda: exact_posterior(3, 7, 1), lambda: exact_posterior(0, 0, 1)):
        with pytest.raises(ValueError):  # eagerly refused, as before
            bad()
    _tally("5 jit", True)


# ------------------------------------------------------------- class 6/8: habit checks


@pytest.mark.parametrize("probs, words", [((0.5, 0.3, 0.0), "sum to 1"),
                                          ((1.2, -0.2, 0.0), "negative"),
                                          ((math.nan, 0.5, 0.5), "NaN")])
def test_habit_prior_checks_its_probabilities(probs, words):
    with pytest.raises(ValueError, match="habit_probs") as info:
        habits.habit_prior(np.array([3, 4]), probs, 10)
    _tally("6 habits", words in str(info.value))
    assert words in str(info.value)


def test_habit_prior_checks_num_slots_and_keeps_its_numbers():
    with pytest.raises(ValueError, match="num_slots"):
        habits.habit_prior(np.array([0, 4]), (1.0, 0.0, 0.0), 10)
    prior = habits.habit_prior(np.array([3, 4]), (0.5, 0.3, 0.2), 10)
    np.testing.assert_allclose(np.asarray(prior).sum(-1), 1.0, rtol=1e-6)
    traced = jax.jit(lambda p: habits.habit_prior(np.array([3]), p, 10))(
        jnp.array([0.5, 0.3, 0.2]))  # traced: used as given (documented)
    np.testing.assert_array_equal(traced, habits.habit_prior(np.array([3]), (0.5, 0.3, 0.2), 10))
    _tally("6 habits", True)


@pytest.mark.parametrize("history_len", [3, 10])
def test_history_posterior_names_the_shape_first(history_len):
    from flowmaps_jax.flowsim.scenes import validation_split

    config = FlowSimConfig()
    scenes = validation_split(config, num_envs=1)
    with pytest.raises(ValueError, match=r"env must have shape \(Q,\)") as info:
        habits.history_posterior(scenes, config, 0, 0, 5, 1, history_len)
    _tally("8 order", "shape (Q,)" in str(info.value))
    # a 1-D call with too long a history: the clear error, not an IndexError
    with pytest.raises(ValueError, match="longer than the query's past"):
        habits.history_posterior(scenes, config, [0], [0], [5], [1], 10)
    with pytest.raises(ValueError, match="longer than the query's past"):
        habits.history_posterior(scenes, config, [0], [0], [5], [1], np.array([7]))


# ------------------------------------------------------------- class 7/9: usage errors


@pytest.mark.parametrize("argv, words", [
    (["--set", "flowsim.layout_budget=0"], "layout_budget must be an int in 1.."),
    (["--set", "flowsim.layout_candidates=0"], "layout_candidates must be"),
])
def test_a_layout_the_config_cannot_place_is_a_usage_error(tmp_path, capsys, monkeypatch,
                                                          argv, words):
    monkeypatch.chdir(tmp_path)
    code, _, err = _cli(train_cli.main, [*QUIET, *argv], capsys)
    ok = code == 2 and words in _error_line(err) and list(tmp_path.iterdir()) == []
    _tally("7 config", ok)
    assert ok, err


def test_a_generation_that_cannot_place_a_layout_is_a_value_error():
    from flowmaps_jax.flowsim import generate

    crowded = FlowSimConfig(table_min_frac=0.24, table_max_frac=0.25, layout_budget=2)
    with pytest.raises(LayoutError, match="layout_budget") as info:
        generate(jax.random.key(0), 64, crowded)
    ok = isinstance(info.value, ValueError) and isinstance(info.value, RuntimeError)
    _tally("7 config", ok)
    assert ok


@pytest.mark.parametrize("run_dir, words", [
    ("x" * 300, "more than the 255"),
    ("ok/" + "y" * 300 + "/run", "more than the 255"),
    ("", "non-empty path"),
])
def test_a_run_dir_that_cannot_be_created_is_a_usage_error(tmp_path, capsys, monkeypatch,
                                                          run_dir, words):
    monkeypatch.chdir(tmp_path)
    code, _, err = _cli(train_cli.main, [*QUIET, "--run-dir", run_dir], capsys)
    ok = code == 2 and words in _error_line(err) and list(tmp_path.iterdir()) == []
    _tally("9 run dir", ok)
    assert ok, err
    with pytest.raises(ValueError, match="more than the 255"):  # the other outputs too
        v.check_output_file("--out", tmp_path / ("z" * 300))


@pytest.mark.parametrize("overrides, words", [
    (["--steps", "2", "--set", "lr=inf"], "lr must be a finite"),
    (["--steps", "2", "--set", "b1=2"], "b1 must be"),
    (["--set", "lr=１"], "lr must be a finite real number"),
    (["--set", "batch_size=８"], "batch_size must be an int"),
])
def test_minor_overrides_name_the_real_error(tmp_path, capsys, monkeypatch, overrides, words):
    monkeypatch.chdir(tmp_path)
    code, _, err = _cli(train_cli.main, [*QUIET, *overrides], capsys)
    ok = code == 2 and words in _error_line(err) and "warmup_steps" not in _error_line(err)
    _tally("minor", ok)
    assert ok, err


def test_table_probabilities_by_weights_checks_num_samples():
    class Weights:
        def table_weights(self, tokens, queries):
            raise AssertionError("not reached")

    for bad in (-5, 2.5, "3"):
        with pytest.raises(ValueError, match="num_samples"):
            table_probabilities(Weights(), None, None, bad, None, method="weights")
    _tally("minor", True)


def test_zz_report_the_tally(capsys):
    """Print tries / OK / problems per class (run last in this module)."""
    with capsys.disabled():
        for cls, results in sorted(TRIES.items()):
            print(f"\n{cls}: {len(results)} tries, {sum(results)} OK, "
                  f"{len(results) - sum(results)} problems", end="")
        print()
