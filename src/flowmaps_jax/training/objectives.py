"""Training objectives, and one registry entry per model kind.

A model kind bundles what every part of the pipeline needs to know about one family of models:
``init`` (fresh params), ``loss`` (the training objective), and the jitted inference cores
``sample``, ``sample_with_log_prob`` and ``log_prob`` (:mod:`flowmaps_jax.model.sampling`).
Training (:func:`objective_for`) and inference (:class:`flowmaps_jax.sample.Predictor`) look a kind
up in :data:`MODEL_KINDS`; adding a model is adding an entry, not an ``if kind ==`` branch.

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
from flowmaps_jax.model import baseline, sampling
from flowmaps_jax.model.config import ModelConfig
from flowmaps_jax.model.flowmaps import (
    encode,
    init_params,
    velocity,
    velocity_and_anchor_logits,
)
from flowmaps_jax.model.sampling import to_flow_space
from flowmaps_jax.tokens import FURNITURE, SceneTokens, TrainBatch, from_centre, to_centre

if TYPE_CHECKING:  # config.py imports this module's registry
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


def jitter_targets(key: jax.Array, boxes: jnp.ndarray, scale: float) -> jnp.ndarray:
    """Boxes (..., 4) moved by ``scale`` × the evaluation protocol's ground-truth std
    (``gt_mixture_sigma``): at scale 1, a draw from the smoothed q around each box."""
    from flowmaps_jax.evaluation.kl import gt_mixture_sigma

    centres = to_centre(boxes)
    noise = jax.random.normal(key, boxes.shape, boxes.dtype)
    return from_centre(centres + scale * gt_mixture_sigma(boxes) * noise)


def _flowmaps_loss(params, cfg: TrainConfig, batch: TrainBatch, key: jax.Array, train: bool):
    return cfm_loss(params, cfg.model, batch, key, cfg.t_sampler, deterministic=not train,
                    pointer_loss=cfg.pointer_loss)


def _mlp_loss(params, cfg: TrainConfig, batch: TrainBatch, key: jax.Array, train: bool):
    return baseline.baseline_loss(params, cfg.model, batch, key if train else None)


def _without_solver(fn):
    """A Gaussian core called with the flow's solver arguments, which it has no use for."""
    def call(params, config, tokens, queries, *args, num_steps=None, method=None):
        return fn(params, config, tokens, queries, *args)
    return call


@dataclasses.dataclass(frozen=True)
class ModelKind:
    """Everything the pipeline needs about one family of models (all pure functions).

    init(key, model_cfg) -> params.
    loss(params, train_cfg, batch, key, train) -> (scalar loss, aux dict).
    sample(params, model_cfg, tokens, queries, keys (B,), num_samples, *, num_steps, method)
        -> boxes (B, Q, N, 4); sample_with_log_prob the same plus log p (B, Q, N).
    log_prob(params, model_cfg, tokens, queries, x (B, Q, N, 4), *, num_steps, method)
        -> (B, Q, N).
    label(model_cfg) -> the row name in reports.
    """

    init: Callable
    loss: Callable
    sample: Callable
    sample_with_log_prob: Callable
    log_prob: Callable
    label: Callable[[ModelConfig], str]


MODEL_KINDS: dict[str, ModelKind] = {
    "flowmaps": ModelKind(
        init=init_params, loss=_flowmaps_loss, sample=sampling.flow_sample,
        sample_with_log_prob=sampling.flow_sample_with_log_prob,
        log_prob=sampling.flow_log_prob, label=lambda cfg: "FlowMaps"),
    "mlp": ModelKind(
        init=baseline.init_baseline, loss=_mlp_loss,
        sample=_without_solver(sampling.gaussian_sample),
        sample_with_log_prob=_without_solver(sampling.gaussian_sample_with_log_prob),
        log_prob=_without_solver(sampling.gaussian_log_prob),
        label=lambda cfg: f"MLP ({cfg.baseline_variance})"),
}


def model_kind(name: str) -> ModelKind:
    """The registry entry of a model kind, or ``ValueError`` listing the kinds."""
    if name not in MODEL_KINDS:
        raise ValueError(f"model kind must be one of {tuple(MODEL_KINDS)}; got {name!r}")
    return MODEL_KINDS[name]


@dataclasses.dataclass(frozen=True)
class Objective:
    """How to initialise and score one model kind.

    init(key) -> params.
    loss(params, batch, key, train) -> (loss, aux): scalar training loss and a dict of scalar
        diagnostics; ``train=False`` must be deterministic given ``key`` (no dropout).
    """

    init: Callable[[jax.Array], Params]
    loss: LossFn


def objective_for(cfg: TrainConfig) -> Objective:
    """The training objective of ``cfg.model_kind`` (its :data:`MODEL_KINDS` entry) bound to
    ``cfg``: FlowMaps' :func:`cfm_loss` or the MLP baseline's Gaussian negative log-likelihood."""
    kind = model_kind(cfg.model_kind)

    def init(key):
        return kind.init(key, cfg.model)

    def loss(params, batch, key, train):
        value, aux = kind.loss(params, cfg, batch, key, train)
        return value, _scalars(aux)

    return Objective(init=init, loss=loss)


def _scalars(aux: dict) -> dict:
    """The scalar diagnostics of a loss's aux dict (per-query arrays and ``loss`` dropped)."""
    return {k: v for k, v in aux.items() if k != "loss" and jnp.ndim(v) == 0}
