"""Sinusoidal features and the small MLP embedders built on them (continuous inputs); integer
inputs use ``flax.linen.Embed`` tables."""

from __future__ import annotations

import flax.linen as nn
import jax.numpy as jnp

from flowmaps_jax.model.precision import compute_dtype, dot

default_kernel_init = nn.initializers.lecun_normal()


class FlatDense(nn.Module):
    """``nn.Dense`` (same parameters and result) as one 2-D GEMM over the flattened leading dims:
    (..., K) → (..., features); ``precision`` sets the operand dtype (float32 result)."""

    features: int
    kernel_init: nn.initializers.Initializer = default_kernel_init
    use_bias: bool = True
    precision: str = "float32"

    @nn.compact
    def __call__(self, x: jnp.ndarray) -> jnp.ndarray:
        kernel = self.param("kernel", self.kernel_init, (x.shape[-1], self.features))
        y = dot(x.reshape(-1, x.shape[-1]), kernel, compute_dtype(self.precision))
        if self.use_bias:
            y = y + self.param("bias", nn.initializers.zeros_init(), (self.features,))
        return y.reshape(*x.shape[:-1], self.features)


def sinusoidal_embedding(x: jnp.ndarray, num_freqs: int, max_frequency: float) -> jnp.ndarray:
    """Sin/cos features at ``num_freqs`` geometric frequencies in [1, max_frequency]: x (..., K)
    → (..., K * 2 * num_freqs), per scalar [sin..., cos...]."""
    freqs = jnp.geomspace(1.0, max_frequency, num_freqs, dtype=jnp.float32)
    angles = x[..., None].astype(jnp.float32) * freqs  # (..., K, F)
    feats = jnp.concatenate([jnp.sin(angles), jnp.cos(angles)], axis=-1)  # (..., K, 2F)
    return feats.reshape(*x.shape[:-1], x.shape[-1] * 2 * num_freqs)


class SinusoidalMLP(nn.Module):
    """Embed K scalars: sinusoidal features → Dense → GELU → Dense. (..., K) → (..., dim)."""

    dim: int
    num_freqs: int
    max_frequency: float
    precision: str = "float32"

    @nn.compact
    def __call__(self, x: jnp.ndarray) -> jnp.ndarray:
        h = sinusoidal_embedding(x, self.num_freqs, self.max_frequency)
        h = FlatDense(self.dim, name="in", precision=self.precision)(h)
        return FlatDense(self.dim, name="out", precision=self.precision)(nn.gelu(h))
