"""Map Encoder: scene tokens at state time τ → context tokens (B, S, D).

Token embedding = SinusoidalMLP(box y, x, h, w) + Embed(descriptor) + Embed(type flag)
+ Embed(τ) (+ Embed(age) with ``history`` > 1: how many steps before τ a token was seen), then
``encoder_layers`` pre-norm transformer layers and a final LayerNorm; no positional embedding
(equivariant to permuting tokens); padding rows of the output are zero.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from flowmaps_jax.model.config import ModelConfig
from flowmaps_jax.model.embeddings import FlatDense, SinusoidalMLP
from flowmaps_jax.model.precision import compute_dtype
from flowmaps_jax.tokens import Queries, SceneTokens


class FeedForward(nn.Module):
    """Dense(mlp_ratio·D) → GELU → dropout → Dense(D). (..., D) → (..., D)."""

    dim: int
    mlp_ratio: int
    dropout: float
    precision: str = "float32"

    @nn.compact
    def __call__(self, x: jnp.ndarray, deterministic: bool) -> jnp.ndarray:
        h = nn.gelu(FlatDense(self.dim * self.mlp_ratio, name="fc1", precision=self.precision)(x))
        h = nn.Dropout(self.dropout)(h, deterministic=deterministic)
        return FlatDense(self.dim, name="fc2", precision=self.precision)(h)


class SelfAttention(nn.Module):
    """Multi-head self-attention over tokens with a key-padding mask. x (B, S, D), mask (B, S)."""

    dim: int
    heads: int
    precision: str = "float32"

    @nn.compact
    def __call__(self, x: jnp.ndarray, mask: jnp.ndarray) -> jnp.ndarray:
        b, s, d = x.shape
        dtype = compute_dtype(self.precision)
        qkv = FlatDense(3 * self.dim, name="qkv", precision=self.precision)(x)
        qkv = qkv.reshape(b, s, 3, self.heads, -1)
        if dtype is not None:
            qkv = qkv.astype(dtype)
        out = jax.nn.dot_product_attention(qkv[:, :, 0], qkv[:, :, 1], qkv[:, :, 2],
                                           mask=mask[:, None, None, :])  # (B, S, H, Dh)
        if dtype is not None:
            out = out.astype(jnp.float32)
        return FlatDense(self.dim, name="out", precision=self.precision)(out.reshape(b, s, d))


class EncoderLayer(nn.Module):
    """Pre-norm transformer layer: x += Drop(MHA(LN x)); x += Drop(MLP(LN x)). x (B, S, D)."""

    dim: int
    heads: int
    mlp_ratio: int
    dropout: float
    precision: str = "float32"

    @nn.compact
    def __call__(self, x: jnp.ndarray, mask: jnp.ndarray, deterministic: bool) -> jnp.ndarray:
        h = SelfAttention(self.dim, self.heads, self.precision, name="attn")(
            nn.LayerNorm(name="norm1")(x), mask)
        x = x + nn.Dropout(self.dropout)(h, deterministic=deterministic)
        h = FeedForward(self.dim, self.mlp_ratio, self.dropout, self.precision, name="mlp")(
            nn.LayerNorm(name="norm2")(x), deterministic)
        return x + nn.Dropout(self.dropout)(h, deterministic=deterministic)


class MapEncoder(nn.Module):
    """SceneTokens with leading dim (B,) → context tokens (B, S, D), zero on padding."""

    config: ModelConfig

    @nn.compact
    def __call__(self, tokens: SceneTokens, deterministic: bool) -> jnp.ndarray:
        cfg = self.config
        x = SinusoidalMLP(cfg.dim, cfg.freq_bands, cfg.max_frequency, cfg.precision,
                          name="box_embed")(tokens.boxes)
        x = x + nn.Embed(cfg.num_descriptors, cfg.dim, name="descriptor_embed")(tokens.descriptor)
        x = x + nn.Embed(2, cfg.dim, name="kind_embed")(tokens.kind)
        x = x + nn.Embed(cfg.tau_max, cfg.dim, name="tau_embed")(tokens.tau)[:, None, :]
        if cfg.history > 1:  # the paper's single map (history 1) has no such parameter
            age = jnp.zeros_like(tokens.kind) if tokens.age is None else tokens.age
            x = x + nn.Embed(cfg.history, cfg.dim, name="age_embed")(
                jnp.minimum(age, cfg.history - 1))
        mask = tokens.mask.astype(bool)
        for i in range(cfg.encoder_layers):
            x = EncoderLayer(cfg.dim, cfg.heads, cfg.mlp_ratio, cfg.dropout, cfg.precision,
                             name=f"layer_{i}")(x, mask, deterministic)
        x = nn.LayerNorm(name="final_norm")(x)
        return jnp.where(mask[..., None], x, 0.0)


def example_inputs() -> tuple[SceneTokens, Queries]:
    """One scene with one token and one query: the smallest input that initialises parameters
    (their shapes depend on the config only, not on B, S or Q)."""
    tokens = SceneTokens(boxes=jnp.zeros((1, 1, 4)), descriptor=jnp.zeros((1, 1), jnp.int32),
                         kind=jnp.zeros((1, 1), jnp.int32), mask=jnp.ones((1, 1), bool),
                         tau=jnp.zeros((1,), jnp.int32))
    return tokens, Queries(descriptor=jnp.zeros((1, 1), jnp.int32),
                           tau_q=jnp.ones((1, 1), jnp.int32))
