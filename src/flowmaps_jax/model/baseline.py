"""MLP-Gaussian baseline: the same Map Encoder, masked mean pool, MLP head → a Gaussian box.

Head input per query: [pooled map (D), Embed(descriptor), Embed(τ), Embed(τ_q)] → MLP → mean (4)
(+ log-variance (4) for ``baseline_variance="learned"``; ``"mean"``: unit variance).
"""

from __future__ import annotations

import functools
import math

import flax.linen as nn
import jax
import jax.numpy as jnp

from flowmaps_jax.model.config import ModelConfig
from flowmaps_jax.model.embeddings import FlatDense
from flowmaps_jax.model.encoder import MapEncoder, example_inputs
from flowmaps_jax.model.family import LossOptions, ModelFamily, scene_noise, without_solver
from flowmaps_jax.tokens import Queries, SceneTokens, TrainBatch

LOG_VAR_RANGE = (-12.0, 4.0)  # keeps the learned variance away from 0 and from blowing up


class BaselineMLP(nn.Module):
    """SceneTokens (B, S), Queries (B, Q) → mean (B, Q, 4), log_var (B, Q, 4)."""

    config: ModelConfig

    @nn.compact
    def __call__(self, tokens: SceneTokens, queries: Queries, deterministic: bool = True):
        cfg = self.config
        context = MapEncoder(cfg, name="encoder")(tokens, deterministic)  # zero on padding
        mask = tokens.mask.astype(context.dtype)
        pooled = context.sum(1) / jnp.maximum(mask.sum(1, keepdims=True), 1.0)  # (B, D)
        q = queries.descriptor.shape[1]
        features = jnp.concatenate([
            jnp.broadcast_to(pooled[:, None], (pooled.shape[0], q, cfg.dim)),
            nn.Embed(cfg.num_descriptors, cfg.dim, name="descriptor_embed")(queries.descriptor),
            jnp.broadcast_to(nn.Embed(cfg.tau_max, cfg.dim, name="tau_embed")(tokens.tau)[:, None],
                             (pooled.shape[0], q, cfg.dim)),
            nn.Embed(cfg.tau_max, cfg.dim, name="tau_q_embed")(queries.tau_q),
        ], axis=-1)
        h = features
        for i in range(2):
            h = nn.gelu(FlatDense(cfg.baseline_hidden, precision=cfg.precision,
                                  name=f"hidden_{i}")(h))
            h = nn.Dropout(cfg.dropout)(h, deterministic=deterministic)
        mean = FlatDense(4, precision=cfg.precision, name="mean")(h)
        if cfg.baseline_variance == "mean":
            return mean, jnp.zeros_like(mean)
        log_var = FlatDense(4, kernel_init=nn.initializers.zeros_init(), precision=cfg.precision,
                            name="log_var")(h)
        return mean, jnp.clip(log_var, *LOG_VAR_RANGE)


@functools.partial(jax.jit, static_argnames="config")
def init_baseline(key: jax.Array, config: ModelConfig):
    """Fresh baseline parameters for ``config`` (variant from ``config.baseline_variance``)."""
    return BaselineMLP(config).init(key, *example_inputs())["params"]


@functools.partial(jax.jit, static_argnames="config")
def baseline_predict(params, config: ModelConfig, tokens: SceneTokens, queries: Queries, *,
                     dropout_key=None):
    """Gaussian over each query's box: mean (B, Q, 4), log_var (B, Q, 4) (zeros for "mean")."""
    rngs = {} if dropout_key is None else {"dropout": dropout_key}
    return BaselineMLP(config).apply({"params": params}, tokens, queries, dropout_key is None,
                                     rngs=rngs)


def baseline_log_prob(mean: jnp.ndarray, log_var: jnp.ndarray, x: jnp.ndarray) -> jnp.ndarray:
    """Diagonal-Gaussian log-density of boxes x. mean, log_var (..., 4); x (..., 4) → (...)."""
    squared = jnp.square(x - mean) * jnp.exp(-log_var)
    return -0.5 * jnp.sum(squared + log_var + math.log(2 * math.pi), axis=-1)


def baseline_loss(params, config: ModelConfig, batch: TrainBatch, key: jax.Array | None = None):
    """Mean Gaussian NLL of the target boxes ``(loss, aux {"loss", "mse"})``; ``key`` drives
    dropout (None: deterministic)."""
    mean, log_var = baseline_predict(params, config, batch.tokens, batch.queries, dropout_key=key)
    loss = -jnp.mean(baseline_log_prob(mean, log_var, batch.target))
    mse = jnp.mean(jnp.square(mean - batch.target))
    return loss, {"loss": loss, "mse": mse}


def mlp_loss(params, config: ModelConfig, batch: TrainBatch, key: jax.Array, train: bool,
             options: LossOptions):
    """The baseline's training loss ``(loss, aux)`` (``ModelFamily.loss``): :func:`baseline_loss`
    with dropout from ``key`` when ``train``, none otherwise; ``options`` are not used."""
    return baseline_loss(params, config, batch, key if train else None)


# --------------------------------------------------------------------------- inference cores


def _gaussian_draw(params, config: ModelConfig, tokens: SceneTokens, queries: Queries,
                   keys: jax.Array, num_samples: int, with_log_prob: bool = False):
    """mean + exp(log_var / 2) · ε per query, ε from keys (B,); with its log-density if asked."""
    mean, log_var = baseline_predict(params, config, tokens, queries)
    eps = scene_noise(keys, (mean.shape[1], num_samples, 4))
    x = mean[:, :, None] + jnp.exp(0.5 * log_var)[:, :, None] * eps
    if not with_log_prob:
        return x
    return x, baseline_log_prob(mean[:, :, None], log_var[:, :, None], x)


@functools.partial(jax.jit, static_argnames=("config", "num_samples"))
def gaussian_sample(params, config: ModelConfig, tokens: SceneTokens, queries: Queries,
                    keys: jax.Array, num_samples: int) -> jnp.ndarray:
    """MLP-baseline samples (B, Q, N, 4): mean + exp(log_var / 2) · ε, ε from keys (B,)."""
    return _gaussian_draw(params, config, tokens, queries, keys, num_samples)


@functools.partial(jax.jit, static_argnames=("config",))
def gaussian_log_prob(params, config: ModelConfig, tokens: SceneTokens, queries: Queries,
                      x: jnp.ndarray) -> jnp.ndarray:
    """Closed-form diagonal-Gaussian log-density (B, Q, N) of x (B, Q, N, 4) under the baseline."""
    mean, log_var = baseline_predict(params, config, tokens, queries)
    return baseline_log_prob(mean[:, :, None], log_var[:, :, None], x)


@functools.partial(jax.jit, static_argnames=("config", "num_samples"))
def gaussian_sample_with_log_prob(params, config: ModelConfig, tokens: SceneTokens,
                                  queries: Queries, keys: jax.Array, num_samples: int
                                  ) -> tuple[jnp.ndarray, jnp.ndarray]:
    """MLP-baseline samples (B, Q, N, 4) and their closed-form log-density (B, Q, N)."""
    return _gaussian_draw(params, config, tokens, queries, keys, num_samples, with_log_prob=True)


FAMILY = ModelFamily(
    name="mlp", init=init_baseline, loss=mlp_loss, sample=without_solver(gaussian_sample),
    sample_with_log_prob=without_solver(gaussian_sample_with_log_prob),
    log_prob=without_solver(gaussian_log_prob),
    label=lambda config: f"MLP ({config.baseline_variance})",
    row_bytes=lambda config: 64, uses_solver=False, gaussian=baseline_predict)
"""The MLP-Gaussian baseline: one closed-form Gaussian per query, no ODE."""
