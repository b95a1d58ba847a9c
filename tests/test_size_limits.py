"""Sizes: every size argument and every config field that scales memory or work goes through the
one resource estimate and is refused before anything is written or compiled.
"""

from __future__ import annotations

import dataclasses
import pathlib
import typing

import jax
import numpy as np
import pytest
from support import (
    TINY,
    error_line,
    only_error_line,
    run_cli,
    synthetic_queries,
    synthetic_tokens,
    unsaved_run,
)

from flowmaps_jax import model as model_lib
from flowmaps_jax import resources
from flowmaps_jax.flowsim import FlowSimConfig
from flowmaps_jax.model import ModelConfig
from flowmaps_jax.predictor import Predictor
from flowmaps_jax.tables import table_probabilities
from flowmaps_jax.training import cli as train_cli
from flowmaps_jax.training.config import (
    TrainConfig,
    apply_overrides,
    check_run_resources,
    get_preset,
)

CFG = dataclasses.replace(get_preset("smoke"), routine_envs=0)


_cli, _error_line = run_cli, error_line  # tests/support.py


_one_line = only_error_line  # tests/support.py


def _unsaved_run(run_dir: pathlib.Path, cfg=CFG) -> pathlib.Path:
    return unsaved_run(run_dir, cfg.to_dict())


"""Per class: one entry per reproduction tried, True when it behaved (reported at the end)."""


# ---------------------------------------------------------- one resource budget


@pytest.mark.parametrize("override, field", [
    ("queries_per_scene=100000000", "queries_per_scene"),
    ("model.dim=65536", "model.dim"),
    ("val_batches=100000000", "val_batches"),
    ("routine_samples=1000000000", "routine_samples"),
    ("batch_size=100000000", "batch_size"),
    ("train_envs=2000000000", "train_envs"),
    ("model.cdit_blocks=100000", "model.cdit_blocks"),
])
def test_train_sizes_refused_before_anything_is_written(tmp_path, capsys, override, field):
    run_dir = tmp_path / "run"
    code, _, err = _cli(train_cli.main, ["--preset", "smoke", "--no-progress", "--run-dir",
                                         str(run_dir), "--set", override], capsys)
    assert code == 2
    line = _one_line(err)
    assert field in line and "GB" in line and resources.MAX_BYTES_ENV in line
    assert not run_dir.exists()


def test_resume_with_a_size_over_budget_keeps_config_json(tmp_path, capsys):
    run_dir = _unsaved_run(tmp_path / "run", get_preset("smoke"))
    before = (run_dir / "config.json").read_bytes()
    code, _, err = _cli(train_cli.main, ["--resume", "--run-dir", str(run_dir), "--steps", "40",
                                         "--set", "routine_samples=1000000000", "--no-progress"],
                        capsys)
    assert code == 2 and "routine_samples=1000000000" in _one_line(err)
    assert (run_dir / "config.json").read_bytes() == before


def test_budget_env_variables(monkeypatch):
    cfg = apply_overrides(CFG, ["val_batches=1000"])
    check_run_resources(cfg)
    monkeypatch.setenv(resources.MAX_BYTES_ENV, "1M")
    with pytest.raises(ValueError, match=r"val_batches=1000 .* more than the 0.001 GB"):
        check_run_resources(cfg)
    monkeypatch.setenv(resources.MAX_BYTES_ENV, "64Gi")
    assert resources.memory_limit() == 64 * 2**30
    monkeypatch.setenv(resources.MAX_BYTES_ENV, "lots")
    with pytest.raises(ValueError, match=resources.MAX_BYTES_ENV):
        resources.memory_limit()
    monkeypatch.delenv(resources.MAX_BYTES_ENV)
    monkeypatch.setenv(resources.MAX_FLOPS_ENV, "1e6")
    with pytest.raises(ValueError, match=r"a train step .* floating-point operations"):
        check_run_resources(CFG)
    monkeypatch.delenv(resources.MAX_FLOPS_ENV)
    assert resources.flops_limit() == resources.DEFAULT_MAX_FLOPS
    with pytest.raises(ValueError, match="budget"):
        resources.check_resources("x=3", flops=resources.DEFAULT_MAX_FLOPS + 1)


def test_every_preset_fits_the_default_budget():
    for name in ("smoke", "cpu", "paper"):
        check_run_resources(get_preset(name))


# -------------------------------------------------------- the resource estimate


@pytest.fixture
def budget_16g(monkeypatch):
    """The same memory budget on every machine (16 GB), so the huge values are huge here too."""
    monkeypatch.setenv(resources.MAX_BYTES_ENV, "16G")


@pytest.fixture(scope="module")
def tiny():
    predictor = Predictor.from_params(model_lib.init_params(jax.random.key(0), TINY), TINY)
    tokens = synthetic_tokens(0)
    return predictor, tokens, synthetic_queries(tokens, 2)


@pytest.mark.usefixtures("budget_16g")
@pytest.mark.parametrize("num_steps", [10**6, 10**9])
def test_sample_refuses_a_huge_num_steps_up_front(tiny, num_steps):
    predictor, tokens, queries = tiny
    with pytest.raises(ValueError, match=f"num_steps={num_steps}") as info:
        predictor.sample(tokens, queries, 4, jax.random.key(0), num_steps=num_steps)
    assert "\n" not in str(info.value)


@pytest.mark.usefixtures("budget_16g")
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
        assert ok, what


@pytest.mark.usefixtures("budget_16g")
def test_freq_bands_is_counted_by_the_estimate(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, _, err = _cli(train_cli.main, ["--preset", "smoke", "--no-progress", "--set",
                                         "model.freq_bands=100000"], capsys)
    ok = code == 2 and "model.freq_bands=100000" in _error_line(err) \
        and list(tmp_path.iterdir()) == []
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


@pytest.mark.usefixtures("budget_16g")
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
        assert ok, name
    assert tried >= 20


# ------------------------------------------------------- sizes (homes training)


@pytest.mark.parametrize("overrides,field", [
    (["model.dim=65536", "model.heads=1"], "model.dim"),
    (["homes.max_vocabulary=1000000000"], "max_vocabulary"),
    (["queries_per_home=100000000"], "queries_per_scene"),
    (["homes.num_hours=1048576"], "num_hours"),
    (["homes.max_tokens=100000"], "max_tokens"),
    (["homes.max_tokens=1000000000"], "max_tokens"),
    (["model.encoder_layers=65536"], "model.encoder_layers"),
    (["chunk_homes=100000000"], "chunk_homes"),
    (["val_homes=100000000"], "val_homes"),
    (["val_batches=100000000"], "val_batches"),
    # other members of the class
    (["val_batches=1000000", "val_homes=4000000"], "val_batches"),
    (["model.weight_blocks=1000"], "model.weight_blocks"),
    (["model.cdit_blocks=65536"], "model.cdit_blocks"),
    (["batch_size=100000000"], "batch_size"),
    (["model.dim=4096", "model.mlp_ratio=4096"], "model.mlp_ratio"),
    (["homes.frequent_length=1e-30"], "frequent_length"),
])
def test_homes_training_refuses_a_size_before_writing_the_run(tmp_path, capsys, overrides,
                                                              field):
    run_dir = tmp_path / "run"
    argv = ["--preset", "homes-smoke", "--run-dir", str(run_dir)]
    for override in overrides:
        argv += ["--set", override]
    code, _, err = _cli(train_cli.main, argv, capsys)
    assert code == 2, err
    assert field in _error_line(err)
    assert not run_dir.exists()
