"""Distance kernels that cannot underflow: weights ∝ exp(−d / L) for any accepted length L
(where every exp(−d / L) of a row would underflow, the row's softmax less its largest logit;
elsewhere the plain exponentials, to the bit).
"""

from __future__ import annotations

import jax.numpy as jnp

PLAIN_FLOOR = 1e-30
"""A row whose plain weights sum to less than this is computed with the largest logit taken
out (float32's smallest normal number is about 1.2e-38)."""


def distance_weights(others, distance, length) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Unnormalised weights (..., F, F) float32 ∝ exp(−distance / length) on the ``others``
    (..., F, F) bool, zero elsewhere, and their row totals (..., F, 1): 0 exactly for a row
    with no others, else positive (the kernel is weights / totals)."""
    plain = jnp.where(others, jnp.exp(-distance / length), 0.0)
    plain_total = jnp.sum(plain, axis=-1, keepdims=True)
    logits = jnp.where(others, -distance / length, -jnp.inf)
    top = jnp.max(logits, axis=-1, keepdims=True)
    shifted = jnp.where(others, jnp.exp(logits - jnp.where(jnp.isfinite(top), top, 0.0)), 0.0)
    shifted_total = jnp.sum(shifted, axis=-1, keepdims=True)
    lost = plain_total < PLAIN_FLOOR
    return (jnp.where(lost, shifted, plain), jnp.where(lost, shifted_total, plain_total))
