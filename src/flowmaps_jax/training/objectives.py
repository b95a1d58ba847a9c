"""Training objectives: a run config's model family bound into an :class:`Objective`.

Each model family brings its own loss (``ModelFamily.loss``, in the family's module under
:mod:`flowmaps_jax.model`: FlowMaps' :func:`~flowmaps_jax.model.flowmaps_family.flowmaps_loss`,
the MLP baseline's :func:`~flowmaps_jax.model.baseline.mlp_loss`); :func:`objective_for` binds it
with the family's init and the run's recipe (:class:`~flowmaps_jax.model.family.LossOptions`).
Adding a model is a family module, not an ``if family ==`` branch here.

:func:`jitter_targets` smooths training targets with the evaluation protocol's σ.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from flowmaps_jax.boxes import from_centre, to_centre
from flowmaps_jax.evaluation.kl import gt_mixture_sigma
from flowmaps_jax.model.families import model_family
from flowmaps_jax.model.family import LossOptions
from flowmaps_jax.tokens import TrainBatch
from flowmaps_jax.training.config import TrainConfig

Params = Any
# loss(params, batch, key, train) -> (scalar loss, dict of scalar diagnostics)
LossFn = Callable[[Params, TrainBatch, jax.Array, bool], tuple[jax.Array, dict]]


def jitter_targets(key: jax.Array, boxes: jnp.ndarray, scale: float) -> jnp.ndarray:
    """Boxes (..., 4) moved by ``scale`` × the evaluation protocol's ground-truth std
    (``gt_mixture_sigma``): at scale 1, a draw from the smoothed q around each box."""
    centres = to_centre(boxes)
    noise = jax.random.normal(key, boxes.shape, boxes.dtype)
    return from_centre(centres + scale * gt_mixture_sigma(boxes) * noise)


@dataclasses.dataclass(frozen=True)
class Objective:
    """How to initialise and score one model family.

    init(key) -> params.
    loss(params, batch, key, train) -> (loss, aux): scalar training loss and a dict of scalar
        diagnostics; ``train=False`` must be deterministic given ``key`` (no dropout).
    """

    init: Callable[[jax.Array], Params]
    loss: LossFn


def loss_options(cfg: TrainConfig) -> LossOptions:
    """The recipe fields of ``cfg`` that a family's loss reads."""
    return LossOptions(t_sampler=cfg.t_sampler, pointer_loss=cfg.pointer_loss,
                       num_objects=cfg.flowsim.num_objects)


def objective_for(cfg: TrainConfig) -> Objective:
    """The training objective of the model family ``cfg.family`` bound to ``cfg``: the family's
    init and its loss (``ModelFamily.loss``: FlowMaps' flow-matching loss or the MLP baseline's
    Gaussian negative log-likelihood) with the run's :func:`loss_options`."""
    family = model_family(cfg.family)
    options = loss_options(cfg)

    def init(key):
        return family.init(key, cfg.model)

    def loss(params, batch, key, train):
        value, aux = family.loss(params, cfg.model, batch, key, train, options)
        return value, _scalars(aux)

    return Objective(init=init, loss=loss)


def _scalars(aux: dict) -> dict:
    """The scalar diagnostics of a loss's aux dict (per-query arrays and ``loss`` dropped)."""
    return {k: v for k, v in aux.items() if k != "loss" and jnp.ndim(v) == 0}
