"""Training objectives: one loss per model family, registered in :data:`LOSSES`.

The model families themselves (init, inference cores, label) live in the model layer
(:data:`flowmaps_jax.model.MODEL_FAMILIES`); training adds only how each one is trained, under
the same name. :func:`objective_for` binds a run config's family and loss into an
:class:`Objective`; adding a model is a family module plus a loss entry here, not an
``if kind ==`` branch.

* ``"flowmaps"``: conditional flow matching on the linear path (:func:`cfm_loss`), with the
  optional pointer loss on the table the target stands on (:func:`supporting_token`).
* ``"mlp"``: the Gaussian baseline's negative log-likelihood
  (:func:`flowmaps_jax.model.baseline_loss`).

:func:`jitter_targets` smooths training targets with the evaluation protocol's σ.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp

from flowmaps_jax import flow
from flowmaps_jax.boxes import from_centre, to_centre
from flowmaps_jax.model import baseline, mixture
from flowmaps_jax.model.config import ModelConfig
from flowmaps_jax.model.families import model_family
from flowmaps_jax.model.flowmaps import (
    encode,
    object_table_logits,
    placement_velocity,
    select_horizon,
    velocity,
    velocity_and_anchor_logits,
)
from flowmaps_jax.model.inference import to_flow_space
from flowmaps_jax.tokens import FURNITURE, SceneTokens, TrainBatch

if TYPE_CHECKING:  # annotations only
    from flowmaps_jax.training.config import TrainConfig

Params = Any
# loss(params, batch, key, train) -> (scalar loss, dict of scalar diagnostics)
LossFn = Callable[[Params, TrainBatch, jax.Array, bool], tuple[jax.Array, dict]]


def supporting_token(tokens: SceneTokens, boxes: jnp.ndarray) -> jnp.ndarray:
    """Index (B, Q) of the furniture token whose centre is nearest each box's centre (B, Q, 4):
    the table an object box stands on. Normalised (y, x, h, w) boxes."""
    centre, token_centre = to_centre(boxes)[..., :2], to_centre(tokens.boxes)[..., :2]
    d = jnp.sum(jnp.square(centre[:, :, None] - token_centre[:, None]), -1)  # (B, Q, S)
    ok = (tokens.mask.astype(bool) & (tokens.kind == FURNITURE))[:, None, :]
    return jnp.argmin(jnp.where(ok, d, jnp.inf), axis=-1)


def cfm_loss(params, config: ModelConfig, batch: TrainBatch, key: jax.Array,
             t_sampler: str = "beta", deterministic: bool = False, pointer_loss: float = 0.0):
    """Conditional flow-matching loss on one batch; returns ``(loss, aux)``.

    The map of each of the B scenes is encoded once and shared by its Q queries. Per query:
    X_0 ~ N(0, I_4), t ~ ``t_sampler``, x_t on the linear path (B, Q, 1, 4), and the loss is the
    squared error to X_1 − X_0 averaged over the 4 numbers (X_1 is the target box in the flow's
    space, :func:`to_flow_space`), then over queries and scenes.
    ``deterministic=True`` turns dropout off (validation).
    ``pointer_loss`` > 0 (pointer head only; departs from the paper) adds that weight times the
    cross-entropy of the head's anchor logits against the table the target stands on
    (:func:`supporting_token`): direct supervision of *which* table, as a pointer probe gets.
    aux: ``{"loss": scalar, "mse_per_query": (B, Q)}`` (+ ``"pointer_ce"`` when used).
    """
    if t_sampler not in flow.T_SAMPLERS:
        raise ValueError(f"t_sampler must be one of {flow.T_SAMPLERS}; got {t_sampler!r}")
    noise_key, t_key, enc_key, vel_key = jax.random.split(key, 4)
    if deterministic:
        enc_key = vel_key = None
    x1 = to_flow_space(batch.target, config)  # (B, Q, 4)
    x0 = jax.random.normal(noise_key, x1.shape, x1.dtype)
    t = flow.sample_t(t_key, x1.shape[:2], t_sampler)  # (B, Q)
    x_t = flow.linear_path(x0, x1, t)[:, :, None, :]  # (B, Q, 1, 4)
    context = encode(params, config, batch.tokens, dropout_key=enc_key)
    extra = {}
    if pointer_loss > 0:
        v, logits = velocity_and_anchor_logits(params, config, context, x_t, t, batch.queries,
                                               dropout_key=vel_key)
        table = supporting_token(batch.tokens, batch.target)  # (B, Q)
        log_w = jax.nn.log_softmax(logits[:, :, 0], axis=-1)  # (B, Q, S)
        extra["pointer_ce"] = -jnp.mean(jnp.take_along_axis(log_w, table[..., None], axis=-1))
    else:
        v = velocity(params, config, context, x_t, t, batch.queries, dropout_key=vel_key)
    mse = jnp.mean(jnp.square(v[:, :, 0] - flow.target_velocity(x0, x1)), axis=-1)  # (B, Q)
    loss = jnp.mean(mse) + pointer_loss * extra.get("pointer_ce", 0.0)
    return loss, {"loss": loss, "mse_per_query": mse, **extra}


def mixture_loss(params, config: ModelConfig, batch: TrainBatch, key: jax.Array,
                 t_sampler: str = "beta", deterministic: bool = False, table_loss: float = 1.0,
                 num_objects: int = 3):
    """The mixture head's loss (``head="mixture"``); returns ``(loss, aux)``.

    ``table_loss`` × the cross-entropy of the table weights against the table the target stands
    on (:func:`supporting_token`), the proper scoring rule of π, plus the flow-matching loss of
    the placement flow on that table, in its local frame (:mod:`flowmaps_jax.model.mixture`).
    aux: ``loss``, ``mse_per_query`` (B, Q), ``table_ce`` and ``selection`` (= ``table_ce``: what
    the best checkpoint is chosen by). The table weights are computed once per (scene, object)
    for the scene's ``num_objects`` current objects (:func:`mixture.scene_objects`), at every
    horizon, and each query reads its object's row at its Δτ.
    """
    noise_key, t_key, enc_key, w_key, vel_key = jax.random.split(key, 5)
    if deterministic:
        enc_key = w_key = vel_key = None
    context = encode(params, config, batch.tokens, dropout_key=enc_key)
    table = supporting_token(batch.tokens, batch.target)  # (B, Q)
    objects = mixture.scene_objects(batch.tokens, num_objects)  # (B, M)
    logits = object_table_logits(params, config, context, objects, dropout_key=w_key)
    which = jnp.argmax(batch.queries.descriptor[:, :, None] == objects[:, None, :], axis=-1)
    logits = jnp.take_along_axis(logits, which[:, :, None, None], axis=1)  # (B, Q, S, T)
    dtau = jnp.clip(batch.queries.tau_q - batch.tokens.tau[:, None], 0, config.tau_max - 1)
    log_w = jax.nn.log_softmax(select_horizon(logits, dtau), axis=-1)
    ce = -jnp.mean(jnp.take_along_axis(log_w, table[..., None], axis=-1))
    means, scale, _ = mixture.placement_frame(context, batch.queries.descriptor)
    rows = table[:, :, None]  # (B, Q, 1)
    z1 = mixture.to_local(batch.target[:, :, None], mixture.gather_rows(means, rows), scale)
    z1 = z1[:, :, 0]  # (B, Q, 4)
    z0 = jax.random.normal(noise_key, z1.shape, z1.dtype)
    t = flow.sample_t(t_key, z1.shape[:2], t_sampler)
    z_t = flow.linear_path(z0, z1, t)[:, :, None, :]
    v = placement_velocity(params, config, context, z_t, t, batch.queries, rows,
                           dropout_key=vel_key)
    mse = jnp.mean(jnp.square(v[:, :, 0] - flow.target_velocity(z0, z1)), axis=-1)  # (B, Q)
    loss = jnp.mean(mse) + table_loss * ce
    return loss, {"loss": loss, "mse_per_query": mse, "table_ce": ce, "selection": ce}


def jitter_targets(key: jax.Array, boxes: jnp.ndarray, scale: float) -> jnp.ndarray:
    """Boxes (..., 4) moved by ``scale`` × the evaluation protocol's ground-truth std
    (``gt_mixture_sigma``): at scale 1, a draw from the smoothed q around each box."""
    from flowmaps_jax.evaluation.kl import gt_mixture_sigma

    centres = to_centre(boxes)
    noise = jax.random.normal(key, boxes.shape, boxes.dtype)
    return from_centre(centres + scale * gt_mixture_sigma(boxes) * noise)


def _flowmaps_loss(params, cfg: TrainConfig, batch: TrainBatch, key: jax.Array, train: bool):
    if cfg.model.head == "mixture":
        return mixture_loss(params, cfg.model, batch, key, cfg.t_sampler,
                            deterministic=not train, table_loss=cfg.pointer_loss,
                            num_objects=cfg.flowsim.num_objects)
    return cfm_loss(params, cfg.model, batch, key, cfg.t_sampler, deterministic=not train,
                    pointer_loss=cfg.pointer_loss)


def _mlp_loss(params, cfg: TrainConfig, batch: TrainBatch, key: jax.Array, train: bool):
    return baseline.baseline_loss(params, cfg.model, batch, key if train else None)


LOSSES: dict[str, Callable] = {
    "flowmaps": _flowmaps_loss,
    "mlp": _mlp_loss,
}
"""The training loss of each model family (:data:`flowmaps_jax.model.MODEL_FAMILIES`), by the
same name: ``loss(params, train_cfg, batch, key, train) -> (scalar loss, aux dict)``."""


@dataclasses.dataclass(frozen=True)
class Objective:
    """How to initialise and score one model family.

    init(key) -> params.
    loss(params, batch, key, train) -> (loss, aux): scalar training loss and a dict of scalar
        diagnostics; ``train=False`` must be deterministic given ``key`` (no dropout).
    """

    init: Callable[[jax.Array], Params]
    loss: LossFn


def objective_for(cfg: TrainConfig) -> Objective:
    """The training objective of the model family ``cfg.model_kind`` bound to ``cfg``: the
    family's init and its :data:`LOSSES` entry (FlowMaps' :func:`cfm_loss` or the MLP baseline's
    Gaussian negative log-likelihood)."""
    family = model_family(cfg.model_kind)
    family_loss = LOSSES[family.name]

    def init(key):
        return family.init(key, cfg.model)

    def loss(params, batch, key, train):
        value, aux = family_loss(params, cfg, batch, key, train)
        return value, _scalars(aux)

    return Objective(init=init, loss=loss)


def _scalars(aux: dict) -> dict:
    """The scalar diagnostics of a loss's aux dict (per-query arrays and ``loss`` dropped)."""
    return {k: v for k, v in aux.items() if k != "loss" and jnp.ndim(v) == 0}
