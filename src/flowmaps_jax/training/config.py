"""Training configuration: the ``TrainConfig`` dataclass, named presets and command-line overrides.

A run is fully described by one frozen :class:`TrainConfig` (which nests the model's
:class:`~flowmaps_jax.model.ModelConfig` and the simulator's
:class:`~flowmaps_jax.flowsim.FlowSimConfig`). It round-trips through JSON (``to_dict`` /
``from_dict``) so a run directory's ``config.json`` is enough to rebuild the run.

Presets (``get_preset(name)``):

* ``paper`` — the paper's hyper-parameters: D = 256, 8 encoder layers, 8 CDiT blocks, 8 heads,
  dropout 0.1, batch 256, 30k steps, AdamW β = (0.95, 0.999), cosine schedule from 1e-4, EMA 0.9999.
* ``cpu`` — the default: a smaller model and schedule that trains in about 20 minutes on a
  2-core CPU, with the recipe that learns the routines (pointer head; see :func:`cpu_preset`).
* ``smoke`` — a tiny model on a tiny dataset that trains in seconds; used by the tests.

Any field, including nested ones (``model.dim``, ``flowsim.num_timesteps``), can be overridden from
strings ``key=value`` (see :func:`apply_overrides`); values are converted to the field's type and
unknown keys or bad values raise ``ValueError`` naming the key.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import types
import typing
from typing import Any, Literal

from flowmaps_jax.flow import T_SAMPLERS
from flowmaps_jax.flowsim.config import FlowSimConfig
from flowmaps_jax.model.config import ModelConfig
from flowmaps_jax.training.objectives import MODEL_KINDS
from flowmaps_jax.validation import (
    INT32_MAX,
    check_int,
    check_plain_name,
    check_real,
    check_resources,
    check_seed,
    network_flops,
    solver_evaluations,
)

DATA_SOURCES = ("train", "endless")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run (model, data, optimiser, logging, checkpoints).

    model: network sizes (``ModelConfig``); also used by the MLP baseline's Map Encoder.
    model_kind: "flowmaps" (flow matching, CDiT) or "mlp" (Gaussian baseline; its variant is
        ``model.baseline_variance``, "mean" or "learned").
    flowsim: simulator settings for the generated train/validation splits.
    batch_size: scenes per step (B); queries_per_scene: queries sharing one encoder pass (Q).
    steps: total optimiser steps; the cosine schedule decays over exactly this many.
    lr, warmup_steps: peak learning rate and linear warm-up length (0 = plain cosine decay).
    b1, b2, weight_decay: AdamW parameters; clip_norm: global-norm clipping (None = off).
    ema_decay: EMA rate of the weights (ema <- decay * ema + (1 - decay) * params).
    t_sampler: flow-time law, "beta" (paper's choice), "uniform" or "logit_normal".
    short_horizon_frac, short_horizon_max: fraction of training queries whose horizon
        τ_q − τ is drawn from 1..short_horizon_max instead of the protocol's mixture (0 = paper).
    target_noise: train on targets jittered by ``target_noise`` × the evaluation protocol's
        ground-truth std (centre 0.35 × side, size 0.02 × side), i.e. on samples of the protocol's
        smoothed q rather than on its delta peaks (0 = paper).
    pointer_loss: weight of an auxiliary cross-entropy on the pointer head's anchor logits
        against the table the target stands on (``flow.cfm_loss``; FlowMaps with
        ``model.head="pointer"`` only; the MLP baseline ignores it. Departs from the paper;
        0 = off).
    data: "train" (fixed FlowSim split of ``train_envs`` environments) or "endless" (a fresh
        chunk of ``train_envs`` environments every ``train_envs // batch_size`` steps).
    train_envs, val_envs: split sizes; val_batches: fixed validation batches per evaluation.
    routine_envs, routine_samples: the routine diagnostic (:mod:`flowmaps_jax.routine`) run at
        every validation on this many validation environments (at most ``val_envs``; × 3
        objects, once one step ahead and once at mixed horizons) with this many samples per
        query; 0 environments = off.
    seed: the single seed from which params, dropout and data keys are derived.
    log_every, val_every, ckpt_every: intervals in steps; keep_last: recent checkpoints kept.
    devices: train data-parallel over this many devices (None = every device JAX sees; see
        :mod:`flowmaps_jax.distributed`). ``batch_size`` must divide by it. The global batch,
        and so the numbers, do not depend on it (up to float summation order), and a checkpoint
        continues on any device count.
    preset: name of the preset this config started from (informational, used in run names).
    """

    model: ModelConfig = dataclasses.field(default_factory=ModelConfig)
    model_kind: str = "flowmaps"
    flowsim: FlowSimConfig = dataclasses.field(default_factory=FlowSimConfig)
    batch_size: int = 64
    queries_per_scene: int = 4
    steps: int = 3000
    lr: float = 3e-4
    warmup_steps: int = 100
    b1: float = 0.95
    b2: float = 0.999
    weight_decay: float = 0.01
    clip_norm: float | None = 1.0
    ema_decay: float = 0.999
    t_sampler: str = "beta"
    short_horizon_frac: float = 0.0
    short_horizon_max: int = 3
    target_noise: float = 0.0
    pointer_loss: float = 0.0
    data: str = "train"
    train_envs: int = 2500
    val_envs: int = 200
    val_batches: int = 4
    routine_envs: int = 20
    routine_samples: int = 32
    seed: int = 0
    log_every: int = 50
    val_every: int = 500
    ckpt_every: int = 500
    keep_last: int = 2
    devices: int | None = None
    preset: str = "cpu"

    def __post_init__(self):
        _check_choice("model_kind", self.model_kind, tuple(MODEL_KINDS))
        _check_choice("t_sampler", self.t_sampler, T_SAMPLERS)
        _check_choice("data", self.data, DATA_SOURCES)
        for name in ("batch_size", "queries_per_scene", "steps", "train_envs", "val_envs",
                     "val_batches", "log_every", "val_every", "ckpt_every", "keep_last",
                     "routine_samples", "short_horizon_max"):
            check_int(name, getattr(self, name), maximum=INT32_MAX)
        check_int("routine_envs", self.routine_envs, minimum=0, maximum=INT32_MAX)
        check_seed("seed", self.seed)
        check_plain_name("preset", self.preset)  # it names the default run directory
        if self.devices is not None:
            check_int("devices", self.devices, maximum=INT32_MAX)
            if self.batch_size % self.devices:
                raise ValueError(
                    f"batch_size={self.batch_size} does not divide evenly over devices="
                    f"{self.devices} (each device takes batch_size / devices scenes): use a "
                    f"multiple of {self.devices}, or devices dividing {self.batch_size}")
        if check_int("warmup_steps", self.warmup_steps, minimum=0) >= self.steps:
            raise ValueError(f"warmup_steps must be an integer in [0, steps={self.steps}); "
                             f"got {self.warmup_steps!r}")
        # Every float: a finite real number (not inf, NaN, a bool or a string) within its range.
        check_real("lr", self.lr, 0.0, low_open=True)
        for name in ("b1", "b2", "ema_decay"):
            check_real(name, getattr(self, name), 0.0, 1.0, high_open=True)
        check_real("weight_decay", self.weight_decay, 0.0)
        if self.clip_norm is not None:
            check_real("clip_norm", self.clip_norm, 0.0, low_open=True)
        check_real("short_horizon_frac", self.short_horizon_frac, 0.0, 1.0)
        check_real("target_noise", self.target_noise, 0.0, 10.0, high_open=True)
        check_real("pointer_loss", self.pointer_loss, 0.0, 100.0, high_open=True)
        if not isinstance(self.model, ModelConfig):
            raise ValueError(f"model must be a ModelConfig; got {type(self.model).__name__}")
        if not isinstance(self.flowsim, FlowSimConfig):
            raise ValueError(f"flowsim must be a FlowSimConfig; got {type(self.flowsim).__name__}")
        if self.pointer_loss > 0 and self.model_kind == "flowmaps" and \
                self.model.head not in ("pointer", "route"):
            raise ValueError("pointer_loss > 0 needs model.head='pointer' or 'route' (the MLP "
                             "baseline ignores it)")
        sim, net = self.flowsim, self.model
        if net.num_descriptors < sim.num_descriptors:
            raise ValueError(f"model.num_descriptors={net.num_descriptors} is smaller than the "
                             f"simulator's {sim.num_descriptors} descriptor ids")
        if net.tau_max != sim.num_timesteps:
            raise ValueError(f"model.tau_max={net.tau_max} must equal "
                             f"flowsim.num_timesteps={sim.num_timesteps}")

    def to_dict(self) -> dict:
        """A JSON-able dict (nested configs become nested dicts)."""
        return _to_jsonable(self)

    @classmethod
    def from_dict(cls, data: dict) -> TrainConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError``."""
        return _from_dict(cls, data, "config")

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=False)


# --------------------------------------------------------------------------------------------
# Resource bounds


_ROUTINE_QUERIES = 3 * 2  # the routine probe: 3 objects per environment, at two horizon laws


def resource_estimate(cfg: TrainConfig, devices: int = 1) -> list[tuple[str, int, int]]:
    """What a run of ``cfg`` needs, part by part, on each of ``devices`` data-parallel devices:
    ``[(what, bytes, FLOPs), ...]`` where ``what`` names the fields that set the part's size.
    FLOPs are those of one uninterruptible call (a train step, a validation); ``steps`` is not
    bounded (a run stops and resumes between steps). A rough, generous estimate
    (:func:`flowmaps_jax.validation.network_flops`)."""
    net, sim = cfg.model, cfg.flowsim
    tokens = sim.num_furniture + sim.num_objects
    b, q = cfg.batch_size, cfg.queries_per_scene
    per_layer = net.dim * net.dim * (4 + 2 * net.mlp_ratio)
    params = (net.encoder_layers * per_layer + net.cdit_blocks * (per_layer + 6 * net.dim ** 2)
              + 2 * net.dim * net.baseline_hidden + net.baseline_hidden ** 2)
    query_flops, scene_flops = network_flops(net, cfg.model_kind, tokens)
    # activations kept for the backward pass: per query row and per scene token, every layer
    row = 4 * net.dim * (net.mlp_ratio + 8) * net.cdit_blocks * 2
    token = 4 * (net.dim * (net.mlp_ratio + 8) + tokens * net.heads) * net.encoder_layers * 2
    shard = max(1, int(devices))
    step_bytes = -(-b // shard) * (q * row + tokens * token)
    batch_bytes = 4 * (b * sim.max_tokens * 7 + b * q * 6)
    envs = cfg.train_envs + cfg.val_envs
    env_bytes = 4 * (sim.num_furniture * 5 + sim.num_objects * (3 + sim.num_furniture)
                     + sim.num_timesteps * sim.num_objects * 5 + 1)
    routine_envs = min(cfg.routine_envs, cfg.val_envs)
    routine_rows = routine_envs * _ROUTINE_QUERIES * cfg.routine_samples
    from flowmaps_jax.model.sampling import DEFAULT_NUM_STEPS

    evaluations = solver_evaluations(DEFAULT_NUM_STEPS) if cfg.model_kind == "flowmaps" else 1
    return [
        (f"the model (model.dim={net.dim}, model.encoder_layers={net.encoder_layers}, "
         f"model.cdit_blocks={net.cdit_blocks}, model.mlp_ratio={net.mlp_ratio}: about "
         f"{params:,} parameters, with EMA, optimiser state and gradients)",
         4 * 5 * params, 0),
        (f"a train step (batch_size={b} x queries_per_scene={q} at model.dim={net.dim})",
         step_bytes, 3 * (b * q * query_flops + b * scene_flops)),
        (f"the validation batches (val_batches={cfg.val_batches} of batch_size={b} x "
         f"queries_per_scene={q})",
         cfg.val_batches * batch_bytes + step_bytes // 2,
         cfg.val_batches * (b * q * query_flops + b * scene_flops)),
        (f"the data (train_envs={cfg.train_envs} + val_envs={cfg.val_envs} environments)",
         envs * env_bytes, 0),
        (f"the routine diagnostic (routine_envs={routine_envs} environments x "
         f"{_ROUTINE_QUERIES} queries x routine_samples={cfg.routine_samples} samples)",
         routine_rows * (4 * net.dim * (net.mlp_ratio + 4) + 4 * (4 + sim.num_furniture)),
         routine_rows * evaluations * query_flops + routine_envs * 2 * scene_flops),
    ]


def check_run_resources(cfg: TrainConfig, devices: int = 1) -> None:
    """``ValueError`` naming the fields when a part of :func:`resource_estimate`, or all of it
    together, is over the memory or work budget (:func:`flowmaps_jax.validation.memory_limit`,
    :func:`~flowmaps_jax.validation.flops_limit`; environment variables FLOWMAPS_MAX_BYTES and
    FLOWMAPS_MAX_FLOPS raise them)."""
    parts = resource_estimate(cfg, devices)
    for what, num_bytes, flops in parts:
        check_resources(what, num_bytes=num_bytes, flops=flops)
    check_resources("the run altogether (model, step, validation, data and routine "
                    "diagnostic)", num_bytes=sum(p[1] for p in parts))


def _check_choice(name: str, value: Any, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ValueError(f"{name} must be one of {list(choices)}; got {value!r}")


# --------------------------------------------------------------------------------------------
# Presets


def paper_preset() -> TrainConfig:
    """The paper's hyper-parameters (PAPER.md, "FlowMaps (model)")."""
    return TrainConfig(
        model=ModelConfig(dim=256, encoder_layers=8, cdit_blocks=8, heads=8, dropout=0.1),
        batch_size=256, queries_per_scene=1, steps=30_000, lr=1e-4, warmup_steps=0,
        b1=0.95, b2=0.999, weight_decay=0.01, clip_norm=None, ema_decay=0.9999,
        log_every=100, val_every=1000, ckpt_every=1000, preset="paper")


def cpu_preset() -> TrainConfig:
    """Default: the model a 2-core CPU trains in under 30 minutes, and that learns the routines.

    Size (docs/results.md, "Choosing the cpu preset"): D = 128 with 4 + 4 layers, B = 64 scenes ×
    Q = 8 queries, 8,500 steps. Recipe (docs/results.md, "Learning the routines", ablation by
    ``experiments/ablate_routines.py``; docs/design.md says why): the pointer read-out head with
    its auxiliary pointer loss, Δτ conditioning, half the queries one step ahead, targets jittered
    by the protocol's σ, lr 1e-3 and no dropout. ``--preset paper`` keeps the paper's recipe.
    """
    return TrainConfig(
        model=ModelConfig(dim=128, encoder_layers=4, cdit_blocks=4, heads=4, dropout=0.0,
                          baseline_hidden=256, head="pointer", condition_on_dtau=True,
                          pointer_widths="relative", pointer_width_scale=10.0),
        batch_size=64, queries_per_scene=8, steps=8500, lr=1e-3, warmup_steps=200,
        clip_norm=1.0, ema_decay=0.999, short_horizon_frac=0.5, short_horizon_max=1,
        target_noise=1.0, pointer_loss=1.0, log_every=50, val_every=500,
        ckpt_every=500, preset="cpu")


def smoke_preset() -> TrainConfig:
    """A tiny model on a tiny dataset: trains in seconds (tests, CI)."""
    return TrainConfig(
        model=ModelConfig(dim=32, encoder_layers=1, cdit_blocks=1, heads=2, dropout=0.1,
                          freq_bands=8, baseline_hidden=32),
        batch_size=8, queries_per_scene=2, steps=20, lr=1e-3, warmup_steps=2,
        clip_norm=1.0, ema_decay=0.9, train_envs=64, val_envs=64, val_batches=2,
        log_every=5, val_every=10, ckpt_every=10, keep_last=2, preset="smoke")


PRESETS = {"paper": paper_preset, "cpu": cpu_preset, "smoke": smoke_preset}
DEFAULT_PRESET = "cpu"


def get_preset(name: str = DEFAULT_PRESET) -> TrainConfig:
    """The named preset (``paper``, ``cpu`` or ``smoke``) as a fresh ``TrainConfig``."""
    if name not in PRESETS:
        raise ValueError(f"preset must be one of {sorted(PRESETS)}; got {name!r}")
    return PRESETS[name]()


# --------------------------------------------------------------------------------------------
# Overrides from strings

SHORTHANDS = {"precision": "model.precision"}
"""Top-level override keys that stand for a nested field (``--set precision=bf16``)."""


def apply_overrides(cfg: TrainConfig, overrides: typing.Iterable[str] | dict[str, Any]
                    ) -> TrainConfig:
    """Return ``cfg`` with fields replaced, e.g. ``["model.dim=64", "lr=1e-3", "clip_norm=none"]``.

    Keys are dotted paths into nested dataclasses. String values are converted to the field's
    annotated type (int, float, bool, str, ``X | None`` where "none"/"null" gives None); a dict
    may also carry already-typed values. All overrides are applied before the result is validated,
    so coupled fields (``flowsim.num_timesteps`` and ``model.tau_max``) can change together.
    Unknown keys, unconvertible values and invalid results raise ``ValueError`` naming the key.
    Keys in :data:`SHORTHANDS` are short for a nested path: ``precision=bf16`` sets
    ``model.precision``.
    """
    if isinstance(overrides, dict):
        items = list(overrides.items())
    else:
        items = []
        for text in overrides:
            if "=" not in text:
                raise ValueError(f"override {text!r} must look like key=value")
            key, value = text.split("=", 1)
            items.append((key.strip(), value.strip()))
    if not items:
        return cfg
    data = cfg.to_dict()
    for key, value in items:
        path = SHORTHANDS.get(key, key).split(".")
        _set_path(TrainConfig, data, path, value, key)
    try:
        return TrainConfig.from_dict(data)
    except (ValueError, TypeError) as err:
        keys = ", ".join(k for k, _ in items)
        raise ValueError(f"bad override ({keys}): {err}") from err


def _set_path(cls: type, data: dict, path: list[str], value: Any, full_key: str) -> None:
    """Set ``data[path]`` (a to_dict() view of dataclass ``cls``), converting ``value``."""
    names = [f.name for f in dataclasses.fields(cls)]
    head = path[0]
    if head not in names:
        raise ValueError(f"unknown config key {full_key!r} ({cls.__name__} has no field "
                         f"{head!r}; known: {sorted(names)})")
    hint = typing.get_type_hints(cls)[head]
    is_section = isinstance(hint, type) and dataclasses.is_dataclass(hint)
    if len(path) > 1:
        if not is_section:
            raise ValueError(f"unknown config key {full_key!r} ({head!r} has no sub-fields)")
        _set_path(hint, data[head], path[1:], value, full_key)
    elif is_section:
        raise ValueError(f"config key {full_key!r} is a section; set one of its fields, "
                         f"e.g. {full_key}.{_field_names(hint)[0]}=...")
    else:
        data[head] = _convert(value, hint, full_key) if isinstance(value, str) else value


def _field_names(cls: type) -> list[str]:
    """Field names of dataclass ``cls`` in declaration order."""
    return [f.name for f in dataclasses.fields(cls)]


_NONE_WORDS = ("none", "null")
_TRUE_WORDS = ("true", "1", "yes", "on")
_FALSE_WORDS = ("false", "0", "no", "off")


def _convert(text: str, hint: Any, key: str) -> Any:
    """Convert a command-line string to the annotated type ``hint``."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        if type(None) in args and text.lower() in _NONE_WORDS:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(text, arg, key)
            except ValueError as err:
                errors.append(str(err))
        raise ValueError(f"bad value {text!r} for {key!r}: " + "; ".join(errors))
    if origin is Literal:
        choices = typing.get_args(hint)
        for choice in choices:
            if str(choice) == text:
                return choice
        raise ValueError(f"bad value {text!r} for {key!r}: must be one of {list(choices)}")
    if hint is bool:
        if text.lower() in _TRUE_WORDS:
            return True
        if text.lower() in _FALSE_WORDS:
            return False
        raise ValueError(f"bad value {text!r} for {key!r}: expected a boolean (true/false)")
    if hint is int:
        with contextlib.suppress(ValueError):
            return int(text)
        try:
            as_float = float(text)
        except ValueError:
            raise ValueError(f"bad value {text!r} for {key!r}: expected an integer") from None
        if not as_float.is_integer():
            raise ValueError(f"bad value {text!r} for {key!r}: expected an integer")
        return int(as_float)
    if hint is float:
        try:
            return float(text)
        except ValueError:
            raise ValueError(f"bad value {text!r} for {key!r}: expected a number") from None
    if hint is str:
        return text
    raise ValueError(f"config key {key!r} (type {hint}) cannot be set from the command line")


# --------------------------------------------------------------------------------------------
# JSON round trip


def _to_jsonable(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        to_dict = getattr(obj, "to_dict", None)
        if to_dict is not None and not isinstance(obj, TrainConfig):
            return _to_jsonable(to_dict())
        return {f.name: _to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): _to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_to_jsonable(v) for v in obj]
    return obj


# Fields that older versions wrote and that no longer exist (they configured nothing): configs
# saved with them still load.
_REMOVED_KEYS = {"TrainConfig": ("run_dir",), "ModelConfig": ("max_tokens",)}


def _from_dict(cls: type, data: Any, where: str) -> Any:
    """Build dataclass ``cls`` from a dict, using ``cls.from_dict`` for nested configs."""
    if not isinstance(data, dict):
        raise ValueError(
            f"{where} must be a dict to build {cls.__name__}; got {type(data).__name__}")
    if cls is not TrainConfig and hasattr(cls, "from_dict"):
        return cls.from_dict(data)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    data = {k: v for k, v in data.items() if k not in _REMOVED_KEYS.get(cls.__name__, ())}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ValueError(f"{where} has unknown keys {unknown} for {cls.__name__}")
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, value in data.items():
        hint = hints[name]
        if isinstance(hint, type) and dataclasses.is_dataclass(hint):
            value = _from_dict(hint, value, f"{where}.{name}")
        elif isinstance(value, list):
            value = tuple(value)
        kwargs[name] = value
    return cls(**kwargs)


def format_config(cfg: TrainConfig) -> str:
    """Human-readable multi-line dump of the resolved config (printed at the start of a run)."""
    flat = _flatten(cfg.to_dict())
    width = max(len(k) for k in flat)
    return "\n".join(f"  {k:<{width}} = {v}" for k, v in flat.items()
                     if not k.startswith(("flowsim.furniture_kinds", "flowsim.categories")))


def _flatten(data: dict, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(_flatten(value, name + "."))
        else:
            out[name] = value
    return out
