"""TrainConfig presets, overrides from strings, JSON round trip and CLI argument resolution."""

import dataclasses
import json

import pytest

from flowmaps_jax.training.cli import build_parser, main, resolve_config
from flowmaps_jax.training.config import (
    PRESETS,
    RESUMABLE_FIELDS,
    ROLES,
    TrainConfig,
    apply_overrides,
    compile_key,
    config_from_stored,
    format_config,
    get_preset,
)
from flowmaps_jax.training.overrides import replace_fields


def test_paper_preset_matches_the_paper():
    cfg = get_preset("paper")
    m = cfg.model
    assert (m.dim, m.encoder_layers, m.cdit_blocks, m.heads, m.dropout) == (256, 8, 8, 8, 0.1)
    assert (cfg.batch_size, cfg.steps, cfg.lr) == (256, 30_000, 1e-4)
    assert (cfg.b1, cfg.b2, cfg.ema_decay) == (0.95, 0.999, 0.9999)
    assert cfg.t_sampler == "beta"
    assert cfg.family == "flowmaps"
    # none of the routine-learning departures (issue 8): the paper's velocity head and objective
    assert (m.head, m.condition_on_dtau) == ("velocity", False)
    assert (cfg.short_horizon_frac, cfg.target_noise, cfg.pointer_loss) == (0.0, 0.0, 0.0)


def test_default_is_cpu_and_smoke_is_tiny():
    assert get_preset() == get_preset("cpu")
    smoke, cpu = get_preset("smoke"), get_preset("cpu")
    assert smoke.model.dim < cpu.model.dim < get_preset("paper").model.dim
    assert smoke.steps <= 50 and smoke.train_envs <= 100
    assert cpu.t_sampler == "beta" and cpu.model.box_scale == 1.0
    assert cpu.model.head == "mixture" and cpu.pointer_loss > 0
    # issue 33: the table-weight rows attend to each other and know their table's geometry
    assert (cpu.model.weight_attention, cpu.model.weight_geometry) == ("self", "relative")
    # issue 33: fresh homes every chunk by default; the paper's recipe keeps the fixed split; the
    # habits keep the previous default's pointer recipe (its cpu-pointer preset went in issue 49)
    assert cpu.data == "endless" and get_preset("paper").data == "train"
    habits = get_preset("habits")
    assert (habits.model.head, habits.model.pointer_widths) == ("pointer", "relative")
    assert "cpu-pointer" not in PRESETS


def test_pointer_loss_needs_the_pointer_head_but_the_mlp_ignores_it():
    cpu = get_preset("cpu")
    with pytest.raises(ValueError, match="pointer_loss"):
        apply_overrides(cpu, ["model.head=velocity"])
    mlp = apply_overrides(cpu, ["family=mlp", "model.head=velocity"])
    assert mlp.pointer_loss == cpu.pointer_loss


def test_unknown_preset():
    with pytest.raises(ValueError, match="preset"):
        get_preset("huge")


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_json_round_trip(name):
    cfg = get_preset(name)
    back = type(cfg).from_dict(json.loads(json.dumps(cfg.to_dict())))
    assert back == cfg
    assert config_from_stored(json.loads(json.dumps(cfg.to_dict()))) == cfg  # by its family
    assert "model.dim" in format_config(cfg)


def test_every_field_declares_its_role_and_both_field_lists_derive_from_it():
    """One declaration per field says whether the compiled functions depend on it and whether
    --resume may change it: the compile-cache key and RESUMABLE_FIELDS cannot disagree."""
    fields = dataclasses.fields(TrainConfig)
    undeclared = [f.name for f in fields if f.metadata.get("role") not in ROLES]
    assert undeclared == []
    assert RESUMABLE_FIELDS == tuple(f.name for f in fields
                                     if ROLES[f.metadata["role"]].resumable)
    assert set(RESUMABLE_FIELDS) == {"steps", "log_every", "val_every", "ckpt_every",
                                     "keep_last", "routine_envs", "routine_samples", "devices",
                                     "preset"}
    smoke, base = get_preset("smoke"), TrainConfig()
    uncompiled = {f.name for f in fields if not ROLES[f.metadata["role"]].compiled}
    assert uncompiled == {"log_every", "val_every", "ckpt_every", "keep_last", "preset", "data",
                          "init_from", "routine_envs", "routine_samples"}
    key = compile_key(smoke)
    for f in fields:
        assert getattr(key, f.name) == getattr(base if f.name in uncompiled else smoke, f.name)
    assert compile_key(apply_overrides(smoke, ["log_every=7", "data=endless"])) == key
    assert compile_key(apply_overrides(smoke, ["steps=30"])) != key


def test_from_dict_rejects_unknown_keys():
    data = get_preset("smoke").to_dict()
    data["learning_rate"] = 1.0
    with pytest.raises(ValueError, match="learning_rate"):
        TrainConfig.from_dict(data)


def test_configs_saved_with_removed_fields_still_load():
    """run_dir (TrainConfig) and max_tokens (ModelConfig) configured nothing and were removed;
    checkpoints written before still restore, and a really unknown key is still refused."""
    data = get_preset("smoke").to_dict()
    data["run_dir"], data["model"]["max_tokens"] = "runs/x", 20
    assert TrainConfig.from_dict(data) == get_preset("smoke")
    data["model"]["max_token"] = 20
    with pytest.raises(ValueError, match="max_token"):
        TrainConfig.from_dict(data)


def test_the_family_is_stored_under_its_old_key():
    """TrainConfig.family is "model_kind" in config.json, as older versions wrote it: saved runs
    and shipped models read as before, and a config naming it either way loads (once)."""
    mlp = apply_overrides(get_preset("smoke"), ["family=mlp"])
    data = mlp.to_dict()
    assert data["model_kind"] == "mlp" and "family" not in data
    assert list(data)[:3] == ["model", "model_kind", "flowsim"]  # the order older versions wrote
    assert TrainConfig.from_dict(data) == mlp
    renamed = {("family" if k == "model_kind" else k): v for k, v in data.items()}
    assert TrainConfig.from_dict(renamed) == mlp
    with pytest.raises(ValueError, match="twice"):
        TrainConfig.from_dict({**data, "family": "mlp"})
    assert apply_overrides(get_preset("smoke"), ["model_kind=mlp"]) == mlp


def test_typed_values_are_set_as_given_with_the_text_overrides():
    smoke = get_preset("smoke")
    cfg = replace_fields(smoke, ["warmup_steps=50", "steps=3"], {"steps": 100, "init_from": "none"})
    assert (cfg.steps, cfg.warmup_steps, cfg.init_from) == (100, 50, "none")  # no text parsing
    assert replace_fields(smoke) is smoke
    with pytest.raises(ValueError, match=r"bad override \(steps\): steps must be"):
        replace_fields(smoke, (), {"steps": 0})
    with pytest.raises(ValueError, match="unknown config key 'stepz'"):
        replace_fields(smoke, (), {"stepz": 3})


def test_overrides_convert_types_including_nested_fields():
    cfg = apply_overrides(get_preset("smoke"), [
        "model.dim=64", "lr=2e-3", "steps=1e3", "clip_norm=none", "t_sampler=uniform",
        "model.baseline_variance=learned", "model.dropout=0.0"])
    assert cfg.model.dim == 64 and isinstance(cfg.model.dim, int)
    assert cfg.lr == 2e-3 and cfg.steps == 1000 and cfg.clip_norm is None
    assert cfg.t_sampler == "uniform" and cfg.model.dropout == 0.0
    assert cfg.model.baseline_variance == "learned"
    again = apply_overrides(cfg, {"clip_norm": "0.5"})
    assert again.clip_norm == 0.5


def test_homes_rhythms_preset_and_tuple_overrides_from_the_command_line():
    """The homes recipe on other preference contexts; tuples set as comma-separated items."""
    homes, rhythms = get_preset("homes"), get_preset("homes-rhythms")
    assert rhythms.homes.day_phases == (7, 9, 17, 18) and homes.homes.day_phases == (0, 6, 12, 18)
    assert dataclasses.replace(rhythms, homes=homes.homes, preset="homes") == homes
    args = build_parser().parse_args(["--preset", "homes", "--set", "homes.day_phases=7, 9,17,18",
                                      "--set", "homes.routine_probs=0.1,0.8,0.1"])
    cfg, _ = resolve_config(args)
    assert cfg.homes == dataclasses.replace(homes.homes, day_phases=(7, 9, 17, 18),
                                            routine_probs=(0.1, 0.8, 0.1))
    for bad in ("7,9,17", "7,9,17,24", "9,7,17,18", "7,9,x,18"):
        with pytest.raises(ValueError, match=r"homes\.day_phases"):
            apply_overrides(homes, [f"homes.day_phases={bad}"])


def test_coupled_overrides_are_validated_together():
    cfg = apply_overrides(get_preset("smoke"), ["flowsim.num_timesteps=10", "model.tau_max=10"])
    assert cfg.model.tau_max == cfg.flowsim.num_timesteps == 10
    with pytest.raises(ValueError, match="tau_max"):
        apply_overrides(get_preset("smoke"), ["flowsim.num_timesteps=10"])


@pytest.mark.parametrize("override, fragment", [
    ("model.dimm=3", "model.dimm"),
    ("nonsense=1", "nonsense"),
    ("lr=fast", "lr must be a finite real number"),
    ("steps=1.5", "steps must be an int"),
    ("family=transformer", "family"),
    ("model_kind=transformer", "model_kind"),  # the key config.json stores it under
    ("t_sampler=normal", "t_sampler"),
    ("model=3", "section"),
    ("lr.x=1", "lr.x"),
    ("model.heads=5", "heads"),
    ("warmup_steps=100000", "warmup_steps"),
    ("ema_decay=1.0", "ema_decay"),
    ("clip_norm=0", "clip_norm"),
    ("batch_size=0", "batch_size"),
    ("no_equals_sign", "key=value"),
])
def test_bad_overrides_raise_value_error_naming_the_key(override, fragment):
    with pytest.raises(ValueError, match=fragment):
        apply_overrides(get_preset("smoke"), [override])


def test_cli_flags_override_the_preset(tmp_path):
    args = build_parser().parse_args([
        "--preset", "smoke", "--family", "mlp", "--steps", "7", "--set", "lr=0.01",
        "--set", "model.dim=16", "--run-dir", str(tmp_path / "r")])
    cfg, run_dir = resolve_config(args)
    assert (cfg.family, cfg.steps, cfg.lr, cfg.model.dim) == ("mlp", 7, 0.01, 16)
    assert run_dir == tmp_path / "r"
    # --model is the older spelling of --family; the typed flags win over --set
    args = build_parser().parse_args(["--preset", "smoke", "--model", "mlp", "--steps", "9",
                                      "--set", "steps=5", "--set", "family=flowmaps"])
    cfg, _ = resolve_config(args)
    assert (cfg.family, cfg.steps) == ("mlp", 9)


def test_a_bad_typed_flag_is_a_usage_error_naming_it(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--preset", "smoke", "--steps", "0"])
    assert exit_info.value.code == 2 and "steps must be" in capsys.readouterr().err


def test_default_run_dir_names_model_and_preset():
    _, run_dir = resolve_config(build_parser().parse_args(["--preset", "smoke"]))
    assert run_dir.parts[0] == "runs" and run_dir.name.startswith("flowmaps-smoke-")


def _save_run(run_dir, cfg):
    """A run directory whose checkpoint (a stand-in state) carries ``cfg``."""
    import jax.numpy as jnp

    from flowmaps_jax.store.checkpoint_store import CheckpointStore
    from flowmaps_jax.training import objectives
    from flowmaps_jax.training import state as train_state

    stand_in = objectives.Objective(init=lambda key: {"w": jnp.ones(3)}, loss=None)
    with CheckpointStore(run_dir / "checkpoints") as store:
        store.save(train_state.init_state(cfg, objective=stand_in), cfg.to_dict())


def test_resume_reads_the_saved_config(tmp_path):
    saved = apply_overrides(get_preset("smoke"), ["model.dim=48", "model.heads=4"])
    _save_run(tmp_path, saved)
    args = build_parser().parse_args(["--resume", "--run-dir", str(tmp_path), "--steps", "30"])
    cfg, run_dir = resolve_config(args)
    assert cfg.model.dim == 48 and cfg.steps == 30 and run_dir == tmp_path
    # config.json (the last run's --steps etc.) is read for the fields --resume may change only
    (tmp_path / "config.json").write_text(json.dumps(
        apply_overrides(saved, ["steps=40"]).to_dict()))
    cfg, _ = resolve_config(build_parser().parse_args(["--resume", "--run-dir", str(tmp_path)]))
    assert cfg.steps == 40 and cfg.model.dim == 48
    # ... and only when it is the config of the same run (issue 19: not another model's)
    (tmp_path / "config.json").write_text(json.dumps(
        apply_overrides(saved, ["steps=40", "model.dim=64"]).to_dict()))
    with pytest.raises(ValueError, match="is not the config of the run's checkpoints"):
        resolve_config(build_parser().parse_args(["--resume", "--run-dir", str(tmp_path)]))
    (tmp_path / "config.json").write_text("{half")
    cfg, _ = resolve_config(build_parser().parse_args(["--resume", "--run-dir", str(tmp_path)]))
    assert cfg == saved


FLOAT_FIELDS = ("lr", "weight_decay", "b1", "b2", "ema_decay", "clip_norm", "target_noise",
                "pointer_loss", "short_horizon_frac")


@pytest.mark.parametrize("name", FLOAT_FIELDS)
@pytest.mark.parametrize("value", [float("inf"), float("-inf"), float("nan"), True, "0.1"])
def test_every_float_field_must_be_a_finite_real_number(name, value):
    with pytest.raises(ValueError, match=f"^{name} must be"):
        dataclasses.replace(get_preset("smoke"), **{name: value})
    if isinstance(value, float):
        with pytest.raises(ValueError, match=f"{name} must be a finite real number"):
            apply_overrides(get_preset("smoke"), [f"{name}={value}"])


@pytest.mark.parametrize("override, fragment", [
    ("seed=99999999999999999999", "seed must be an int in 0..4294967295"),
    ("seed=-1", "seed"),
    ("steps=3000000000", "steps must be an int in 1..2147483647"),
    ("lr=1e400", "lr must be a finite real number"),
])
def test_out_of_range_numbers_are_value_errors(override, fragment):
    with pytest.raises(ValueError, match=fragment):
        apply_overrides(get_preset("smoke"), [override])


def test_large_integers_convert_exactly():
    assert apply_overrides(get_preset("smoke"), ["seed=4294967295"]).seed == 2**32 - 1


@pytest.mark.parametrize("argv, fragment", [
    (["--resume"], "--run-dir"),
    (["--resume", "--run-dir", "RUN", "--preset", "smoke"], "does not exist"),  # repeat allowed
    (["--resume", "--run-dir", "RUN"], "does not exist"),
    (["--preset", "smoke", "--set", "model.width=3"], "model.width"),
    (["--preset", "smoke", "--stop-at", "999"], "stop_at"),
    (["--preset", "smoke", "--set", "seed=99999999999999999999"], "seed"),
    (["--preset", "smoke", "--set", "lr=inf"], "lr must be a finite real number"),
    (["--preset", "smoke", "--from-step", "3"], "--from-step needs --resume"),
    (["--resume", "--overwrite", "--run-dir", "RUN"], "exclude each other"),
])
def test_cli_errors_are_clear(argv, fragment, tmp_path, capsys):
    argv = [str(tmp_path / "missing") if a == "RUN" else a for a in argv]
    argv += [] if "--run-dir" in argv else ["--run-dir", str(tmp_path / "out")]
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert fragment in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # nothing was written
