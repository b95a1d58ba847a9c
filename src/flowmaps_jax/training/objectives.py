"""Training objectives: a run config's world and model family bound into an :class:`Objective`
(each world brings it, ``World.objective``; :func:`objective_for` asks the run's world)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from flowmaps_jax.worlds import world

Params = Any
# loss(params, batch, key, train) -> (scalar loss, dict of scalar diagnostics)
LossFn = Callable[[Params, Any, jax.Array, bool], tuple[jax.Array, dict]]


@dataclasses.dataclass(frozen=True)
class Objective:
    """``init(key) -> params`` and ``loss(params, batch, key, train) -> (loss, aux)`` (a scalar
    and a dict of scalar diagnostics; ``train=False``: deterministic given ``key``)."""

    init: Callable[[jax.Array], Params]
    loss: LossFn


def objective_for(cfg) -> Objective:
    """The training objective of the run config ``cfg``: its world's
    (``World.objective(cfg)``), with the loss's per-query diagnostics dropped."""
    init, family_loss = world(cfg.world).objective(cfg)

    def loss(params, batch, key, train):
        value, aux = family_loss(params, batch, key, train)
        return value, _scalars(aux)

    return Objective(init=init, loss=loss)


def _scalars(aux: dict) -> dict:
    """The scalar diagnostics of a loss's aux dict (per-query arrays and ``loss`` dropped)."""
    return {k: v for k, v in aux.items() if k != "loss" and jnp.ndim(v) == 0}
