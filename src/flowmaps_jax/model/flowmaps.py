"""FlowMaps: Map Encoder + CDiT velocity network as pure functions over a params pytree:
``init_params(key, config)``, ``encode(params, config, tokens) -> Context`` (once per scene) and
``velocity(params, config, context, x_t, t, queries) -> v``; the N rows of a query share its
conditioning. ``dropout_key=None``: no dropout. ``config`` is a static jit argument.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Collection

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from flowmaps_jax.model import mixture
from flowmaps_jax.model.cdit import CDiTBlock, FinalLayer
from flowmaps_jax.model.config import ModelConfig
from flowmaps_jax.model.embeddings import FlatDense, SinusoidalMLP
from flowmaps_jax.model.encoder import EncoderLayer, MapEncoder, example_inputs
from flowmaps_jax.model.readout import PointerReadout
from flowmaps_jax.model.route import RouteReadout
from flowmaps_jax.tokens import Queries, SceneTokens, validate_queries, validate_tokens
from flowmaps_jax.validation import check_array, check_instance, check_real_array


@struct.dataclass
class Context:
    """Encoded map: tokens (B, S, D) from the Map Encoder (zero on padding), mask (B, S) bool,
    and what the heads read besides: the tokens' normalised boxes (B, S, 4), descriptor and kind
    (B, S) ints, and the map's τ (B,)."""

    tokens: jnp.ndarray
    mask: jnp.ndarray
    boxes: jnp.ndarray
    tau: jnp.ndarray
    descriptor: jnp.ndarray
    kind: jnp.ndarray


class FlowMaps(nn.Module):
    """The flax module behind the pure functions (``encode``/``velocity`` via apply);
    ``config.precision`` reaches every submodule that multiplies."""

    config: ModelConfig

    def setup(self):
        cfg = self.config
        self.encoder = MapEncoder(cfg)
        self.query_embed = SinusoidalMLP(cfg.dim, cfg.freq_bands, cfg.max_frequency,
                                         cfg.precision)
        self.query_pos = self.param("query_pos", nn.initializers.normal(0.02), (cfg.dim,))
        self.time_embed = SinusoidalMLP(cfg.dim, cfg.freq_bands, cfg.max_frequency,
                                        cfg.precision)
        self.tau_q_embed = nn.Embed(cfg.tau_max, cfg.dim)
        self.descriptor_embed = nn.Embed(cfg.num_descriptors, cfg.dim)
        if cfg.condition_on_dtau or cfg.head == "mixture":
            self.dtau_embed = nn.Embed(cfg.tau_max, cfg.dim)
        self.blocks = [CDiTBlock(cfg.dim, cfg.heads, cfg.mlp_ratio, cfg.dropout, cfg.precision)
                       for _ in range(cfg.cdit_blocks)]
        if cfg.head == "pointer":
            self.final_norm = FinalLayer(cfg.dim, out_dim=None, precision=cfg.precision)
            self.readout = PointerReadout(cfg.dim, cfg.box_scale, cfg.box_offset,
                                          cfg.pointer_width_scale, cfg.precision,
                                          cfg.pointer_widths)
        elif cfg.head == "route":
            self.final_norm = FinalLayer(cfg.dim, out_dim=None, precision=cfg.precision)
            self.readout = RouteReadout(cfg.dim, cfg.tau_max, cfg.box_scale, cfg.box_offset,
                                        cfg.pointer_width_scale, cfg.precision)
        else:
            self.final = FinalLayer(cfg.dim, precision=cfg.precision)
        if cfg.head == "mixture":  # the table weights' own CDiT rows (model/mixture.py)
            if cfg.weight_attention == "self":
                self.weight_blocks = [EncoderLayer(cfg.dim, cfg.heads, cfg.mlp_ratio, cfg.dropout,
                                                   cfg.precision)
                                      for _ in range(cfg.weight_blocks)]
            else:
                self.weight_blocks = [CDiTBlock(cfg.dim, cfg.heads, cfg.mlp_ratio, cfg.dropout,
                                                cfg.precision) for _ in range(cfg.weight_blocks)]
            self.weight_pos = self.param("weight_pos", nn.initializers.normal(0.02), (cfg.dim,))
            self.start_pos = self.param("start_pos", nn.initializers.normal(0.02), (cfg.dim,))
            self.weight_tau_embed = nn.Embed(cfg.tau_max, cfg.dim)
            self.weight_final = FinalLayer(cfg.dim, out_dim=cfg.tau_max, precision=cfg.precision)
            self.table_embed = FlatDense(cfg.dim, precision=cfg.precision)
            if cfg.weight_geometry != "none":
                self.geometry_embed = FlatDense(cfg.dim, precision=cfg.precision)

    def encode(self, tokens: SceneTokens, deterministic: bool = True) -> Context:
        mask = tokens.mask.astype(bool)
        return Context(tokens=self.encoder(tokens, deterministic), mask=mask,
                       boxes=jnp.asarray(tokens.boxes, jnp.float32), tau=tokens.tau,
                       descriptor=jnp.asarray(tokens.descriptor), kind=jnp.asarray(tokens.kind))

    def velocity(self, context: Context, x_t, t, queries: Queries, deterministic: bool = True):
        cfg = self.config
        c = (self.tau_q_embed(queries.tau_q) + self.descriptor_embed(queries.descriptor)
             + self.time_embed(t[..., None]))  # (B, Q, D)
        if cfg.condition_on_dtau:
            c = c + self.dtau_embed(self._dtau(context, queries))
        if cfg.head == "mixture":
            raise ValueError("ModelConfig.head='mixture' has no unconditional velocity: use "
                             "placement_velocity with the rows' tables")
        x = self.query_embed(x_t) + self.query_pos  # (B, Q, N, D)
        for block in self.blocks:
            x = block(x, c, context.tokens, context.mask, deterministic)
        if cfg.head == "pointer":
            return self.readout(self.final_norm(x, c), c, context.tokens, context.mask,
                                context.boxes, x_t, t)
        if cfg.head == "route":
            return self.readout(self.final_norm(x, c), self.descriptor_embed(queries.descriptor),
                                context, queries.descriptor, self._dtau(context, queries), x_t, t)
        return self.final(x, c)

    def object_table_logits(self, context: Context, descriptors, deterministic: bool = True):
        """The mixture head's table logits for every horizon (B, R, S, tau_max) of the objects
        named by ``descriptors`` (B, R), very negative off the furniture; free of x_t and t."""
        c = (self.weight_tau_embed(context.tau)[:, None, :]
             + self.descriptor_embed(descriptors))  # (B, R, D)
        _, _, start = mixture.placement_frame(context, descriptors)
        s = context.tokens.shape[1]
        on_start = jax.nn.one_hot(start, s, dtype=context.tokens.dtype)[..., None]  # (B,R,S,1)
        rows = context.tokens[:, None] + self.weight_pos + on_start * self.start_pos
        if self.config.weight_geometry != "none":
            rows = rows + self.geometry_embed(mixture.relative_geometry(
                context.boxes, start, angle=self.config.weight_geometry == "relative"))
        if self.config.weight_attention == "self":  # one object's rows attend to each other
            b, r = descriptors.shape
            x = (rows + c[:, :, None, :]).reshape(b * r, s, -1)
            mask = jnp.broadcast_to(context.mask[:, None], (b, r, s)).reshape(b * r, s)
            for block in self.weight_blocks:
                x = block(x, mask, deterministic)
            rows = x.reshape(b, r, s, -1)
        else:
            for block in self.weight_blocks:
                rows = block(rows, c, context.tokens, context.mask, deterministic)
        logits = self.weight_final(rows, c)  # (B, R, S, tau_max)
        keep = mixture.tables_of(context)[:, None, :, None]
        return jnp.where(keep, logits, jnp.finfo(jnp.float32).min / 4)

    def table_logits(self, context: Context, queries: Queries, deterministic: bool = True):
        """The mixture head's table logits (B, Q, S) of each query at its own Δτ."""
        logits = self.object_table_logits(context, queries.descriptor, deterministic)
        return select_horizon(logits, self._dtau(context, queries))

    def placement_velocity(self, context: Context, z_t, t, queries: Queries, table,
                           deterministic: bool = True):
        """The mixture head's vector field in the local frame of each row's table:
        z_t (B, Q, N, 4), t (B, Q), table (B, Q, N) token indices → v (B, Q, N, 4)."""
        smooth = mixture.SMOOTH_FREQUENCY / self.config.max_frequency  # a smooth field
        c = (self.tau_q_embed(queries.tau_q) + self.descriptor_embed(queries.descriptor)
             + self.time_embed(smooth * t[..., None])
             + self.dtau_embed(self._dtau(context, queries)))
        chosen = mixture.gather_tokens(context.tokens, table)  # (B, Q, N, D)
        x = self.query_embed(smooth * z_t) + self.query_pos + self.table_embed(chosen)
        for block in self.blocks:
            x = block(x, c, context.tokens, context.mask, deterministic)
        return self.final(x, c)

    def _dtau(self, context: Context, queries: Queries):
        return horizon_index(queries.tau_q, context.tau, self.config.tau_max)

    def mixture(self, context: Context, queries: Queries):
        """The route head's mixture (log-weights (B, Q, S), means (B, Q, S, 4), log-variances
        (B, Q, 4), flow space): what the flow carries noise onto when its residual is zero."""
        return self.readout(None, self.descriptor_embed(queries.descriptor), context,
                            queries.descriptor, self._dtau(context, queries), None, None,
                            mixture_only=True)

    def __call__(self, tokens, x_t, t, queries, deterministic: bool = True):
        if self.config.head == "mixture":  # init: touch both branches
            context = self.encode(tokens, deterministic)
            logits = self.table_logits(context, queries, deterministic)
            table = jnp.argmax(logits, axis=-1)[:, :, None]
            table = jnp.broadcast_to(table, x_t.shape[:3])
            return self.placement_velocity(context, x_t, t, queries, table, deterministic)
        return self.velocity(self.encode(tokens, deterministic), x_t, t, queries, deterministic)


def horizon_index(tau_q, tau, tau_max: int):
    """Each query's horizon Δτ = τ_q − τ (B, Q) as a column index of the per-horizon outputs,
    clipped to [0, tau_max − 1]; tau_q (B, Q), tau (B,)."""
    return jnp.clip(tau_q - tau[:, None], 0, tau_max - 1)


def select_horizon(logits, dtau):
    """Per-horizon logits (B, Q, S, T) at each query's Δτ (B, Q) → (B, Q, S)."""
    return jnp.take_along_axis(logits, dtau[:, :, None, None], axis=-1)[..., 0]


def _rngs(dropout_key):
    return {} if dropout_key is None else {"dropout": dropout_key}


@functools.partial(jax.jit, static_argnames="config")
def init_params(key: jax.Array, config: ModelConfig):
    """Fresh FlowMaps parameters (a nested dict pytree) for ``config``."""
    tokens, queries = example_inputs()
    return FlowMaps(config).init(key, tokens, jnp.zeros((1, 1, 1, 4)), jnp.zeros((1, 1)),
                                 queries)["params"]


@functools.partial(jax.jit, static_argnames="config")
def encode(params, config: ModelConfig, tokens: SceneTokens, *, dropout_key=None) -> Context:
    """Encode B scenes once: SceneTokens (B, S) → Context (tokens (B, S, D), mask (B, S))."""
    return FlowMaps(config).apply({"params": params}, tokens, dropout_key is None,
                                  method=FlowMaps.encode, rngs=_rngs(dropout_key))


@functools.partial(jax.jit, static_argnames="config")
def velocity(params, config: ModelConfig, context: Context, x_t, t, queries: Queries, *,
             dropout_key=None):
    """Velocity u_θ(x_t, t | map, query): context from :func:`encode`, x_t (B, Q, N, 4), t (B, Q),
    queries (B, Q) → v (B, Q, N, 4)."""
    return FlowMaps(config).apply({"params": params}, context, x_t, t, queries,
                                  dropout_key is None, method=FlowMaps.velocity,
                                  rngs=_rngs(dropout_key))


@functools.partial(jax.jit, static_argnames="config")
def table_logits(params, config: ModelConfig, context: Context, queries: Queries, *,
                 dropout_key=None):
    """The mixture head's table logits (B, Q, S) (``head="mixture"`` only), free of x_t and t;
    a very negative number off the furniture tokens."""
    return FlowMaps(config).apply({"params": params}, context, queries, dropout_key is None,
                                  method=FlowMaps.table_logits, rngs=_rngs(dropout_key))


@functools.partial(jax.jit, static_argnames="config")
def object_table_logits(params, config: ModelConfig, context: Context, descriptors, *,
                        dropout_key=None):
    """The mixture head's table logits at every horizon (B, R, S, tau_max) of the objects
    ``descriptors`` (B, R) (``head="mixture"`` only); column Δτ is the horizon Δτ."""
    return FlowMaps(config).apply({"params": params}, context, descriptors, dropout_key is None,
                                  method=FlowMaps.object_table_logits, rngs=_rngs(dropout_key))


@functools.partial(jax.jit, static_argnames="config")
def placement_velocity(params, config: ModelConfig, context: Context, z_t, t, queries: Queries,
                       table, *, dropout_key=None):
    """The mixture head's vector field in each row's table frame (``head="mixture"`` only):
    z_t (B, Q, N, 4), t (B, Q), table (B, Q, N) token indices → v (B, Q, N, 4)."""
    return FlowMaps(config).apply({"params": params}, context, z_t, t, queries, table,
                                  dropout_key is None, method=FlowMaps.placement_velocity,
                                  rngs=_rngs(dropout_key))


@functools.partial(jax.jit, static_argnames="config")
def route_mixture(params, config: ModelConfig, context: Context, queries: Queries):
    """The route head's mixture over the map's tables (``head="route"`` only): log-weights
    (B, Q, S) (−inf off the tables), means (B, Q, S, 4) and log-variances (B, Q, 4), in the
    flow's space."""
    return FlowMaps(config).apply({"params": params}, context, queries,
                                  method=FlowMaps.mixture)


@functools.partial(jax.jit, static_argnames="config")
def velocity_and_anchor_logits(params, config: ModelConfig, context: Context, x_t, t,
                               queries: Queries, *, dropout_key=None):
    """:func:`velocity` plus the pointer head's anchor logits (B, Q, N, S) (``head="pointer"``
    only): the mixture's log-weights over the map's tokens before the x_t likelihood."""
    if config.head not in ("pointer", "route"):
        raise ValueError("anchor logits exist only for ModelConfig.head='pointer' or 'route'")
    v, state = FlowMaps(config).apply({"params": params}, context, x_t, t, queries,
                                      dropout_key is None, method=FlowMaps.velocity,
                                      rngs=_rngs(dropout_key), mutable=["intermediates"])
    return v, state["intermediates"]["readout"]["anchor_logits"][0]


@functools.partial(jax.jit, static_argnames="config")
def forward(params, config: ModelConfig, tokens: SceneTokens, x_t, t, queries: Queries,
            dropout_key=None):
    """``velocity(encode(tokens))`` in one call. Shapes as in :func:`velocity`."""
    enc_key = vel_key = None
    if dropout_key is not None:
        enc_key, vel_key = jax.random.split(dropout_key)
    context = encode(params, config, tokens, dropout_key=enc_key)
    return velocity(params, config, context, x_t, t, queries, dropout_key=vel_key)


def make_velocity_fn(params, config: ModelConfig, context: Context,
                     queries: Queries) -> Callable[[jnp.ndarray, jnp.ndarray], jnp.ndarray]:
    """``fn(x (B, Q, N, 4), t scalar) -> v`` over a context and queries, no dropout (the
    ``velocity_fn`` of :mod:`flowmaps_jax.flow`)."""
    def velocity_fn(x, t):
        t_bq = jnp.broadcast_to(jnp.asarray(t, x.dtype), x.shape[:2])
        return velocity(params, config, context, x, t_bq, queries)
    return velocity_fn


def check_inputs(config: ModelConfig, tokens: SceneTokens, queries: Queries, x_t=None, t=None,
                 object_descriptors: Collection[int] | None = None) -> None:
    """``ValueError`` naming the argument if model inputs are malformed (outside jit): tokens
    (B, S), queries (B, Q) with tau < tau_q < tau_max and known descriptors (``object_descriptors``
    if given), x_t (B, Q, N, 4) finite, t (B, Q) in [0, 1].
    """
    check_instance("tokens", tokens, SceneTokens)
    b = check_array("tokens.mask", tokens.mask, (None, None)).shape[0]
    check_instance("queries", queries, Queries)
    q = check_array("queries.descriptor", queries.descriptor, (b, None)).shape[1]
    if b == 0 or q == 0:
        raise ValueError(f"queries.descriptor must not be empty (at least one scene and one "
                         f"query); got shape {(b, q)}")
    if x_t is not None:
        check_real_array("x_t", x_t, (b, q, None, 4))
    if t is not None:
        check_real_array("t", t, (b, q), low=0.0, high=1.0, what="flow time")
    validate_tokens(tokens, config.num_descriptors, num_timesteps=config.tau_max)
    validate_queries(queries, tokens.tau, config.num_descriptors, config.tau_max,
                     object_descriptors)
