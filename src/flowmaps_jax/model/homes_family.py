"""FlowMaps on homes: the network, its loss and its jitted cores, in one module.

The mixture read-out on a home's tokens and the queried object's history
(:mod:`flowmaps_jax.model.homes_inputs`, which reads only what any log has):

    p_θ(box | home at τ, query) = Σ_r π_r(home, query, history) · p_θ(box | r, home, query)

* **Map Encoder.** Token embedding = SinusoidalMLP(6-D box) + Embed(descriptor, the class
  vocabulary) + Embed(kind), then ``encoder_layers`` pre-norm transformer layers
  (:class:`~flowmaps_jax.model.encoder.EncoderLayer`) and a LayerNorm: the context (B, S, D).
* **Query.** c (B, Q, D) = Embed(the object's descriptor) + MLP(query features: periodic
  features of τ and τ_q, the log-scaled horizon) + Dense(the object's context token).
* **History read-out** (learned rhythms). ``history_heads`` heads attend over the object's
  observed history events: keys from each event's hour of day, day of week and age
  (``homes_inputs.periodic``), a query from c and τ_q's periodic features. Per head and
  receptacle r: the softmax-weighted fraction of the events on r, and two unnormalised sums
  with sigmoid gates, log(1 + Σ g · [on r]) and log(1 + Σ g · [arrived on r]), beside the head's
  log(1 + Σ g): how much evidence the learned context holds, as a count per context would say.
* **Receptacle weights π** (B, Q, R), independent of the flow's x_t and t: one row per
  receptacle slot, built from that receptacle's context token, an MLP of its row features
  (``homes_inputs.ROW_FEATURES``, the history read-out, and its place relative to the object's
  last-seen receptacle, :func:`flowmaps_jax.model.mixture.relative_geometry`), plus c.
  ``weight_blocks`` times, the rows of one query self-attend (over the object's allowed
  receptacles) and then cross-attend to the context (a :class:`~flowmaps_jax.model.cdit.CDiTBlock`,
  AdaLN-Zero on c); a zero-initialised AdaLN final layer gives one logit per row, plus a
  zero-initialised linear term of the row's features, masked to the object's allowed
  receptacles. Trained by cross-entropy against the receptacle the object stands on at τ_q: the
  proper scoring rule, whose optimum is the exact posterior.
* **Placement** p_θ(box | r): a flow-matching model of the 6-D box in the local frame of
  receptacle r, z = (box − μ_r) / scale_r with μ_r = (r's centre x, y; its top + the object's
  half height; the object's w, d, h) and scale_r = :data:`PLACEMENT_SCALE` × (r's w, d; the
  object's h, w, d, h). The CDiT vector field (AdaLN-Zero on c and the flow time t, a
  zero-initialised output, so the velocity is exactly 0 at init) reads r's context token in its
  query row and is integrated by the midpoint solver (:mod:`flowmaps_jax.flow`). In the simulator
  an object's true placement is a point (centred on its receptacle's top, z = 0 in the frame), so
  the flow is trained (CFM, linear path) on the target jittered by :data:`TARGET_JITTER` local
  units: samples spread over the top of the receptacle rather than collapse onto its centre.

Loss = CE + CFM. Everything is a pure function over an explicit params pytree; ``config``
(:class:`HomesModelConfig`) and ``homes_config`` (:class:`HomesConfig`) are static jit arguments.
Shapes: a :class:`~flowmaps_jax.model.homes_inputs.HomesBatch` of B scenes with Q queries
each; boxes normalised (``tokens.normalise_boxes``). The validated wrapper is
:class:`flowmaps_jax.predictor.Predictor` (its homes inference:
:mod:`flowmaps_jax.model.homes_inference`).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from flowmaps_jax import flow
from flowmaps_jax.flowsim.homes.config import HomesConfig
from flowmaps_jax.model import mixture
from flowmaps_jax.model.cdit import CDiTBlock, FinalLayer
from flowmaps_jax.model.embeddings import FlatDense, SinusoidalMLP
from flowmaps_jax.model.encoder import EncoderLayer
from flowmaps_jax.model.homes_inputs import (
    DEFAULT_HISTORY,
    NEGATIVE_FEATURES,
    QUERY_FEATURES,
    ROW_FEATURES,
    HomesBatch,
    HomeTokens,
    periodic,
    token_layout,
)
from flowmaps_jax.validation import check_keys
from flowmaps_jax.validation.fields import Choice, Int, Real, check_fields

FAMILY_NAME = "flowmaps-homes"
"""The family name stored with the model (``"model_kind"`` of its config)."""
PLACEMENT_SCALE = (0.25, 0.25, 0.05, 0.05, 0.05, 0.05)
"""The local frame's unit: fractions of the receptacle's (w, d) for the centre's x, y, and of
the object's (h, w, d, h) for its z and its size."""
TARGET_JITTER = 0.5
"""Std of the noise (local units) added to the placement targets, which are points."""
DEFAULT_NUM_STEPS = 10
"""ODE grid points of the placement flow (the paper's ``linspace(0, 1, 10)``: 18 evaluations)."""
NEGATIVE = jnp.finfo(jnp.float32).min / 4
"""The logit of a receptacle the object may not stand on."""
HISTORY_KEY = 16
"""Width of each history head's keys and query."""
COUNT_SCALE = 4.0
"""The history read-out's log(1 + sums) are divided by this (about 1 at 50 events)."""


@dataclasses.dataclass(frozen=True)
class HomesModelConfig:
    """Sizes of the homes network (frozen: a static jit argument).

    dim: width D; encoder_layers: Map Encoder layers; weight_blocks: (self, cross) block pairs of
    the receptacle-weight rows; cdit_blocks: CDiT blocks of the placement flow; heads: attention
    heads (divide ``dim``); mlp_ratio: MLP hidden width ÷ D; freq_bands, max_frequency: the
    sinusoidal features of boxes; history: hours of history the network reads; history_heads:
    heads of the history read-out; history_observed: trained on partially observed data (every
    query must say which hours were observed); geometry_angle: the rows' geometry has the angle
    around the home's centre (False: offsets and the distance only); negative_evidence: the rows
    end with ``homes_inputs.NEGATIVE_FEATURES``; geometry: False for data without boxes (token
    boxes and the rows' geometry read as zeros, no placement loss).
    """

    dim: int = 64
    encoder_layers: int = 2
    weight_blocks: int = 2
    cdit_blocks: int = 2
    heads: int = 4
    mlp_ratio: int = 4
    freq_bands: int = 8
    max_frequency: float = 100.0
    history: int = DEFAULT_HISTORY
    history_heads: int = 8
    history_observed: bool = False
    geometry_angle: bool = False
    negative_evidence: bool = False
    geometry: bool = True

    def __post_init__(self):
        check_fields(self, _MODEL_RULES, prefix="model.", store=False)
        if self.dim % self.heads:
            raise ValueError(f"model.dim={self.dim} must be divisible by model.heads="
                             f"{self.heads}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> HomesModelConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError`` naming them."""
        if isinstance(data, dict) and "history_counts" in data:
            raise ValueError("this homes model reads the generator-told history features "
                             "removed in issue 54; retrain it (python -m flowmaps_jax.train "
                             "--preset homes, or --data PATH)")
        check_keys("the homes model config", data, [f.name for f in dataclasses.fields(cls)],
                   what="unknown keys")
        return cls(**data)


MAX_BLOCKS = 64
"""The most layers (or block pairs) of each stack of the homes network: its stacks are
unrolled when compiled, so the compile time grows with them."""
_MODEL_RULES = {**{name: Int(1, 1 << 16) for name in (
    "dim", "heads", "mlp_ratio", "freq_bands", "history", "history_heads")},
    **{name: Int(1, MAX_BLOCKS, "each layer is compiled on its own") for name in (
        "encoder_layers", "weight_blocks", "cdit_blocks")}, "max_frequency": Real(1.0),
    **{name: Choice((False, True)) for name in (
        "history_observed", "geometry_angle", "negative_evidence", "geometry")}}
"""The rules of :class:`HomesModelConfig`'s fields (messages name ``model.<field>``)."""


@struct.dataclass
class Context:
    """The encoded scenes: tokens (B, S, D) (zero on padding), mask (B, S), the tokens' boxes
    (B, S, 6) and descriptors (B, S)."""

    tokens: jax.Array
    mask: jax.Array
    boxes: jax.Array
    descriptor: jax.Array


def _gather(values, index):
    """values (B, S, …) at index (B, Q) → (B, Q, …)."""
    return jax.vmap(lambda v, i: v[i])(values, index)


def placement_frame(boxes, object_token, homes_config: HomesConfig):
    """Local frames of every (query, receptacle): means and scales (B, Q, R, 6) (see the module
    docstring), from the tokens' boxes (B, S, 6) and the queried object's token (B, Q)."""
    first, _, _ = token_layout(homes_config)
    rec = boxes[:, first:first + homes_config.max_receptacles]  # (B, R, 6)
    size = jnp.maximum(_gather(boxes, object_token)[..., 3:], 1e-4)  # (B, Q, 3)
    b, q, r = size.shape[0], size.shape[1], rec.shape[1]
    top = rec[..., 2] + rec[..., 5] / 2  # (B, R)
    mean = jnp.concatenate([
        jnp.broadcast_to(rec[:, None, :, :2], (b, q, r, 2)),
        (top[:, None, :] + size[:, :, None, 2] / 2)[..., None],
        jnp.broadcast_to(size[:, :, None, :], (b, q, r, 3))], axis=-1)
    unit = jnp.asarray(PLACEMENT_SCALE, jnp.float32)
    scale = jnp.concatenate([
        jnp.broadcast_to(jnp.maximum(rec[:, None, :, 3:5], 1e-4), (b, q, r, 2)),
        jnp.broadcast_to(jnp.concatenate([size[..., 2:], size], -1)[:, :, None], (b, q, r, 4))],
        axis=-1) * unit
    return mean, scale


def _receptacle_boxes_4d(boxes, homes_config: HomesConfig):
    """The receptacle tokens' boxes as 2-D (y0, x0, h, w) (B, R, 4), for ``relative_geometry``."""
    first, _, _ = token_layout(homes_config)
    rec = boxes[:, first:first + homes_config.max_receptacles]
    return jnp.stack([rec[..., 1] - rec[..., 4] / 2, rec[..., 0] - rec[..., 3] / 2,
                      rec[..., 4], rec[..., 3]], axis=-1)


class _MLP(nn.Module):
    """Dense(D) → GELU → Dense(D)."""

    dim: int

    @nn.compact
    def __call__(self, x):
        return FlatDense(self.dim, name="out")(nn.gelu(FlatDense(self.dim, name="in")(x)))


class HomesNet(nn.Module):
    """The flax module behind the pure functions (see the module docstring)."""

    config: HomesModelConfig
    homes_config: HomesConfig

    def setup(self):
        cfg, d = self.config, self.config.dim
        block = lambda: CDiTBlock(d, cfg.heads, cfg.mlp_ratio, 0.0)  # noqa: E731
        layer = lambda: EncoderLayer(d, cfg.heads, cfg.mlp_ratio, 0.0)  # noqa: E731
        self.box_embed = SinusoidalMLP(d, cfg.freq_bands, cfg.max_frequency)
        self.descriptor_embed = nn.Embed(self.homes_config.max_vocabulary, d)
        self.kind_embed = nn.Embed(3, d)
        self.encoder = [layer() for _ in range(cfg.encoder_layers)]
        self.encoder_norm = nn.LayerNorm()
        self.query_mlp = _MLP(d)
        self.object_proj = FlatDense(d)
        self.row_mlp = _MLP(d)
        self.history_query = FlatDense(cfg.history_heads * HISTORY_KEY)
        self.history_key = FlatDense(cfg.history_heads * HISTORY_KEY)
        self.history_gate = self.param("history_gate", nn.initializers.zeros_init(),
                                       (cfg.history_heads,))
        self.weight_pos = self.param("weight_pos", nn.initializers.normal(0.02), (d,))
        self.row_self = [layer() for _ in range(cfg.weight_blocks)]
        self.row_cross = [block() for _ in range(cfg.weight_blocks)]
        self.weight_final = FinalLayer(d, out_dim=1)
        self.feature_logit = FlatDense(1, kernel_init=nn.initializers.zeros_init())
        self.z_embed = SinusoidalMLP(d, cfg.freq_bands, cfg.max_frequency)
        self.time_embed = SinusoidalMLP(d, cfg.freq_bands, cfg.max_frequency)
        self.table_embed = FlatDense(d)
        self.query_pos = self.param("query_pos", nn.initializers.normal(0.02), (d,))
        self.blocks = [block() for _ in range(cfg.cdit_blocks)]
        self.final = FinalLayer(d, out_dim=6)

    def encode(self, tokens: HomeTokens) -> Context:
        mask = tokens.mask.astype(bool)
        boxes = tokens.boxes if self.config.geometry else jnp.zeros_like(tokens.boxes)
        x = (self.box_embed(boxes) + self.descriptor_embed(tokens.descriptor)
             + self.kind_embed(tokens.kind))
        for layer in self.encoder:
            x = layer(x, mask, True)
        x = jnp.where(mask[..., None], self.encoder_norm(x), 0.0)
        return Context(tokens=x, mask=mask, boxes=tokens.boxes, descriptor=tokens.descriptor)

    def condition(self, context: Context, batch: HomesBatch):
        """c (B, Q, D) of every query."""
        descriptor = jnp.take_along_axis(context.descriptor, batch.object_token, axis=1)
        return (self.descriptor_embed(descriptor) + self.query_mlp(batch.query)
                + self.object_proj(_gather(context.tokens, batch.object_token)))

    def read_history(self, c, batch: HomesBatch):
        """The learned history read-out (B, Q, R, 4 · history_heads): see the module docstring."""
        k, r = self.config.history_heads, self.homes_config.max_receptacles
        h = batch.events.shape[-1]
        hours = batch.tau[..., None] - h + 1 + jnp.arange(h)  # (B, Q, H)
        age = (batch.tau[..., None] - hours).astype(jnp.float32)
        event_time = jnp.concatenate([periodic(hours), age[..., None] / h,
                                      jnp.log1p(age)[..., None] / jnp.log1p(float(h))], -1)
        keys = self.history_key(event_time).reshape(*hours.shape, k, HISTORY_KEY)
        query = self.history_query(jnp.concatenate([c, batch.query], -1))
        score = jnp.einsum("bqhkd,bqkd->bqkh", keys,
                           query.reshape(*c.shape[:2], k, HISTORY_KEY)) / HISTORY_KEY ** 0.5
        seen = (batch.events >= 0)[:, :, None, :]  # (B, Q, 1, H)
        weight = jax.nn.softmax(jnp.where(seen, score, NEGATIVE), -1) * seen
        gate = jax.nn.sigmoid(score + self.history_gate[:, None]) * seen
        on = jax.nn.one_hot(batch.events, r, dtype=jnp.float32)  # (B, Q, H, R)
        code = jnp.where(batch.events >= 0, jnp.arange(h) * r + batch.events, -1)
        before = jnp.concatenate([jnp.full_like(code[..., :1], -1),
                                  jax.lax.cummax(code, axis=code.ndim - 1)[..., :-1]], -1)
        arrived = on * ((before >= 0) & (before % r != batch.events))[..., None]
        total = jnp.log1p(gate.sum(-1))[..., None] / COUNT_SCALE  # (B, Q, K, 1)
        out = [jnp.einsum("bqkh,bqhr->bqkr", weight, on),
               jnp.log1p(jnp.einsum("bqkh,bqhr->bqkr", gate, on)) / COUNT_SCALE,
               jnp.log1p(jnp.einsum("bqkh,bqhr->bqkr", gate, arrived)) / COUNT_SCALE,
               jnp.broadcast_to(total, (*total.shape[:-1], r))]
        return jnp.concatenate(out, axis=2).swapaxes(2, 3)  # (B, Q, R, 4K)

    def weight_logits(self, context: Context, c, batch: HomesBatch):
        """Receptacle logits (B, Q, R), :data:`NEGATIVE` off the allowed receptacles."""
        first, _, _ = token_layout(self.homes_config)
        r = self.homes_config.max_receptacles
        b, q = batch.current.shape
        geometry = mixture.relative_geometry(_receptacle_boxes_4d(context.boxes,
                                                                  self.homes_config),
                                             batch.current,
                                             angle=self.config.geometry_angle)  # (B, Q, R, G)
        geometry = geometry * self.config.geometry
        features = jnp.concatenate([batch.rows, self.read_history(c, batch), geometry], -1)
        rows = (context.tokens[:, None, first:first + r] + self.row_mlp(features)
                + self.weight_pos + c[:, :, None, :])  # (B, Q, R, D)
        allowed = batch.allowed.reshape(b * q, r)
        for attend, cross in zip(self.row_self, self.row_cross, strict=True):
            rows = attend(rows.reshape(b * q, r, -1), allowed, True).reshape(b, q, r, -1)
            rows = cross(rows, c, context.tokens, context.mask, True)
        logits = self.weight_final(rows, c)[..., 0] + self.feature_logit(features)[..., 0]
        return jnp.where(batch.allowed, logits, NEGATIVE)

    def placement_velocity(self, context: Context, c, z_t, t, table):
        """The placement field in each row's frame: z_t (B, Q, N, 6), t (B, Q), table (B, Q, N)
        receptacle slots → v (B, Q, N, 6)."""
        first, _, _ = token_layout(self.homes_config)
        smooth = mixture.SMOOTH_FREQUENCY / self.config.max_frequency  # a smooth field
        ct = c + self.time_embed(smooth * t[..., None])
        chosen = jax.vmap(lambda tok, i: tok[first + i])(context.tokens, table)  # (B, Q, N, D)
        x = self.z_embed(smooth * z_t) + self.query_pos + self.table_embed(chosen)
        for block in self.blocks:
            x = block(x, ct, context.tokens, context.mask, True)
        return self.final(x, ct)

    def __call__(self, batch: HomesBatch, z_t, t):  # init: touch every branch
        context = self.encode(batch.tokens)
        c = self.condition(context, batch)
        logits = self.weight_logits(context, c, batch)
        table = jnp.broadcast_to(jnp.argmax(logits, -1)[..., None], z_t.shape[:3])
        return self.placement_velocity(context, c, z_t, t, table)


def example_batch(homes_config: HomesConfig, b: int = 1, q: int = 1,
                  features: int = len(ROW_FEATURES)) -> HomesBatch:
    """The smallest batch of the right feature sizes (zeros; one allowed receptacle)."""
    s, r = homes_config.max_tokens, homes_config.max_receptacles
    tokens = HomeTokens(boxes=jnp.zeros((b, s, 6)), descriptor=jnp.zeros((b, s), jnp.int32),
                        kind=jnp.zeros((b, s), jnp.int32), mask=jnp.ones((b, s), bool))
    zeros = jnp.zeros((b, q), jnp.int32)
    return HomesBatch(tokens=tokens, object_token=zeros, tau=zeros, tau_q=zeros + 1,
                      query=jnp.zeros((b, q, QUERY_FEATURES)),
                      events=jnp.zeros((b, q, DEFAULT_HISTORY), jnp.int32),
                      rows=jnp.zeros((b, q, r, features)),
                      allowed=jnp.arange(r) == jnp.zeros((b, q, 1), jnp.int32),
                      current=jnp.zeros((b, q), jnp.int32), target=jnp.zeros((b, q), jnp.int32),
                      target_box=jnp.zeros((b, q, 6)))


# --------------------------------------------------------------------------- pure functions


@functools.partial(jax.jit, static_argnames=("config", "homes_config"))
def init_params(key, config: HomesModelConfig, homes_config: HomesConfig):
    """Fresh parameters (a nested dict pytree)."""
    batch = example_batch(homes_config, features=len(ROW_FEATURES) + len(
        NEGATIVE_FEATURES) * config.negative_evidence)
    return HomesNet(config, homes_config).init(key, batch, jnp.zeros((1, 1, 1, 6)),
                                               jnp.zeros((1, 1)))["params"]


def _apply(params, config, homes_config, method, *args):
    return HomesNet(config, homes_config).apply({"params": params}, *args, method=method)


def _encode_and_condition(params, config, homes_config, batch: HomesBatch):
    def both(module, batch):
        context = module.encode(batch.tokens)
        return context, module.condition(context, batch)

    return _apply(params, config, homes_config, both, batch)


def weight_logits(params, config, homes_config, context, c, batch):
    """Receptacle logits (B, Q, R) (pure; not jitted on its own)."""
    return _apply(params, config, homes_config, HomesNet.weight_logits, context, c, batch)


def placement_velocity(params, config, homes_config, context, c, z_t, t, table):
    """The placement field v (B, Q, N, 6) (pure; not jitted on its own)."""
    return _apply(params, config, homes_config, HomesNet.placement_velocity, context, c, z_t,
                  t, table)


def _frames_at(mean, scale, table):
    """Means and scales (B, Q, R, 6) at the rows' receptacles table (B, Q, N) → (B, Q, N, 6)."""
    return mixture.gather_rows(mean, table), mixture.gather_rows(scale, table)


def homes_loss(params, config: HomesModelConfig, homes_config: HomesConfig, batch: HomesBatch,
               key, cfm_weight: float = 1.0):
    """``(loss, aux)``: the cross-entropy of the receptacle weights against the receptacle each
    object stands on at τ_q, plus ``cfm_weight`` × the flow-matching loss of the placement flow
    on that receptacle (targets jittered, see the module docstring). aux: ``loss``, ``ce``,
    ``cfm`` and ``selection`` (= ``ce``, what the best checkpoint is chosen by)."""
    jitter_key, noise_key, t_key = jax.random.split(key, 3)
    context, c = _encode_and_condition(params, config, homes_config, batch)
    logits = weight_logits(params, config, homes_config, context, c, batch)
    log_w = jax.nn.log_softmax(logits, axis=-1)
    ce = -jnp.mean(jnp.take_along_axis(log_w, batch.target[..., None], axis=-1))
    table = batch.target[..., None]  # (B, Q, 1)
    mean, scale = _frames_at(*placement_frame(context.boxes, batch.object_token, homes_config),
                             table)
    z1 = (batch.target_box[:, :, None] - mean) / scale
    z1 = z1 + TARGET_JITTER * jax.random.normal(jitter_key, z1.shape)
    z0 = jax.random.normal(noise_key, z1.shape)
    t = flow.sample_t(t_key, z1.shape[:2], "beta")
    v = placement_velocity(params, config, homes_config, context, c,
                           flow.linear_path(z0, z1, t[..., None]), t, table)
    cfm = jnp.mean(jnp.square(v - flow.target_velocity(z0, z1)))
    loss = ce + cfm_weight * config.geometry * cfm
    return loss, {"loss": loss, "ce": ce, "cfm": cfm, "selection": ce}


@functools.partial(jax.jit, static_argnames=("config", "homes_config"))
def receptacle_probabilities(params, config: HomesModelConfig, homes_config: HomesConfig,
                             batch: HomesBatch):
    """The mixture weights π (B, Q, R): a distribution over each object's allowed receptacles
    (exactly 0 elsewhere), read without sampling."""
    context, c = _encode_and_condition(params, config, homes_config, batch)
    logits = weight_logits(params, config, homes_config, context, c, batch)
    p = jnp.where(batch.allowed, jax.nn.softmax(logits, axis=-1), 0.0)
    return p / jnp.sum(p, axis=-1, keepdims=True)


@functools.partial(jax.jit, static_argnames=("config", "homes_config", "num_samples",
                                             "num_steps"))
def sample_placements(params, config: HomesModelConfig, homes_config: HomesConfig,
                      batch: HomesBatch, key, num_samples: int,
                      num_steps: int = DEFAULT_NUM_STEPS):
    """N samples per query: receptacles (B, Q, N) int32 drawn from π, and normalised boxes
    (B, Q, N, 6) from the placement flow on them (midpoint solver, one ``lax.scan``)."""
    choice_key, noise_key = jax.random.split(key)
    context, c = _encode_and_condition(params, config, homes_config, batch)
    logits = weight_logits(params, config, homes_config, context, c, batch)
    b, q = logits.shape[:2]
    table = jax.random.categorical(choice_key, logits[:, :, None, :],
                                   shape=(b, q, num_samples)).astype(jnp.int32)
    mean, scale = _frames_at(*placement_frame(context.boxes, batch.object_token, homes_config),
                             table)

    def velocity_fn(z, t):
        return placement_velocity(params, config, homes_config, context, c, z,
                                  jnp.broadcast_to(t, (b, q)), table)

    z0 = jax.random.normal(noise_key, (b, q, num_samples, 6))
    z1 = flow.integrate(velocity_fn, z0, num_steps, "midpoint")
    return table, mean + scale * z1


# --------------------------------------------------------------------------- stored configs


class HomesSpec(NamedTuple):
    """What a stored homes config describes (the store layer's model spec of this family):
    ``family_name`` (:data:`FAMILY_NAME`), the network's ``model`` sizes and the ``homes`` world."""

    family_name: str
    model: HomesModelConfig
    homes: HomesConfig

    def abstract_params(self):
        """Structure, shapes and dtypes of the params (nothing computed)."""
        return jax.eval_shape(lambda key: init_params(key, self.model, self.homes),
                              jax.random.key(0))


def homes_spec(config: dict) -> HomesSpec:
    """The spec of a stored homes run config (``HomesTrainConfig.to_dict()``: its ``model`` and
    ``homes`` sections; the training fields are not read). ``ValueError`` naming what is
    wrong."""
    if not isinstance(config, dict) or config.get("model_kind") != FAMILY_NAME:
        raise ValueError(f"not a stored {FAMILY_NAME!r} config")
    for section in ("model", "homes"):
        if not isinstance(config.get(section), dict):
            raise ValueError(f"the {FAMILY_NAME!r} config has no {section!r} section")
    return HomesSpec(family_name=FAMILY_NAME, model=HomesModelConfig.from_dict(config["model"]),
                     homes=HomesConfig.from_dict(config["homes"]))
