"""Compute precision of the network's matmuls (``ModelConfig.precision``): ``"float32"`` plain
products; ``"bf16"`` bfloat16 operands with float32 accumulation and result (everything else
stays float32)."""

from __future__ import annotations

import jax.numpy as jnp

from flowmaps_jax.model.config import PRECISIONS
from flowmaps_jax.validation import check_choice

_DTYPES = {"float32": None, "bf16": jnp.bfloat16}


def compute_dtype(name: str):
    """Operand dtype of the matmuls for precision ``name``: None (plain float32) or bfloat16."""
    return _DTYPES[check_choice("precision", name, PRECISIONS)]


def dot(x: jnp.ndarray, w: jnp.ndarray, dtype=None) -> jnp.ndarray:
    """``x @ w``; with a ``dtype``, on operands cast to it and with a float32 result."""
    if dtype is None:
        return x @ w
    return jnp.matmul(x.astype(dtype), w.astype(dtype), preferred_element_type=jnp.float32)


def einsum(spec: str, a: jnp.ndarray, b: jnp.ndarray, dtype=None) -> jnp.ndarray:
    """``jnp.einsum(spec, a, b)``; with a ``dtype``, on operands cast to it, float32 result."""
    if dtype is None:
        return jnp.einsum(spec, a, b)
    return jnp.einsum(spec, a.astype(dtype), b.astype(dtype), preferred_element_type=jnp.float32)
