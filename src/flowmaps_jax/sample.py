"""Inference API: load a trained model and draw box samples or exact log-likelihoods.

    predictor = load("runs/flowmaps-cpu-.../checkpoints")          # FlowMaps or MLP baseline
    boxes = predictor.sample(tokens, queries, num_samples=25, key=jax.random.key(0))
    log_p = predictor.log_prob(tokens, queries, boxes)               # (B, Q, 25)

Shapes: ``tokens`` is a :class:`~flowmaps_jax.tokens.SceneTokens` with leading dim (B,), ``queries``
a :class:`~flowmaps_jax.tokens.Queries` with dims (B, Q). Boxes are normalised ``(y, x, h, w)``;
``pixels=True`` returns pixel corners ``(y0, x0, y1, x1)`` instead.

How it runs. Inputs are validated on the host (clear ``ValueError`` naming the argument), then one
``jax.jit``-compiled function does the work:

* FlowMaps: the map of every scene is encoded **once**; X_0 ~ N(0, I_4) of shape (B, Q, N, 4) is
  integrated from t = 0 to 1 by :func:`flowmaps_jax.flow.integrate` (a ``lax.scan`` over the time
  grid). The N samples of a query are N rows of one velocity call, so they share the query's
  context and, at every step, its conditioning. ``log_prob`` integrates the augmented ODE backwards
  with the exact 4-D divergence (:func:`flowmaps_jax.flow.log_prob`).
* MLP baseline: one forward pass gives a diagonal Gaussian per query; samples are
  ``mean + std · ε`` and the log-density is closed form.

Random numbers: the samples of scene b come from ``split(key, B)[b]`` (or from ``key[b]`` when a
batch of B keys is passed), so a scene's samples do not depend on which other scenes share the
batch when per-scene keys are given.
"""

from __future__ import annotations

import dataclasses
import functools
import pathlib
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax import flow
from flowmaps_jax.flowsim.config import FlowSimConfig
from flowmaps_jax.flowsim.scenes import denormalise_boxes
from flowmaps_jax.model import (
    ModelConfig,
    baseline_log_prob,
    baseline_predict,
    check_inputs,
    encode,
    make_velocity_fn,
)
from flowmaps_jax.tokens import Queries, SceneTokens, trim_padding
from flowmaps_jax.validation import check_int

MODEL_KINDS = ("flowmaps", "mlp")
SOLVERS = flow.SOLVERS
DEFAULT_NUM_STEPS = 10
"""ODE grid points (the reference's ``linspace(0, 1, 10)``): 18 midpoint evaluations."""
WHICH = ("best", "latest")


# --------------------------------------------------------------------------- jitted cores


def _noise(keys: jax.Array, shape: tuple[int, ...]) -> jnp.ndarray:
    """Standard normal (B, *shape) with scene b drawn from keys[b]."""
    return jax.vmap(lambda k: jax.random.normal(k, shape, jnp.float32))(keys)


@functools.partial(jax.jit, static_argnames=("config", "num_samples", "num_steps", "method"))
def flow_sample(params, config: ModelConfig, tokens: SceneTokens, queries: Queries,
                keys: jax.Array, num_samples: int, num_steps: int = DEFAULT_NUM_STEPS,
                method: str = "midpoint") -> jnp.ndarray:
    """FlowMaps samples (B, Q, N, 4) normalised (y, x, h, w); keys (B,) one PRNG key per scene.

    Encodes the B maps once, then integrates all B·Q·N noise rows together (``lax.scan`` over the
    num_steps − 1 intervals). No validation: use :meth:`Predictor.sample`.
    """
    q = queries.tau_q.shape[1]
    context = encode(params, config, tokens)
    x0 = _noise(keys, (q, num_samples, 4))
    velocity_fn = make_velocity_fn(params, config, context, queries)
    return flow.from_flow_space(flow.integrate(velocity_fn, x0, num_steps, method), config)


@functools.partial(jax.jit, static_argnames=("config", "num_steps", "method"))
def flow_log_prob(params, config: ModelConfig, tokens: SceneTokens, queries: Queries,
                  x: jnp.ndarray, num_steps: int = DEFAULT_NUM_STEPS,
                  method: str = "midpoint") -> jnp.ndarray:
    """Exact log-density (B, Q, N) of boxes x (B, Q, N, 4) under FlowMaps (change of variables).

    Encodes the maps once; the backward ODE for all rows runs in one ``lax.scan`` in the flow's
    space (``ModelConfig.box_scale``/``box_offset``), plus that map's constant log-Jacobian.
    """
    context = encode(params, config, tokens)
    velocity_fn = make_velocity_fn(params, config, context, queries)
    z = flow.to_flow_space(x, config)
    return flow.log_prob(velocity_fn, z, num_steps, method) + flow.flow_space_log_det(config)


@functools.partial(jax.jit, static_argnames=("config", "num_samples"))
def gaussian_sample(params, config: ModelConfig, tokens: SceneTokens, queries: Queries,
                    keys: jax.Array, num_samples: int) -> jnp.ndarray:
    """MLP-baseline samples (B, Q, N, 4): mean + exp(log_var / 2) · ε, ε from keys (B,)."""
    mean, log_var = baseline_predict(params, config, tokens, queries)
    eps = _noise(keys, (mean.shape[1], num_samples, 4))
    return mean[:, :, None] + jnp.exp(0.5 * log_var)[:, :, None] * eps


@functools.partial(jax.jit, static_argnames=("config",))
def gaussian_log_prob(params, config: ModelConfig, tokens: SceneTokens, queries: Queries,
                      x: jnp.ndarray) -> jnp.ndarray:
    """Closed-form diagonal-Gaussian log-density (B, Q, N) of x (B, Q, N, 4) under the baseline."""
    mean, log_var = baseline_predict(params, config, tokens, queries)
    return baseline_log_prob(mean[:, :, None], log_var[:, :, None], x)


# --------------------------------------------------------------------------- validation helpers


def _scene_keys(key: Any, num_scenes: int) -> jax.Array:
    """One typed PRNG key per scene from a single key (split) or a batch of B keys (as given).

    Raw uint32 keys (``jax.random.PRNGKey``) are wrapped, so both kinds share compiled code.
    """
    if not (isinstance(key, jax.Array) and jnp.issubdtype(key.dtype, jax.dtypes.prng_key)):
        arr = np.asarray(key)
        if arr.dtype != np.uint32 or arr.ndim not in (1, 2) or arr.shape[-1] != 2:
            raise ValueError("key must be a JAX PRNG key (jax.random.key(seed) or "
                             "jax.random.PRNGKey(seed)), or a batch of one key per scene; got "
                             f"{type(key).__name__} with shape {arr.shape} and dtype {arr.dtype}")
        key = jax.random.wrap_key_data(jnp.asarray(arr))
    if key.shape == ():
        return jax.random.split(key, num_scenes)
    if key.shape != (num_scenes,):
        raise ValueError(f"key must be one PRNG key or one per scene (shape ({num_scenes},)); "
                         f"got shape {key.shape}")
    return key


def _as_arrays(tokens: SceneTokens, queries: Queries) -> tuple[SceneTokens, Queries]:
    """Canonical dtypes, so every call with the same shapes hits one compiled function.

    Token slots after the last real token of every scene are dropped (``tokens.trim_padding``):
    padding is masked anyway, so results are identical and the encoder and cross-attention skip
    empty slots (FlowSim maps have 13 real tokens of the 20 slots).
    """
    used = np.flatnonzero(np.asarray(tokens.mask).reshape(-1, np.shape(tokens.mask)[-1]).any(0))
    tokens = trim_padding(tokens, int(used[-1]) + 1)
    tokens = SceneTokens(boxes=jnp.asarray(tokens.boxes, jnp.float32),
                         descriptor=jnp.asarray(tokens.descriptor, jnp.int32),
                         kind=jnp.asarray(tokens.kind, jnp.int32),
                         mask=jnp.asarray(tokens.mask, bool),
                         tau=jnp.asarray(tokens.tau, jnp.int32))
    queries = Queries(descriptor=jnp.asarray(queries.descriptor, jnp.int32),
                      tau_q=jnp.asarray(queries.tau_q, jnp.int32))
    return tokens, queries


# --------------------------------------------------------------------------- the predictor


@dataclasses.dataclass(frozen=True)
class Predictor:
    """A trained (or freshly initialised) FlowMaps or MLP-baseline model, ready for inference.

    params: the model's parameter pytree (EMA weights when loaded with ``use_ema=True``).
    model: its :class:`~flowmaps_jax.model.ModelConfig` (static: defines the compiled functions).
    kind: "flowmaps" (flow matching) or "mlp" (Gaussian baseline; variant in
        ``model.baseline_variance``).
    flowsim: the simulator config the model was trained on (map size for pixel boxes).
    source: where the params came from (checkpoint path) and step, for reports.
    """

    params: Any
    model: ModelConfig
    kind: str = "flowmaps"
    flowsim: FlowSimConfig = dataclasses.field(default_factory=FlowSimConfig)
    source: str | None = None
    step: int | None = None

    def __post_init__(self):
        if self.kind not in MODEL_KINDS:
            raise ValueError(f"kind must be one of {MODEL_KINDS}; got {self.kind!r}")
        if not isinstance(self.model, ModelConfig):
            raise ValueError(f"model must be a ModelConfig; got {type(self.model).__name__}")
        if not isinstance(self.flowsim, FlowSimConfig):
            raise ValueError(f"flowsim must be a FlowSimConfig; got {type(self.flowsim).__name__}")

    @classmethod
    def from_params(cls, params, model: ModelConfig, kind: str = "flowmaps",
                    flowsim: FlowSimConfig | None = None, **info) -> Predictor:
        """Wrap params you already have (tests, notebooks, a training loop) without a checkpoint.

        Example: ``Predictor.from_params(model.init_params(key, cfg), cfg)``.
        """
        return cls(params=params, model=model, kind=kind,
                   flowsim=FlowSimConfig() if flowsim is None else flowsim, **info)

    @property
    def name(self) -> str:
        """Row label for reports: "FlowMaps", "MLP (mean)" or "MLP (learned)"."""
        if self.kind == "flowmaps":
            return "FlowMaps"
        return f"MLP ({self.model.baseline_variance})"

    # ----------------------------------------------------------------------- validation

    def validate(self, tokens: SceneTokens, queries: Queries) -> tuple[int, int]:
        """Check tokens (B, S) and queries (B, Q) for this model; returns (B, Q).

        Raises ``ValueError`` for wrong shapes, boxes outside [0, 1], unknown descriptors,
        more than ``model.max_tokens`` tokens, τ out of range or τ_q ≤ τ.
        """
        if not isinstance(tokens, SceneTokens):
            raise ValueError(f"tokens must be a SceneTokens; got {type(tokens).__name__}")
        if not isinstance(queries, Queries):
            raise ValueError(f"queries must be a Queries; got {type(queries).__name__}")
        if np.ndim(tokens.boxes) != 3:
            raise ValueError(f"tokens.boxes must have shape (B, S, 4); got "
                             f"{np.shape(tokens.boxes)}")
        if np.ndim(queries.descriptor) != 2:
            raise ValueError(f"queries.descriptor must have shape (B, Q); got "
                             f"{np.shape(queries.descriptor)}")
        check_inputs(self.model, tokens, queries)
        b, q = np.shape(queries.descriptor)
        if b < 1 or q < 1:
            raise ValueError(f"tokens/queries must hold at least one scene and one query; got "
                             f"B={b}, Q={q}")
        return b, q

    def _check_x(self, x, b: int, q: int) -> jnp.ndarray:
        shape = np.shape(x)
        if len(shape) != 4 or shape[:2] != (b, q) or shape[-1] != 4:
            raise ValueError(f"x must have shape (B={b}, Q={q}, N, 4) of normalised (y, x, h, w) "
                             f"boxes; got {shape}")
        if shape[2] < 1:
            raise ValueError("x must hold at least one box per query (N >= 1)")
        x = jnp.asarray(x, jnp.float32)
        if not bool(jnp.all(jnp.isfinite(x))):
            raise ValueError("x contains NaN or inf")
        return x

    # ----------------------------------------------------------------------- inference

    def sample(self, tokens: SceneTokens, queries: Queries, num_samples: int, key,
               num_steps: int = DEFAULT_NUM_STEPS, method: str = "midpoint",
               pixels: bool = False) -> jnp.ndarray:
        """Draw num_samples boxes per query → (B, Q, num_samples, 4).

        Normalised (y, x, h, w) by default; ``pixels=True`` gives pixel corners (y0, x0, y1, x1).
        key: one PRNG key (split over the B scenes) or one key per scene (B,). The solver
        (``num_steps`` grid points, ``method`` "midpoint" or "euler") is ignored by the MLP.
        Same key and inputs → the same samples.
        """
        b, _ = self.validate(tokens, queries)
        num_samples = check_int("num_samples", num_samples)
        num_steps, method = flow.check_solver(num_steps, method)
        keys = _scene_keys(key, b)
        tokens, queries = _as_arrays(tokens, queries)
        if self.kind == "flowmaps":
            boxes = flow_sample(self.params, self.model, tokens, queries, keys, num_samples,
                                num_steps, method)
        else:
            boxes = gaussian_sample(self.params, self.model, tokens, queries, keys, num_samples)
        return denormalise_boxes(boxes, self.flowsim) if pixels else boxes

    def log_prob(self, tokens: SceneTokens, queries: Queries, x,
                 num_steps: int = DEFAULT_NUM_STEPS, method: str = "midpoint") -> jnp.ndarray:
        """Exact log-density (B, Q, N) of normalised boxes x (B, Q, N, 4) (y, x, h, w).

        FlowMaps: instantaneous change of variables with the exact divergence, integrated back
        from t = 1 to 0 on ``num_steps`` grid points (the only error is the ODE discretisation).
        MLP: the closed-form diagonal Gaussian.
        """
        b, q = self.validate(tokens, queries)
        num_steps, method = flow.check_solver(num_steps, method)
        x = self._check_x(x, b, q)
        tokens, queries = _as_arrays(tokens, queries)
        if self.kind == "flowmaps":
            return flow_log_prob(self.params, self.model, tokens, queries, x, num_steps, method)
        return gaussian_log_prob(self.params, self.model, tokens, queries, x)

    def gaussian(self, tokens: SceneTokens, queries: Queries) -> tuple[jnp.ndarray, jnp.ndarray]:
        """MLP baseline only: (mean, log_var), each (B, Q, 4), of the predicted Gaussian."""
        if self.kind != "mlp":
            raise ValueError("gaussian() is only defined for the MLP baseline (kind='mlp')")
        self.validate(tokens, queries)
        tokens, queries = _as_arrays(tokens, queries)
        return baseline_predict(self.params, self.model, tokens, queries)


# --------------------------------------------------------------------------- loading


def load(checkpoint_dir: str | pathlib.Path, which: str = "best",
         use_ema: bool = True) -> Predictor:
    """Load a trained model from a checkpoint directory (or a run directory holding one).

    which: "best" (lowest validation loss; falls back to the latest save when no validation
    has run yet) or "latest". use_ema: the EMA weights (default) or the raw training weights.
    The model kind (FlowMaps or MLP baseline) and sizes come from the config saved with the
    checkpoint. Raises ``ValueError`` for a missing, empty or corrupt directory.
    """
    from flowmaps_jax import checkpoint

    if which not in WHICH:
        raise ValueError(f"which must be one of {WHICH}; got {which!r}")
    if not isinstance(use_ema, bool):
        raise ValueError(f"use_ema must be True or False; got {use_ema!r}")
    root = checkpoint.resolve_checkpoint_dir(checkpoint_dir)
    store_which = checkpoint.BEST if which == "best" else checkpoint.LAST
    params, cfg = checkpoint.load_for_inference(root, which=store_which, ema=use_ema)
    step = _checkpoint_step(root, store_which)
    return Predictor(params=params, model=cfg.model, kind=cfg.model_kind, flowsim=cfg.flowsim,
                     source=str(root), step=step)


def _checkpoint_step(root: pathlib.Path, which: str) -> int | None:
    """Step of the checkpoint ``load_for_inference`` restored (best, else latest); for reports."""
    def steps(sub: pathlib.Path) -> list[int]:
        return [int(p.name) for p in sub.iterdir() if p.name.isdigit()] if sub.is_dir() else []

    best, last = steps(root / "best"), steps(root / "last")
    if which == "best" and best:
        return max(best)
    return max(last) if last else None


def load_pretrained(name: str) -> Predictor:
    """A trained default model shipped inside the package: ``"flowmaps"``, ``"mlp"`` or
    ``"mlp-learned"`` (the EMA weights of the `cpu`-preset runs in docs/results.md). The same
    :class:`Predictor` as :func:`load` of that run; a wrong name raises ``ValueError`` listing the
    names. See :mod:`flowmaps_jax.pretrained`."""
    from flowmaps_jax.pretrained import load_pretrained as _load

    return _load(name)
