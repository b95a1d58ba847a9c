"""The model a stored run config describes: its family, sizes and simulator, and the check that
stored weights fit it. Read from a checkpoint's ``config`` item or a pretrained model's
``.json``; the training fields of the config are not read (no training code, no optax)."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping

import jax
import numpy as np

from flowmaps_jax.flowsim.config import FlowSimConfig
from flowmaps_jax.model import homes_family
from flowmaps_jax.model.config import ModelConfig
from flowmaps_jax.model.families import model_family
from flowmaps_jax.model.family import ModelFamily
from flowmaps_jax.store.integrity import leaf_name
from flowmaps_jax.validation import check_instance, check_int

DEFAULT_FAMILY = "flowmaps"
"""The family of a stored config without ``model_kind`` (``TrainConfig``'s default)."""
HOMES_FAMILY = homes_family.FAMILY_NAME
"""The homes model: its configs, model and simulator are read by
:func:`flowmaps_jax.model.homes_family.homes_spec`."""


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """The part of a stored run config that inference needs; made only for a model that fits
    its simulator (ValueError otherwise: the one home of that check, ``TrainConfig`` makes one
    too)."""

    family_name: str
    """The model family's name (``TrainConfig.family``, ``Predictor.family_name``; a run config
    stores it as ``"model_kind"``, a pretrained model's ``.json`` as ``"kind"``)."""
    model: ModelConfig
    flowsim: FlowSimConfig

    @property
    def family(self) -> ModelFamily:
        """The model family itself (:func:`flowmaps_jax.model.families.model_family`)."""
        return model_family(self.family_name)

    def __post_init__(self):
        check_instance("flowsim", self.flowsim, FlowSimConfig)
        check_instance("model", self.model, ModelConfig)
        # a model that fits its simulator: a time embedding for each of its timesteps ...
        if self.model.tau_max != self.flowsim.num_timesteps:
            raise ValueError(f"model.tau_max must be flowsim.num_timesteps = "
                             f"{self.flowsim.num_timesteps}; got {self.model.tau_max}")
        # ... and descriptor ids for all the simulator's descriptors
        check_int("model.num_descriptors", self.model.num_descriptors,
                  self.flowsim.num_descriptors)

    def abstract_params(self):
        """Structure, shapes and dtypes of the params this model initialises (nothing
        computed)."""
        return jax.eval_shape(lambda key: self.family.init(key, self.model), jax.random.key(0))


def model_spec(config: dict) -> ModelSpec:
    """The model family, model sizes and simulator of a stored run config (a checkpoint's
    ``config`` item or a pretrained model's ``.json`` ``config``; ``TrainConfig.to_dict()``).
    Checks them, and that the model fits the simulator; the training fields are not read.
    Raises ``ValueError`` naming what is wrong; ``config`` is a dict (its callers' checks:
    a checkpoint's config item, a pretrained model's checked ``.json``)."""
    family_name = config.get("model_kind", DEFAULT_FAMILY)  # the key run configs store it under
    if family_name in SPEC_READERS:  # a family with its own reader (same shape: family_name,
        return SPEC_READERS[family_name](config)  # model, abstract_params())
    model_family(family_name)  # ValueError listing the families
    model = ModelConfig.from_dict(config["model"]) if "model" in config else ModelConfig()
    flowsim = FlowSimConfig.from_dict(config["flowsim"]) if "flowsim" in config \
        else FlowSimConfig()
    return ModelSpec(family_name=family_name, model=model, flowsim=flowsim)


SPEC_READERS = {HOMES_FAMILY: homes_family.homes_spec}
"""The families whose stored configs another world's spec describes (the homes network's
model and :class:`~flowmaps_jax.flowsim.homes.HomesConfig`), by family name; the 2-D families
are read into a :class:`ModelSpec`."""


def _leaves(tree) -> dict:
    return {leaf_name(path): (tuple(np.shape(leaf)), np.dtype(getattr(leaf, "dtype", object)))
            for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]}


@functools.lru_cache(maxsize=16)
def _initialised(spec) -> dict:
    return _leaves(spec.abstract_params())


def check_params(params, spec: ModelSpec, where: str) -> None:
    """``ValueError`` unless ``params`` has the leaves (paths, shapes and dtypes) that
    ``spec``'s family initialises (weights that do not fit their config), naming the first
    leaf that differs."""
    check_instance(where, params, Mapping)
    got, want = _leaves(params), _initialised(spec)
    if got != want:
        key = next(k for k in sorted(got.keys() | want.keys()) if got.get(k) != want.get(k))
        def what(leaf):
            return "absent" if leaf is None else f"{leaf[0]} {leaf[1]}"
        raise ValueError(f"{where}: parameter {key} is {what(got.get(key))}; the "
                         f"{spec.family_name!r} model its config describes has "
                         f"{what(want.get(key))}")
