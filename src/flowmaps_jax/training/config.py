"""Training configuration: the run configs of each world and their named presets.

A run is one frozen config (:class:`TrainConfig` on 2-D FlowSim, :class:`HomesTrainConfig`,
:class:`RecordedTrainConfig`) that round-trips through JSON (``config.json`` rebuilds the run).
Presets: ``get_preset(name)`` (each preset function says what it is). Every field declares its
role (:data:`ROLES`), from which :func:`compile_key` (the compile cache's key) and
:data:`RESUMABLE_FIELDS` (what ``--resume`` may change) derive. ``key=value`` overrides:
:mod:`flowmaps_jax.training.overrides`.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import typing
from typing import Any

from flowmaps_jax.flow import T_SAMPLERS
from flowmaps_jax.flowsim.config import FlowSimConfig
from flowmaps_jax.flowsim.homes.config import HomesConfig
from flowmaps_jax.flowsim.worlds import HABITS_HISTORY, world_config  # the habits preset's H
from flowmaps_jax.model.config import ModelConfig
from flowmaps_jax.model.families import MODEL_FAMILIES, model_family
from flowmaps_jax.model.homes_family import FAMILY_NAME as HOMES_FAMILY
from flowmaps_jax.model.homes_family import HomesModelConfig
from flowmaps_jax.resources import check_resources
from flowmaps_jax.store.model_spec import ModelSpec
from flowmaps_jax.training.overrides import (
    SHORTHANDS,
    apply_overrides,
    config_from_dict,
    config_to_dict,
    flatten,
)
from flowmaps_jax.validation import (
    INT32_MAX,
    check_instance,
    check_int,
    check_plain_name,
    check_seed,
    prefix_errors,
)
from flowmaps_jax.validation.fields import Choice, Int, Optional, Real, Text, check_fields
from flowmaps_jax.worlds import WORLDS, world, world_of_family

DATA_SOURCES = ("train", "endless")

__all__ = ["DATA_SOURCES", "DEFAULT_PRESET", "PRESETS", "RESUMABLE_FIELDS", "ROLES", "SHORTHANDS",
           "HomesTrainConfig", "RecordedTrainConfig", "Role", "TrainConfig", "apply_overrides",
           "check_run_resources", "compile_key", "config_from_stored", "cpu_preset",
           "format_config", "get_preset", "paper_preset", "presets", "recorded_config",
           "resumable_fields", "run_configs", "smoke_preset"]


# --------------------------------------------------------------------------------------------
# Field roles


class Role(typing.NamedTuple):
    """What a :class:`TrainConfig` field is to a run."""

    compiled: bool
    """The compiled functions depend on it: it is part of :func:`compile_key`."""
    resumable: bool
    """``--resume`` may change it (:data:`RESUMABLE_FIELDS`)."""


ROLES = {
    # the model, objective, optimiser, data sizes and seed: what the run computes
    "recipe": Role(compiled=True, resumable=False),
    # how long the schedule runs (steps) and over how many devices: compiled in, yet a resumed
    # run may extend or move it
    "extent": Role(compiled=True, resumable=True),
    # where the training scenes come from: the step takes them as an argument, but a resumed
    # run keeps its data
    "source": Role(compiled=False, resumable=False),
    # logging, val and checkpoint intervals, the routine diagnostic, the preset's name
    "bookkeeping": Role(compiled=False, resumable=True),
}
"""The role each :class:`TrainConfig` field declares (``metadata["role"]``)."""


def _field(role: str, default: Any, stored_as: str | None = None) -> Any:
    """A dataclass field declaring its role in a run (a key of :data:`ROLES`), and the key it is
    stored under in ``config.json`` when that is not its name (``stored_as``; see
    :func:`flowmaps_jax.training.overrides.config_to_dict`)."""
    metadata = {"role": role} if stored_as is None else {"role": role, "stored_as": stored_as}
    return dataclasses.field(default=default, metadata=metadata)


_AS_RECIPE = {"role": "recipe"}  # for the nested configs, built by a default_factory
_recipe = functools.partial(_field, "recipe")
_extent = functools.partial(_field, "extent")
_source = functools.partial(_field, "source")
_bookkeeping = functools.partial(_field, "bookkeeping")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run (model, data, optimiser, logging, checkpoints).

    model: network sizes (``ModelConfig``); also used by the MLP baseline's Map Encoder.
    family: the model family, a :data:`~flowmaps_jax.model.families.MODEL_FAMILIES` name:
        "flowmaps" (flow matching, CDiT) or "mlp" (Gaussian baseline; its variant is
        ``model.baseline_variance``). Stored in ``config.json`` as ``"model_kind"`` (also
        accepted by ``--set``).
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
    pointer_loss: weight of the cross-entropy of the table weights against the table the
        target stands on (the mixture head's weights, or the pointer / route head's anchor
        logits as an auxiliary loss; ``training.objectives``; the MLP baseline ignores it.
        Departs from the paper; 0 = off).
    data: "train" (fixed FlowSim split of ``train_envs`` environments) or "endless" (a fresh
        chunk of ``train_envs`` environments every ``train_envs // batch_size`` steps).
    init_from: start from these weights instead of a random init (a run or checkpoint
        directory, or ``pretrained:NAME``): every parameter they hold is copied (same name and
        shape, or ValueError); parameters they lack, such as the age embedding of a model
        reading ``model.history`` > 1 maps, keep their fresh init. The optimiser starts fresh.
        None (default): a random init.
    train_envs, val_envs: split sizes; val_batches: fixed validation batches per val pass.
    routine_envs, routine_samples: the routine diagnostic (:mod:`flowmaps_jax.evaluation.routine`)
        run at every val pass on this many validation environments (at most ``val_envs``; × 3
        objects, once one step ahead and once at mixed horizons) with this many samples per
        query; 0 environments = off.
    seed: the single seed from which params, dropout and data keys are derived.
    log_every, val_every, ckpt_every: intervals in steps; keep_last: recent checkpoints kept.
    devices: train data-parallel over this many devices (None = every device JAX sees);
        ``batch_size`` must divide by it; the numbers do not depend on it.
    preset: name of the preset this config started from (informational, used in run names).

    Each field declares its role (:data:`ROLES`): ``recipe``, ``extent``, ``source`` or
    ``bookkeeping``.
    """

    world: typing.ClassVar[str] = "flowsim"
    """The world this config trains on (:func:`flowmaps_jax.worlds.world`)."""

    model: ModelConfig = dataclasses.field(default_factory=ModelConfig, metadata=_AS_RECIPE)
    family: str = _recipe("flowmaps", stored_as="model_kind")
    flowsim: FlowSimConfig = dataclasses.field(default_factory=FlowSimConfig, metadata=_AS_RECIPE)
    batch_size: int = _recipe(64)
    queries_per_scene: int = _recipe(4)
    steps: int = _extent(3000)
    lr: float = _recipe(3e-4)
    warmup_steps: int = _recipe(100)
    b1: float = _recipe(0.95)
    b2: float = _recipe(0.999)
    weight_decay: float = _recipe(0.01)
    clip_norm: float | None = _recipe(1.0)
    ema_decay: float = _recipe(0.999)
    t_sampler: str = _recipe("beta")
    short_horizon_frac: float = _recipe(0.0)
    short_horizon_max: int = _recipe(3)
    target_noise: float = _recipe(0.0)
    pointer_loss: float = _recipe(0.0)
    data: str = _source("train")
    init_from: str | None = _source(None)
    train_envs: int = _recipe(2500)
    val_envs: int = _recipe(200)
    val_batches: int = _recipe(4)
    routine_envs: int = _bookkeeping(20)
    routine_samples: int = _bookkeeping(32)
    seed: int = _recipe(0)
    log_every: int = _bookkeeping(50)
    val_every: int = _bookkeeping(500)
    ckpt_every: int = _bookkeeping(500)
    keep_last: int = _bookkeeping(2)
    devices: int | None = _extent(None)
    preset: str = _bookkeeping("cpu")

    def __post_init__(self):
        check_fields(self, _RULES, store=False)
        check_instance("model", self.model, ModelConfig)
        check_instance("flowsim", self.flowsim, FlowSimConfig)
        # Then the checks that couple two fields: each field's own error is named first.
        _check_warmup(self)
        if self.devices is not None and self.batch_size % self.devices:
            raise ValueError(
                f"batch_size={self.batch_size} does not divide evenly over devices="
                f"{self.devices} (each device takes batch_size / devices scenes): use a "
                f"multiple of {self.devices}, or devices dividing {self.batch_size}")
        reads_out = model_family(self.family).table_weights is not None  # FlowMaps' heads
        if self.pointer_loss > 0 and reads_out and not \
                model_family(self.family).has_table_weights(self.model):
            raise ValueError("pointer_loss > 0 needs model.head='pointer', 'route' or 'mixture' "
                             "(the MLP baseline ignores it)")
        ModelSpec(self.family, self.model, self.flowsim)  # the model fits the simulator
        sim, net = self.flowsim, self.model
        needed = sim.num_furniture + sim.num_objects * net.history
        if net.history > 1 and needed > sim.max_tokens:
            raise ValueError(f"model.history={net.history} reads {needed} tokens (F + M × "
                             f"history) but flowsim.max_tokens={sim.max_tokens}; raise "
                             f"flowsim.max_tokens to {needed}")

    def to_dict(self) -> dict:
        """A JSON-able dict (nested configs become nested dicts)."""
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, data: dict) -> TrainConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError``."""
        return config_from_dict(cls, data, "config")


_COUNT = Int(1, INT32_MAX)
_DECAY = Real(0.0, 1.0, high_open=True)
_RUN_RULES = {
    **{name: _COUNT for name in ("batch_size", "queries_per_scene", "steps", "val_batches",
                                 "log_every", "val_every", "ckpt_every", "keep_last")},
    "seed": check_seed, "preset": check_plain_name,  # the preset names the default run dir
    "init_from": Optional(Text("a checkpoint directory or pretrained:NAME")),
    "devices": Optional(_COUNT),
    # Every float: a finite real number (not inf, NaN, a bool or a string) within its range.
    "lr": Real(0.0, low_open=True), "b1": _DECAY, "b2": _DECAY, "ema_decay": _DECAY,
    "weight_decay": Real(0.0), "clip_norm": Optional(Real(0.0, low_open=True)),
}
"""The fields every run config has (the loop, the optimiser, the intervals), whatever its
world."""
_RULES = {
    "family": Choice(tuple(MODEL_FAMILIES)), "t_sampler": Choice(T_SAMPLERS),
    "data": Choice(DATA_SOURCES), **_RUN_RULES,
    **{name: _COUNT for name in ("train_envs", "val_envs", "routine_samples",
                                 "short_horizon_max")},
    "routine_envs": Int(0, INT32_MAX),
    "short_horizon_frac": Real(0.0, 1.0), "target_noise": Real(0.0, 10.0, high_open=True),
    "pointer_loss": Real(0.0, 100.0, high_open=True),
}
"""What each :class:`TrainConfig` field may hold on its own (checked, not converted); ``model``,
``flowsim`` and the checks that couple two fields follow in ``__post_init__``."""


def _check_warmup(config: TrainConfig | HomesTrainConfig) -> None:
    """``warmup_steps``: an int in 0..steps-1 (kept as a Python int)."""
    warmup = check_int("warmup_steps", config.warmup_steps, 0)
    if warmup >= config.steps:
        raise ValueError(f"warmup_steps must be an int in 0..steps-1 (steps = {config.steps}); "
                         f"got {warmup}")
    object.__setattr__(config, "warmup_steps", warmup)


@dataclasses.dataclass(frozen=True)
class HomesTrainConfig:
    """A training run on FlowSim homes (the world ``"homes"``, :mod:`flowmaps_jax.worlds.homes`).

    model: the homes network's sizes; family: ``"flowmaps-homes"`` (stored as ``"model_kind"``);
    homes: the homes world (regime ``"mixed"``: one model for all four regimes);
    ``batch_size`` homes per step × ``queries_per_scene`` queries (stored as
    ``"queries_per_home"``); the optimiser as :class:`TrainConfig`'s (``lr``, ``warmup_steps``,
    ``b1``, ``b2``, ``weight_decay``, ``clip_norm``, ``ema_decay``); fresh data
    (``chunk_homes`` new homes every ``chunk_steps`` steps); horizons
    (``default_horizon_frac`` of the queries from ``DEFAULT_HORIZONS`` up to ``max_horizon``,
    the rest log-uniform in 1 … ``max_horizon``); ``cfm_weight`` of the placement loss;
    validation (``val_homes`` fixed homes, ``val_batches`` batches of ``batch_size`` of them);
    ``init_from``, ``seed``, the intervals, ``keep_last``, ``devices`` and ``preset`` as
    :class:`TrainConfig`'s. Each field declares its role (:data:`ROLES`).
    """

    world: typing.ClassVar[str] = "homes"
    """The world this config trains on (:func:`flowmaps_jax.worlds.world`)."""

    model: HomesModelConfig = dataclasses.field(default_factory=HomesModelConfig,
                                                metadata=_AS_RECIPE)
    family: str = _recipe(HOMES_FAMILY, stored_as="model_kind")
    homes: HomesConfig = dataclasses.field(default_factory=lambda: HomesConfig(regime="mixed"),
                                           metadata=_AS_RECIPE)
    batch_size: int = _recipe(32)
    queries_per_scene: int = _recipe(8, stored_as="queries_per_home")
    steps: int = _extent(5000)
    lr: float = _recipe(1e-3)
    warmup_steps: int = _recipe(200)
    b1: float = _recipe(0.9)
    b2: float = _recipe(0.999)
    weight_decay: float = _recipe(0.01)
    clip_norm: float | None = _recipe(1.0)
    ema_decay: float = _recipe(0.998)
    chunk_homes: int = _recipe(256)
    chunk_steps: int = _recipe(32)
    default_horizon_frac: float = _recipe(0.5)
    max_horizon: int = _recipe(168)
    cfm_weight: float = _recipe(1.0)
    val_homes: int = _recipe(256)
    val_batches: int = _recipe(8)
    init_from: str | None = _source(None)
    seed: int = _recipe(0)
    log_every: int = _bookkeeping(50)
    val_every: int = _bookkeeping(250)
    ckpt_every: int = _bookkeeping(500)
    keep_last: int = _bookkeeping(2)
    devices: int | None = _extent(None)
    preset: str = _bookkeeping("homes")

    def __post_init__(self):
        check_instance("model", self.model, HomesModelConfig)
        check_instance("homes", self.homes, HomesConfig)
        check_fields(self, _HOMES_RULES, store=False)
        # Then the checks that couple two fields: each field's own error is named first.
        _check_warmup(self)
        most = self.homes.num_hours - self.model.history
        if self.max_horizon > most:
            raise ValueError(
                f"max_horizon must be <= {most} (homes.num_hours={self.homes.num_hours} - "
                f"model.history={self.model.history}: a map hour needs model.history hours "
                f"before it and max_horizon after it); got {self.max_horizon}")
        self._check_data()
        if self.devices is not None and self.batch_size % self.devices:
            raise ValueError(f"batch_size={self.batch_size} does not divide evenly over "
                             f"devices={self.devices}: use a multiple of {self.devices}")

    def _check_data(self) -> None:
        """The checks of the fields that say where the data comes from."""
        if self.val_homes < self.val_batches * self.batch_size:
            raise ValueError(f"val_homes must be an int in {self.val_batches * self.batch_size}"
                             f".. (val_batches x batch_size); got {self.val_homes}")

    def to_dict(self) -> dict:
        """A JSON-able dict (nested configs become nested dicts)."""
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, data: dict) -> HomesTrainConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError``."""
        return config_from_dict(cls, data, "config")


_HOMES_RULES = {
    "family": Choice((HOMES_FAMILY,)), **_RUN_RULES,
    **{name: _COUNT for name in ("chunk_homes", "chunk_steps", "max_horizon", "val_homes")},
    "cfm_weight": Real(0.0), "default_horizon_frac": Real(0.0, 1.0),
}
"""What each :class:`HomesTrainConfig` field may hold on its own (``model`` and ``homes`` are
checked first, in ``__post_init__``); the checks that couple two fields follow there."""

@dataclasses.dataclass(frozen=True)
class RecordedTrainConfig(HomesTrainConfig):
    """A training run of the homes network on a recorded dataset (the world ``"recorded"``,
    :mod:`flowmaps_jax.worlds.recorded`): :class:`HomesTrainConfig`'s fields (``homes`` is
    derived from the data, :func:`recorded_config`; ``chunk_homes``, ``chunk_steps`` and
    ``val_homes`` are not read) and ``data`` (the dataset's folder), the split by environment
    (``val_fraction``, ``test_fraction`` of them held out, 10 % each in every recipe, seeded by
    ``split_seed``) and by time (``time_fraction``: the last hours of every training
    environment held out; ``worlds.recorded.part_of``).
    ``data_digest``: :func:`flowmaps_jax.recorded.format.content_digest` of the data when the
    run began (set by :func:`recorded_config`): a resume refuses changed data, and evaluation
    knows a copy of the data elsewhere for the run's own. ``config.json`` stores
    ``"world": "recorded"`` beside the fields."""

    world: typing.ClassVar[str] = "recorded"
    """The world this config trains on (:func:`flowmaps_jax.worlds.world`)."""

    data: str | None = _source(None)
    data_digest: str | None = _source(None)
    val_fraction: float = _recipe(0.1)
    test_fraction: float = _recipe(0.1)
    time_fraction: float = _recipe(0.0)
    split_seed: int = _recipe(0)
    preset: str = _bookkeeping("recorded")

    def _check_data(self) -> None:
        """``data`` and the split (``val_homes``, ``chunk_homes``, ``chunk_steps``: not
        read)."""
        check_fields(self, _RECORDED_RULES, store=False)
        if self.val_fraction + self.test_fraction >= 1.0:
            raise ValueError(f"val_fraction + test_fraction must be < 1 (some environments "
                             f"train); got {self.val_fraction} + {self.test_fraction}")

    def to_dict(self) -> dict:
        """A JSON-able dict, with ``"world"`` (what :func:`config_from_stored` reads)."""
        return {**config_to_dict(self), "world": self.world}

    @classmethod
    def from_dict(cls, data: dict) -> RecordedTrainConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError``."""
        return config_from_dict(cls, {k: v for k, v in data.items() if k != "world"}, "config")


_RECORDED_RULES = {
    "data": Optional(Text("a recorded dataset's folder")),
    "data_digest": Optional(Text("a SHA-256 digest (hex)")),
    "val_fraction": Real(0.0, 1.0, high_open=True), "test_fraction": Real(0.0, 1.0, high_open=True),
    "time_fraction": Real(0.0, 1.0, high_open=True), "split_seed": check_seed,
}


def run_configs() -> tuple[type, ...]:
    """The run config classes of the registered worlds (each names its world: ``cls.world``)."""
    return tuple(dict.fromkeys(w.hook("config") for w in WORLDS.values()))


def config_from_stored(data: dict, where: str = "config") -> TrainConfig | HomesTrainConfig:
    """The run config a stored dict describes (``config.json``, a checkpoint's ``config``
    item): the class whose world trains the stored family (``"model_kind"``)."""
    if not isinstance(data, dict):
        raise ValueError(f"{where} must be a JSON object; got {type(data).__name__}")
    family = data.get("model_kind", data.get("family", TrainConfig().family))
    if not isinstance(family, str):
        raise ValueError(f"{where}: model_kind must be a string; got {family!r}")
    plugin = world(data["world"]) if "world" in data else world_of_family(family)
    if family not in plugin.families:
        raise ValueError(f"{where}: world {plugin.name!r} does not train {family!r} models")
    return config_from_dict(plugin.hook("config"), {k: v for k, v in data.items()
                                                    if k != "world"}, where)


def _fields_whose_role(cls: type, prop: str, value: bool) -> tuple[str, ...]:
    """The fields of the run config class ``cls`` whose role has ``prop`` equal to ``value``."""
    names = []
    for field in dataclasses.fields(cls):
        role = field.metadata.get("role")
        if role not in ROLES:
            raise TypeError(f"{cls.__name__}.{field.name} declares no role (one of "
                            f"{list(ROLES)})")
        if getattr(ROLES[role], prop) == value:
            names.append(field.name)
    return tuple(names)


def resumable_fields(cfg) -> tuple[str, ...]:
    """The fields of ``cfg``'s class that ``--resume`` may change; every other field would
    change the model, its parameters, its optimiser or its data, i.e. mix two runs in one
    directory."""
    return _fields_whose_role(type(cfg), "resumable", True)


RESUMABLE_FIELDS = _fields_whose_role(TrainConfig, "resumable", True)
""":func:`resumable_fields` of a :class:`TrainConfig`."""


def compile_key(cfg):
    """``cfg`` with the fields that the compiled functions do not depend on reset to their
    defaults: the key of the compile cache, so that runs differing only there compile once."""
    base = type(cfg)()
    return dataclasses.replace(cfg, **{name: getattr(base, name)
                                       for name in _fields_whose_role(type(cfg), "compiled",
                                                                      False)})


# --------------------------------------------------------------------------------------------
# Resource bounds


def check_run_resources(cfg: TrainConfig | HomesTrainConfig, devices: int = 1) -> None:
    """``ValueError`` naming the fields when a part of the run's resource estimate (its
    world's ``resources``, e.g. :func:`flowmaps_jax.worlds.flowsim.resource_estimate`), or all of it
    together, is over the memory or work budget (:func:`flowmaps_jax.resources.memory_limit`,
    :func:`~flowmaps_jax.resources.flops_limit`; environment variables FLOWMAPS_MAX_BYTES and
    FLOWMAPS_MAX_FLOPS raise them)."""
    parts = world(cfg.world).resources(cfg, devices)
    total = ("the run altogether (model, step, validation, data and diagnostics)",
             sum(p[1] for p in parts), 0)
    for what, num_bytes, flops in [*parts, total]:
        check_resources(what, num_bytes=num_bytes, flops=flops)


# --------------------------------------------------------------------------------------------
# Presets


def paper_preset() -> TrainConfig:
    """The paper's hyper-parameters (Argenziano et al. 2025, the FlowMaps model; README.md,
    "Citing")."""
    return TrainConfig(
        model=ModelConfig(dim=256, encoder_layers=8, cdit_blocks=8, heads=8, dropout=0.1),
        batch_size=256, queries_per_scene=1, steps=30_000, lr=1e-4, warmup_steps=0,
        b1=0.95, b2=0.999, weight_decay=0.01, clip_norm=None, ema_decay=0.9999,
        log_every=100, val_every=1000, ckpt_every=1000, preset="paper")


def cpu_preset() -> TrainConfig:
    """Default: the model a 2-core CPU trains in about 30 minutes, and that learns the routines.

    D = 128 with 4 + 4 layers (+ 2 CDiT blocks for the table weights), B = 64 scenes × Q = 8
    queries, 7,000 steps; the mixture read-out with self-attending, geometry-aware weight rows,
    endless data, Δτ conditioning, half the queries one step ahead, jittered targets, lr 1e-3,
    no dropout (why: docs/design.md; the measurements: docs/results.md).
    """
    return TrainConfig(
        model=ModelConfig(dim=128, encoder_layers=4, cdit_blocks=4, heads=4, dropout=0.0,
                          baseline_hidden=256, head="mixture", condition_on_dtau=True,
                          weight_blocks=2, weight_attention="self", weight_geometry="relative"),
        batch_size=64, queries_per_scene=8, steps=7000, lr=1e-3, warmup_steps=200,
        clip_norm=1.0, ema_decay=0.999, short_horizon_frac=0.5, short_horizon_max=1,
        target_noise=1.0, pointer_loss=1.0, data="endless", log_every=50, val_every=500,
        ckpt_every=500, preset="cpu")


def smoke_preset() -> TrainConfig:
    """A tiny model on a tiny dataset: trains in seconds (tests, CI)."""
    return TrainConfig(
        model=ModelConfig(dim=32, encoder_layers=1, cdit_blocks=1, heads=2, dropout=0.1,
                          freq_bands=8, baseline_hidden=32),
        batch_size=8, queries_per_scene=2, steps=20, lr=1e-3, warmup_steps=2,
        clip_norm=1.0, ema_decay=0.9, train_envs=64, val_envs=64, val_batches=2,
        log_every=5, val_every=10, ckpt_every=10, keep_last=2, preset="smoke")




def habits_preset() -> TrainConfig:
    """The pointer read-out with relative widths and its pointer loss on the preferences world,
    reading the last ``HABITS_HISTORY`` maps; fresh environments every chunk
    (``data="endless"``: a fixed split's hidden favourites can be memorised); 3,000 steps."""
    base = dataclasses.replace(
        cpu_preset(),
        model=ModelConfig(dim=128, encoder_layers=4, cdit_blocks=4, heads=4, dropout=0.0,
                          baseline_hidden=256, head="pointer", condition_on_dtau=True,
                          pointer_widths="relative", pointer_width_scale=10.0))
    sim = world_config("preferences", FlowSimConfig(
        max_tokens=FlowSimConfig().num_furniture + FlowSimConfig().num_objects * HABITS_HISTORY))
    return dataclasses.replace(
        base, flowsim=sim, model=dataclasses.replace(base.model, history=HABITS_HISTORY),
        steps=3000, short_horizon_frac=0.25, data="endless", preset="habits")


def homes_preset() -> HomesTrainConfig:
    """The shipped homes model's recipe: D = 64, 2 encoder layers, 2 weight block pairs, 2
    placement blocks; 32 homes × 8 queries per step, 10,000 steps."""
    return HomesTrainConfig(model=HomesModelConfig(), steps=10000)


def homes_rhythms_preset() -> HomesTrainConfig:
    """The homes recipe on homes of other rhythms: preference contexts 07–09, 09–17, 17–18 and
    18–07 h (``HomesConfig.day_phases``), not six-hour blocks: the rhythms must be learned."""
    base = homes_preset()
    return dataclasses.replace(base, preset="homes-rhythms", homes=dataclasses.replace(
        base.homes, day_phases=(7, 9, 17, 18)))


def homes_smoke_preset() -> HomesTrainConfig:
    """A tiny homes model on short homes: trains in seconds (tests)."""
    return HomesTrainConfig(
        model=HomesModelConfig(dim=16, encoder_layers=1, weight_blocks=1, cdit_blocks=1,
                               heads=2, mlp_ratio=2, freq_bands=4, history=24,
                               history_heads=2),
        homes=HomesConfig(regime="mixed", num_hours=96), batch_size=4, queries_per_scene=2,
        steps=6, warmup_steps=1, chunk_homes=8, chunk_steps=3, max_horizon=24, val_homes=8,
        val_batches=2, log_every=2, val_every=3, ckpt_every=3, preset="homes-smoke")


def with_world(cfg: TrainConfig, habits: str) -> TrainConfig:
    """``cfg`` on the FlowSim habit world ``habits`` (a ``flowsim.HABIT_WORLDS`` name; ValueError
    naming ``world`` otherwise): only ``flowsim.habits`` changes (``--set world=dynamic``)."""
    if not isinstance(cfg, TrainConfig):
        raise ValueError(f"world={habits!r}: --set world=... chooses a habit world of the 2-D "
                         f"FlowSim presets; preset {cfg.preset!r} trains on another world")
    return dataclasses.replace(cfg, flowsim=world_config(habits, cfg.flowsim))


def recorded_smoke_preset() -> RecordedTrainConfig:
    """A tiny homes model on a recorded dataset (``--preset smoke --data PATH``): trains in
    seconds on 3 environments x 72 hours."""
    smoke = homes_smoke_preset()
    return RecordedTrainConfig(
        model=dataclasses.replace(smoke.model, history_observed=True), batch_size=4,
        queries_per_scene=2, steps=6, warmup_steps=1, max_horizon=24,
        val_batches=2, log_every=2, val_every=3, ckpt_every=3, preset="recorded-smoke")


def recorded_homes_preset() -> RecordedTrainConfig:
    """The homes recipe on a recorded dataset (``--data PATH``, or ``--preset homes --data``):
    queries must say which hours were observed (``history_observed``)."""
    return RecordedTrainConfig(model=HomesModelConfig(history_observed=True), steps=10000)


RECORDED_PRESETS = {"smoke": recorded_smoke_preset, "homes-smoke": recorded_smoke_preset,
                    "homes": recorded_homes_preset}
"""The recipes ``--preset NAME --data PATH`` trains (default ``homes``)."""


def recorded_config(preset: str | None, data: str) -> RecordedTrainConfig:
    """The run config of ``--preset PRESET --data DATA``: the recipe ``RECORDED_PRESETS[preset]``
    with ``homes`` derived from the dataset (its vocabulary, sizes and hours,
    :func:`flowmaps_jax.worlds.recorded.homes_config_of`), ``model.history`` at most half its
    hours, ``max_horizon`` what fits after it, ``model.negative_evidence`` on when some
    environment has ``not_at`` and ``model.geometry`` off when one has no receptacle boxes.
    ValueError naming ``--preset`` or ``data``."""
    from flowmaps_jax.worlds.recorded import homes_config_of, load_data

    preset = preset or "homes"
    if preset not in RECORDED_PRESETS:
        raise ValueError(f"--preset {preset}: with --data the preset must be one of "
                         f"{sorted(RECORDED_PRESETS)}")
    base = RECORDED_PRESETS[preset]()
    base = dataclasses.replace(base, data=os.path.abspath(data))
    with prefix_errors("--data: "):
        recorded, digest = load_data(base.data)
        homes = homes_config_of(recorded)
    base = dataclasses.replace(base, data_digest=digest)
    history = min(base.model.history, max(1, homes.num_hours // 2))
    envs = recorded.environments
    model = dataclasses.replace(
        base.model, history=history,
        negative_evidence=any(e.not_at is not None for e in envs) or base.model.negative_evidence,
        geometry=all(e.receptacle_corners is not None for e in envs) and base.model.geometry)
    return dataclasses.replace(
        base, homes=homes, model=model,
        max_horizon=min(base.max_horizon, homes.num_hours - history))


FLOWSIM_PRESETS = {"paper": paper_preset, "cpu": cpu_preset, "smoke": smoke_preset,
                   "habits": habits_preset}
HOMES_PRESETS = {"homes": homes_preset, "homes-smoke": homes_smoke_preset,
                 "homes-rhythms": homes_rhythms_preset}
PRESETS = {**FLOWSIM_PRESETS, **HOMES_PRESETS}
DEFAULT_PRESET = "cpu"


def presets() -> dict:
    """The presets of every registered world whose data is generated (``--preset NAME``; with
    ``--data`` the files world's), by name: :data:`PRESETS` and those of worlds added since."""
    return {name: make for w in WORLDS.values() if not w.reads_files
            for name, make in w.hook("presets").items()}


def get_preset(name: str = DEFAULT_PRESET):
    """The preset ``name`` (of :func:`presets`) as a fresh run config."""
    table = presets()
    if name not in table:
        raise ValueError(f"preset must be one of {sorted(table)}; got {name!r}")
    return table[name]()


_UNPRINTED = ("flowsim.furniture_kinds", "flowsim.categories", "homes.room_types",
              "homes.receptacle_classes", "homes.object_classes")
"""The class tables of the worlds' configs, left out of the run's printed config."""
_RECORDED_PRINTED = ("homes.num_hours", "homes.max_tokens", "homes.max_vocabulary")
"""A recorded run prints only these of ``homes`` (the rest are FlowSim generator fields) and
none of the fields it does not read (``chunk_homes``, ``chunk_steps``, ``val_homes``)."""


def format_config(cfg: TrainConfig | HomesTrainConfig) -> str:
    """Human-readable multi-line dump of the resolved config (printed at the start of a run)."""
    flat = flatten(cfg.to_dict())
    if isinstance(cfg, RecordedTrainConfig):
        flat = {k: v for k, v in flat.items() if k in _RECORDED_PRINTED or not k.startswith(
            ("homes.", "chunk_homes", "chunk_steps", "val_homes"))}
    width = max(len(k) for k in flat)
    return "\n".join(f"  {k:<{width}} = {v}" for k, v in flat.items()
                     if not k.startswith(_UNPRINTED))
