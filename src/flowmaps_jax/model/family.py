"""What a model family gives the pipeline (:class:`ModelFamily`, registered by
:mod:`flowmaps_jax.model.families`), and helpers its cores share. The cores are unvalidated,
jitted pure functions of canonical inputs (:func:`canonical_inputs`): tokens (B, S), queries
(B, Q), keys (B,), boxes (B, Q, N, 4) normalised (y, x, h, w), log-densities (B, Q, N).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.model.config import ModelConfig
from flowmaps_jax.tokens import Queries, SceneTokens, trim_padding

DENSITY_FACTOR = 5
"""A log-density (the exact divergence: 4 JVPs) needs about this many times a sample's memory."""


def _never(config: ModelConfig) -> bool:
    return False


class LossOptions(NamedTuple):
    """The recipe's knobs a family's loss reads: t_sampler (``flow.T_SAMPLERS``), pointer_loss
    (weight of the table-weight cross-entropy), num_objects (the scene's current objects)."""

    t_sampler: str = "beta"
    pointer_loss: float = 0.0
    num_objects: int = 3


@dataclasses.dataclass(frozen=True)
class ModelFamily:
    """One family of models, as the pipeline sees it (all pure functions).

    name: the registry key, also ``TrainConfig.family`` and ``Predictor.family_name`` (stored on
        disk as a config's ``"model_kind"`` and a meta's ``"kind"``).
    init(key, model_cfg) -> params.
    loss(params, model_cfg, batch: TrainBatch, key, train: bool, options: LossOptions)
        -> (scalar loss, aux dict); ``train=False`` is deterministic given ``key`` (no dropout).
    sample(params, model_cfg, tokens, queries, keys (B,), num_samples, *, num_steps, method)
        -> boxes (B, Q, N, 4); sample_with_log_prob the same plus log p (B, Q, N).
    log_prob(params, model_cfg, tokens, queries, x (B, Q, N, 4), *, num_steps, method)
        -> (B, Q, N).
    label(model_cfg) -> the row name in reports.
    row_bytes(model_cfg) -> working memory of one sampled box.
    uses_solver: whether ``num_steps`` / ``method`` matter (else ignored, :func:`without_solver`).
    table_weights(params, model_cfg, tokens, queries) -> (B, Q, S) mixture weight per token,
        read without sampling, for the configs where ``has_table_weights(model_cfg)``.
    gaussian(params, model_cfg, tokens, queries) -> (mean, log_var) (B, Q, 4) each, for a
        family whose prediction is one Gaussian per query (None otherwise).
    """

    name: str
    init: Callable
    loss: Callable
    sample: Callable
    sample_with_log_prob: Callable
    log_prob: Callable
    label: Callable[[ModelConfig], str]
    row_bytes: Callable[[ModelConfig], int]
    uses_solver: bool = True
    table_weights: Callable | None = None
    has_table_weights: Callable[[ModelConfig], bool] = _never
    gaussian: Callable | None = None

    def request_bytes(self, config: ModelConfig, boxes: int, with_density: bool) -> int:
        """Working memory of sampling (or, ``with_density``, scoring) ``boxes`` boxes at once."""
        return boxes * self.row_bytes(config) * (DENSITY_FACTOR if with_density else 1)


def without_solver(core: Callable) -> Callable:
    """A core without an ODE (closed form), callable with the solver's keyword arguments
    ``num_steps`` and ``method``, which it ignores: the signature :class:`ModelFamily` asks."""
    def call(params, config, tokens, queries, *args, num_steps=None, method=None):
        return core(params, config, tokens, queries, *args)
    return call


def scene_noise(keys: jax.Array, shape: tuple[int, ...]) -> jnp.ndarray:
    """Standard normal (B, *shape) float32, scene b's draws from keys[b]."""
    return jax.vmap(lambda k: jax.random.normal(k, shape, jnp.float32))(keys)


def canonical_inputs(tokens: SceneTokens, queries: Queries) -> tuple[SceneTokens, Queries]:
    """Tokens and queries as the cores take them (concrete): canonical dtypes, and without the
    token slots after the last real token of every scene (results identical)."""
    used = np.flatnonzero(np.asarray(tokens.mask).reshape(-1, np.shape(tokens.mask)[-1]).any(0))
    tokens = trim_padding(tokens, int(used[-1]) + 1)
    tokens = SceneTokens(boxes=jnp.asarray(tokens.boxes, jnp.float32),
                         descriptor=jnp.asarray(tokens.descriptor, jnp.int32),
                         kind=jnp.asarray(tokens.kind, jnp.int32),
                         mask=jnp.asarray(tokens.mask, bool),
                         tau=jnp.asarray(tokens.tau, jnp.int32),
                         age=None if tokens.age is None else jnp.asarray(tokens.age, jnp.int32))
    queries = Queries(descriptor=jnp.asarray(queries.descriptor, jnp.int32),
                      tau_q=jnp.asarray(queries.tau_q, jnp.int32))
    return tokens, queries
