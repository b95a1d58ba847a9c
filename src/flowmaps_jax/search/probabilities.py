"""Table probabilities of the exact priors, and every prior's as plain Python dicts.

One layout for every prior: ``probs`` (B, Q, S + 1), entry ``[b, q, s]`` the mass on furniture
token ``s`` (exactly zero on object tokens and padding), the last entry the "off" mass; rows
sum to 1. A model's are :func:`flowmaps_jax.tables.table_probabilities`; the exact priors' are
slot distributions along the visiting order, spread by :func:`spread_over_tables` (off mass 0);
:func:`table_dict` gives plain dicts keyed by table token index, for planners outside JAX.
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
    """Slot k's mass on table ``visit_order[k]``, no checks (the search set runs it on the
    FlowSim arrays it built): slot_probs (..., F), or (..., F + 1) with its off bin dropped;
    visit_order (..., F) int, −1 padded → (..., S + 1), off 0."""
    if slot_probs.shape[-1] == visit_order.shape[-1] + 1:
        slot_probs = slot_probs[..., :-1]
    target = jnp.where(visit_order >= 0, visit_order, num_tokens)  # padding → the off bin
    onehot = jax.nn.one_hot(target, num_tokens + 1, dtype=jnp.float32)  # (..., F, S + 1)
    return jnp.einsum("...f,...fs->...s", slot_probs, onehot)


# --------------------------------------------------------------------------- plain dicts


def table_dict(probs, tokens: SceneTokens) -> list:
    """Table probabilities (B, Q, S + 1) as plain Python: ``out[b][q]`` is a dict
    ``{table token index: probability, ..., "off": off mass}`` over every furniture token of scene
    b (floats and ints only, no arrays), for planners outside JAX."""
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
