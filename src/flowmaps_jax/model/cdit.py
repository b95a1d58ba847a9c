"""CDiT block without self-attention (Navigation World Models' CDiT, as FlowMaps uses it).

Each block takes query rows x (B, Q, N, D) — the N rows of one query share its conditioning
c (B, Q, D) — and the context tokens (B, S, D) with their padding mask (B, S):

    shift_ctx, scale_ctx, shift_ca, scale_ca, gate_ca, shift_mlp, scale_mlp, gate_mlp
        = Dense(SiLU(c))                                                  (once per query)
    m   = LN(context) ⊙ (1 + scale_ctx) + shift_ctx                    (modulated context)
    x  += gate_ca  · CrossAttn(query = LN(x) ⊙ (1 + scale_ca) + shift_ca, keys/values = m)
    x  += gate_mlp · MLP(LN(x) ⊙ (1 + scale_mlp) + shift_mlp)

LayerNorms have no learned affine; the modulation Dense and the final projection are
zero-initialised (AdaLN-Zero). ``dtype``: the matmul operand dtype (None: float32); results are
float32.
"""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp

from flowmaps_jax.model.embeddings import FlatDense
from flowmaps_jax.model.encoder import FeedForward
from flowmaps_jax.model.precision import compute_dtype, dot, einsum


def _layer_norm(x: jnp.ndarray, eps: float = 1e-6) -> jnp.ndarray:
    """LayerNorm over the last axis without learned scale or bias."""
    mean = x.mean(-1, keepdims=True)
    var = jnp.square(x - mean).mean(-1, keepdims=True)
    return (x - mean) * jax.lax.rsqrt(var + eps)


def modulate(x: jnp.ndarray, shift: jnp.ndarray, scale: jnp.ndarray) -> jnp.ndarray:
    """AdaLN modulation ``x * (1 + scale) + shift`` (shift/scale broadcast against x)."""
    return x * (1.0 + scale) + shift


def _masked_softmax(scores: jnp.ndarray, key_mask: jnp.ndarray) -> jnp.ndarray:
    """Softmax over the last axis (keys) with padding keys (mask False) excluded."""
    scores = jnp.where(key_mask, scores, jnp.finfo(scores.dtype).min)
    return jax.nn.softmax(scores, axis=-1)


def absorbed_cross_attention(x, context_norm, mask, shift, scale, weights, dtype=None):
    """Cross-attention to a per-query modulated context, without materialising it.

    Shapes: x (B, Q, N, D) query rows; context_norm n = LN(context) (B, S, D); mask (B, S) bool;
    shift, scale (B, Q, D) context modulation of each query; weights: dict with wq, wk, wv
    (D, H, Dh), bq, bk, bv (H, Dh), wo (H, Dh, D), bo (D,). Returns (B, Q, N, D).

    With m_s = n_s ⊙ (1 + scale_q) + shift_q, per head: score = ((W_k)ᵀ q ⊙ (1 + scale_q)) · n_s
    + const_q (softmax drops the constant), and Σ_s a_s (W_v m_s + b_v) = W_v ((Σ_s a_s n_s) ⊙
    (1 + scale_q) + shift_q) + b_v: O(H·S·D + D²) per row instead of O(S·D²).
    """
    b, q, n, d = x.shape
    heads, head_dim = weights["wq"].shape[1:]
    gain = (1.0 + scale)[:, :, None, None, :]  # (B, Q, 1, 1, D), shared by the N rows
    # Row-wise products are written on flat (rows, ...) arrays: one GEMM each, fast backward on CPU.
    query = (dot(x.reshape(-1, d), weights["wq"].reshape(d, heads * head_dim), dtype)
             + weights["bq"].reshape(-1)).reshape(-1, heads, head_dim)  # (B·Q·N, H, Dh)
    u = einsum("rhk,dhk->rhd", query, weights["wk"], dtype).reshape(b, q, n, heads, d)
    u = u * (gain / math.sqrt(head_dim))
    # One batched matmul per scene over all its (query, row, head) triples: (B, QNH, D)·(B, S, D)ᵀ
    u = u.reshape(b, q * n * heads, d)
    scores = einsum("bxd,bsd->bxs", u, context_norm, dtype)
    attn = _masked_softmax(scores, mask[:, None, :])
    pooled = einsum("bxs,bsd->bxd", attn, context_norm, dtype).reshape(b, q, n, heads, d)
    pooled = (pooled * gain + shift[:, :, None, None, :]).reshape(-1, heads, d)
    values = einsum("rhd,dhk->rhk", pooled, weights["wv"], dtype) + weights["bv"]
    out = dot(values.reshape(-1, heads * head_dim), weights["wo"].reshape(heads * head_dim, d),
              dtype)
    return (out + weights["bo"]).reshape(b, q, n, d)


def shared_kv_cross_attention(x, context_norm, mask, shift, scale, weights, dtype=None):
    """Cross-attention that projects the modulated context once per query, shared by its N rows.

    Same arguments and result as :func:`absorbed_cross_attention`; cheaper with several rows
    per query.
    """
    b, q, n, d = x.shape
    heads, head_dim = weights["wq"].shape[1:]
    s = context_norm.shape[1]
    m = modulate(context_norm[:, None], shift[:, :, None, :], scale[:, :, None, :])  # (B,Q,S,D)
    w_kv = jnp.concatenate([weights["wk"].reshape(d, -1), weights["wv"].reshape(d, -1)], axis=1)
    b_kv = jnp.concatenate([weights["bk"].reshape(-1), weights["bv"].reshape(-1)])
    kv = (dot(m.reshape(-1, d), w_kv, dtype) + b_kv).reshape(b * q, s, 2, heads, head_dim)
    query = (dot(x.reshape(-1, d), weights["wq"].reshape(d, -1), dtype) + weights["bq"].reshape(-1))
    query = query.reshape(b * q, n, heads, head_dim) / math.sqrt(head_dim)
    scores = einsum("xnhk,xshk->xhns", query, kv[:, :, 0], dtype)  # (B·Q, H, N, S)
    key_mask = jnp.broadcast_to(mask[:, None], (b, q, s)).reshape(b * q, 1, 1, s)
    attn = _masked_softmax(scores, key_mask)
    values = einsum("xhns,xshk->xnhk", attn, kv[:, :, 1], dtype).reshape(-1, heads * head_dim)
    out = dot(values, weights["wo"].reshape(heads * head_dim, d), dtype) + weights["bo"]
    return out.reshape(b, q, n, d)


def cross_attention(x, context_norm, mask, shift, scale, weights, dtype=None):
    """Modulated cross-attention: :func:`absorbed_cross_attention` for one row per query,
    :func:`shared_kv_cross_attention` for several (the faster exact form for the static N)."""
    rows = x.shape[2]
    form = absorbed_cross_attention if rows == 1 else shared_kv_cross_attention
    return form(x, context_norm, mask, shift, scale, weights, dtype)


def plain_cross_attention(x, context_norm, mask, shift, scale, weights, dtype=None):
    """Reference cross-attention forming the modulated context per query (tests only)."""
    head_dim = weights["wq"].shape[-1]
    m = modulate(context_norm[:, None], shift[:, :, None, :], scale[:, :, None, :])  # (B,Q,S,D)
    q = einsum("bqnd,dhk->bqnhk", x, weights["wq"], dtype) + weights["bq"]
    k = einsum("bqsd,dhk->bqshk", m, weights["wk"], dtype) + weights["bk"]
    v = einsum("bqsd,dhk->bqshk", m, weights["wv"], dtype) + weights["bv"]
    scores = einsum("bqnhk,bqshk->bqnhs", q, k, dtype) / math.sqrt(head_dim)
    attn = _masked_softmax(scores, mask[:, None, None, None, :])
    values = einsum("bqnhs,bqshk->bqnhk", attn, v, dtype)
    return einsum("bqnhk,hkd->bqnd", values, weights["wo"], dtype) + weights["bo"]


class ModulatedCrossAttention(nn.Module):
    """Holds the attention weights and applies :func:`cross_attention`."""

    dim: int
    heads: int
    precision: str = "float32"

    @nn.compact
    def __call__(self, x, context_norm, mask, shift, scale):
        head_dim = self.dim // self.heads
        proj_init = nn.initializers.lecun_normal(in_axis=0, out_axis=(1, 2))
        out_init = nn.initializers.lecun_normal(in_axis=(0, 1), out_axis=2)
        zeros = nn.initializers.zeros_init()
        shape_in, shape_b = (self.dim, self.heads, head_dim), (self.heads, head_dim)
        weights = {
            "wq": self.param("wq", proj_init, shape_in), "bq": self.param("bq", zeros, shape_b),
            "wk": self.param("wk", proj_init, shape_in), "bk": self.param("bk", zeros, shape_b),
            "wv": self.param("wv", proj_init, shape_in), "bv": self.param("bv", zeros, shape_b),
            "wo": self.param("wo", out_init, (self.heads, head_dim, self.dim)),
            "bo": self.param("bo", zeros, (self.dim,)),
        }
        return cross_attention(x, context_norm, mask, shift, scale, weights,
                               compute_dtype(self.precision))


class CDiTBlock(nn.Module):
    """One cross-attention-only CDiT block. x (B, Q, N, D), c (B, Q, D), context (B, S, D)."""

    dim: int
    heads: int
    mlp_ratio: int
    dropout: float
    precision: str = "float32"

    @nn.compact
    def __call__(self, x, c, context, mask, deterministic: bool):
        mod = FlatDense(8 * self.dim, kernel_init=nn.initializers.zeros_init(),  # once per query
                        precision=self.precision, name="adaln_modulation")(nn.silu(c))
        (shift_ctx, scale_ctx, shift_ca, scale_ca, gate_ca,
         shift_mlp, scale_mlp, gate_mlp) = jnp.split(mod, 8, axis=-1)
        rows = lambda a: a[:, :, None, :]  # noqa: E731  (B, Q, D) → (B, Q, 1, D)
        h = modulate(_layer_norm(x), rows(shift_ca), rows(scale_ca))
        h = ModulatedCrossAttention(self.dim, self.heads, self.precision, name="cross_attn")(
            h, _layer_norm(context), mask, shift_ctx, scale_ctx)
        x = x + rows(gate_ca) * nn.Dropout(self.dropout)(h, deterministic=deterministic)
        h = modulate(_layer_norm(x), rows(shift_mlp), rows(scale_mlp))
        h = FeedForward(self.dim, self.mlp_ratio, self.dropout, self.precision, name="mlp")(
            h, deterministic)
        return x + rows(gate_mlp) * nn.Dropout(self.dropout)(h, deterministic=deterministic)


class FinalLayer(nn.Module):
    """AdaLN (shift/scale from c) + zero-initialised projection to the 4 box numbers
    (``out_dim=None``: the modulated rows themselves, for a read-out head)."""

    dim: int
    out_dim: int | None = 4
    precision: str = "float32"

    @nn.compact
    def __call__(self, x, c):
        mod = FlatDense(2 * self.dim, kernel_init=nn.initializers.zeros_init(),
                        precision=self.precision, name="adaln_modulation")(nn.silu(c))
        shift, scale = jnp.split(mod, 2, axis=-1)
        h = modulate(_layer_norm(x), shift[:, :, None, :], scale[:, :, None, :])
        if self.out_dim is None:
            return h
        return FlatDense(self.out_dim, kernel_init=nn.initializers.zeros_init(),
                         precision=self.precision, name="proj")(h)
