"""Table probabilities of the exact priors, and every prior's as plain Python dicts. One layout:
``probs`` (B, Q, S + 1), the mass on each furniture token (zero on object tokens and padding),
then "off"; rows sum to 1.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.tokens import FURNITURE, SceneTokens

OFF = "off"
"""Key of the off-table mass in :func:`table_dict`."""


# --------------------------------------------------------------------------- exact priors


@functools.partial(jax.jit, static_argnames="num_tokens")
def spread_over_tables(slot_probs, visit_order, num_tokens: int):
    """Slot k's mass on table ``visit_order[k]`` (no checks): slot_probs (..., F or F + 1),
    visit_order (..., F) int, −1 padded → (..., S + 1), off 0."""
    if slot_probs.shape[-1] == visit_order.shape[-1] + 1:
        slot_probs = slot_probs[..., :-1]
    target = jnp.where(visit_order >= 0, visit_order, num_tokens)  # padding → the off bin
    onehot = jax.nn.one_hot(target, num_tokens + 1, dtype=jnp.float32)  # (..., F, S + 1)
    return jnp.einsum("...f,...fs->...s", slot_probs, onehot)


# --------------------------------------------------------------------------- plain dicts


def table_dict(probs, tokens: SceneTokens) -> list:
    """``out[b][q] = {table token index: probability, ..., "off": off mass}`` (plain Python)."""
    p = np.asarray(probs, np.float64)
    table = np.asarray(tokens.mask, bool) & (np.asarray(tokens.kind) == FURNITURE)
    if p.ndim != 3 or table.ndim != 2 or p.shape[0] != table.shape[0] \
            or p.shape[2] != table.shape[1] + 1:
        raise ValueError(f"probs must have shape (B, Q, S + 1) for tokens (B, S) = {table.shape}; "
                         f"got {p.shape}")
    out = []
    for b in range(p.shape[0]):  # host conversion for callers outside JAX, not a hot path
        index = np.flatnonzero(table[b]).tolist()
        out.append([{**dict(zip(index, row[index].tolist(), strict=True)), OFF: float(row[-1])}
                    for row in p[b]])
    return out
