"""Sinusoidal features and the small MLP embedders built on them.

Every continuous input of the model (the 4 box numbers of a scene token, the 4 numbers of the
noisy query box X_t, the flow time t) goes through ``sinusoidal_embedding`` then an MLP; integer
inputs (descriptor, type flag, τ, τ_q) use ``flax.linen.Embed`` tables directly.
"""

from __future__ import annotations

import flax.linen as nn
import jax.numpy as jnp

from flowmaps_jax.model.precision import compute_dtype, dot

default_kernel_init = nn.initializers.lecun_normal()


class FlatDense(nn.Module):
    """``nn.Dense`` that flattens leading dims first: (..., K) → (..., features).

    Same parameters (``kernel`` (K, features), ``bias``) and result as ``nn.Dense``, but the matmul
    (and its backward) is a single 2-D GEMM: XLA on CPU runs the weight gradient of a dot with
    several contracted batch dims 2–5× slower than the same product on a (rows, K) matrix.
    ``precision`` ("float32" or "bf16", :mod:`~flowmaps_jax.model.precision`) sets the matmul's
    operand dtype; the kernel is stored and the result returned in float32 either way.
    """

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
    """Sin/cos features of each scalar at ``num_freqs`` geometric frequencies in [1, max_frequency].

    x: (..., K) scalars → (..., K * 2 * num_freqs), laid out per scalar as [sin..., cos...].
    """
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
