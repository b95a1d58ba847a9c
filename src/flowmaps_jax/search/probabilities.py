"""Table probabilities of the exact priors, and every prior's as plain Python dicts.

One layout for every prior, the array a planner consumes::

    probs = table_probabilities(predictor, tokens, queries, num_samples=100, key=key)
    probs.shape == (B, Q, S + 1)   # S token slots of the map, then the "off" mass

Entry ``[b, q, s]`` is the mass on furniture token ``s`` of scene ``b`` for query ``q``; entries
of object tokens and padding are exactly zero; the last entry is the mass on no table ("off").
Each row sums to 1.

* **Sampled priors** (FlowMaps, the MLP baseline) and models with explicit table weights:
  :func:`flowmaps_jax.tables.table_probabilities` (below the predictor, which offers it as
  ``Predictor.table_probabilities``; ``search.table_probabilities`` is the same function): the
  samples assigned to the tables by the evaluation protocol's rule.
* **Exact priors** (FlowSim's exact posterior, uniform over the kind, last-seen) are slot
  distributions along the object's visiting order; :func:`slots_to_tables` puts slot ``k``'s mass
  on the table ``visit_order[k]`` (furniture tokens come first in ``scene_tokens``, so a furniture
  index is its token index). Their off mass is 0.

:func:`table_dict` gives the same numbers as plain Python dicts keyed by table (token) index,
for planners outside JAX.

:func:`slots_to_tables` checks its arguments once and runs the jitted kernel
:func:`spread_over_tables`, which checks nothing and which the search set (:mod:`.episodes`) runs
on the FlowSim arrays it built.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.tokens import FURNITURE, SceneTokens
from flowmaps_jax.validation import check_int, check_int_array

OFF = "off"
"""Key of the off-table mass in :func:`table_dict`."""


# --------------------------------------------------------------------------- exact priors


@functools.partial(jax.jit, static_argnames="num_tokens")
def spread_over_tables(slot_probs, visit_order, num_tokens: int):
    """The kernel of :func:`slots_to_tables` (no checks): slot_probs (..., F) or (..., F + 1)
    (its off bin dropped), visit_order (..., F) int, −1 padded → (..., S + 1)."""
    if slot_probs.shape[-1] == visit_order.shape[-1] + 1:
        slot_probs = slot_probs[..., :-1]
    target = jnp.where(visit_order >= 0, visit_order, num_tokens)  # padding → the off bin
    onehot = jax.nn.one_hot(target, num_tokens + 1, dtype=jnp.float32)  # (..., F, S + 1)
    return jnp.einsum("...f,...fs->...s", slot_probs, onehot)


def slots_to_tables(slot_probs, visit_order, num_tokens: int) -> jnp.ndarray:
    """A slot distribution along a visiting order as table probabilities.

    slot_probs: (..., F) mass on position k of the visiting order (zero beyond K), e.g.
    ``flowsim.exact_posterior``, or (..., F + 1) with an off bin last (``uniform_slots``,
    ``last_seen_slots``; its off mass must be 0). visit_order: (..., F) int furniture
    (token) index of each position, −1 padded (``Scenes.visit_order``). num_tokens: S.
    Returns (..., S + 1): slot k's mass on token ``visit_order[k]``, zeros elsewhere, off 0.
    """
    num_tokens = check_int("num_tokens", num_tokens)
    visit_order = check_int_array("visit_order", visit_order, None, num_tokens - 1)
    probs = jnp.asarray(slot_probs, jnp.float32)
    order = np.shape(visit_order)
    if probs.shape[:-1] != order[:-1] or probs.shape[-1] not in (order[-1], order[-1] + 1):
        raise ValueError(f"slot_probs must have shape {order} or {(*order[:-1], order[-1] + 1)} "
                         f"to match visit_order; got {probs.shape}")
    if probs.shape[-1] == order[-1] + 1 and not bool(jnp.all(probs[..., -1] == 0)):
        raise ValueError("slot_probs has off mass; an exact prior puts all mass on slots")
    return spread_over_tables(probs, jnp.asarray(visit_order, jnp.int32), num_tokens)


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
