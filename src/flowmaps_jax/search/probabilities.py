"""Table probabilities: where a prior puts the object, as mass on the map's tables.

One layout for every prior, the array a planner consumes::

    probs = table_probabilities(predictor, tokens, queries, num_samples=100, key=key)
    probs.shape == (B, Q, S + 1)   # S token slots of the map, then the "off" mass

Entry ``[b, q, s]`` is the mass on furniture token ``s`` of scene ``b`` for query ``q``; entries
of object tokens and padding are exactly zero; the last entry is the mass on no table ("off").
Each row sums to 1.

* **Sampled priors** (FlowMaps, the MLP baseline): ``num_samples`` boxes per query, assigned by
  the evaluation protocol's rule (v2, ``evaluation.slots``) over every table of the map instead of
  the K tables of the object's kind: a sample counts for the table whose centre is nearest to the
  sample's centre, unless that distance exceeds max(:data:`ASSIGN_TOLERANCE`, 3 · 0.35 × the
  object's longer side), when it is "off". The object's size is read from its own token at τ
  (objects keep their size); on a table it stands at the table's centre. On a 256 px map 0.05 is
  12.75 px. Models that give their table weights explicitly (FlowMaps' pointer and route
  heads, ``Predictor.table_weights``) can instead be read without sampling:
  ``method="weights"`` (:func:`table_probabilities`).
* **Exact priors** (FlowSim's exact posterior, uniform over the kind, last-seen) are slot
  distributions along the object's visiting order; :func:`slots_to_tables` puts slot ``k``'s mass
  on the table ``visit_order[k]`` (furniture tokens come first in ``scene_tokens``, so a furniture
  index is its token index). Their off mass is 0.

:func:`table_dict` gives the same numbers as plain Python dicts keyed by table (token) index,
for planners outside JAX.

Public functions check their arguments once; :func:`table_probabilities_core` and
:func:`slots_to_tables_core` are their unchecked cores, which the search set
(:mod:`.episodes`) calls on the FlowSim arrays it built.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.evaluation import slots as slot_metrics
from flowmaps_jax.tokens import FURNITURE, OBJECT, Queries, SceneTokens
from flowmaps_jax.validation import check_instance, check_int

ASSIGN_TOLERANCE = slot_metrics.ASSIGN_RADIUS
"""The least assignment radius (normalised units; the evaluation protocol's): a sample whose centre
is this close to a table's centre counts for the nearest table."""
OFF = "off"
"""Key of the off-table mass in :func:`table_dict`."""


# --------------------------------------------------------------------------- table boxes


def _check_pair(tokens: Any, queries: Any) -> tuple[int, int, int]:
    """(B, S, Q) of SceneTokens (B, S) and Queries (B, Q), or ValueError naming the argument."""
    check_instance("tokens", tokens, SceneTokens)
    check_instance("queries", queries, Queries)
    box_shape = np.shape(tokens.boxes)
    if len(box_shape) != 3 or box_shape[-1] != 4:
        raise ValueError(f"tokens.boxes must have shape (B, S, 4); got {box_shape}")
    q_shape = np.shape(queries.descriptor)
    if len(q_shape) != 2 or q_shape[0] != box_shape[0]:
        raise ValueError(f"queries.descriptor must have shape (B={box_shape[0]}, Q); got "
                         f"{q_shape}")
    return box_shape[0], box_shape[1], q_shape[1]


def _object_matches(tokens: SceneTokens, queries: Queries) -> jnp.ndarray:
    """(B, Q, S) bool: the real object tokens whose descriptor is the query's."""
    is_object = jnp.asarray(tokens.mask, bool) & (jnp.asarray(tokens.kind) == OBJECT)
    same = jnp.asarray(queries.descriptor)[:, :, None] == jnp.asarray(tokens.descriptor)[:, None]
    return same & is_object[:, None, :]


@jax.jit
def _table_boxes(tokens: SceneTokens, queries: Queries) -> tuple[jnp.ndarray, jnp.ndarray]:
    match = _object_matches(tokens, queries).astype(jnp.float32)  # (B, Q, S)
    size = jnp.einsum("bqs,bsk->bqk", match, tokens.boxes[..., 2:]) / jnp.maximum(
        match.sum(-1, keepdims=True), 1.0)  # (B, Q, 2) object (h, w)
    table = tokens.boxes[:, None, :, :]  # (B, 1, S, 4)
    shape = (*size.shape[:2], table.shape[2], 2)
    centre = jnp.broadcast_to(table[..., :2] + 0.5 * table[..., 2:], shape)
    size = jnp.broadcast_to(size[:, :, None, :], shape)
    boxes = jnp.concatenate([centre - 0.5 * size, size], axis=-1)  # (B, Q, S, 4)
    is_table = jnp.asarray(tokens.mask, bool) & (jnp.asarray(tokens.kind) == FURNITURE)
    mask = jnp.broadcast_to(is_table[:, None, :], boxes.shape[:-1])
    return jnp.where(mask[..., None], boxes, 0.0), mask


def table_boxes(tokens: SceneTokens, queries: Queries) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Where the queried object would be on each table: its box centred on every table.

    tokens: SceneTokens (B, S); queries: Queries (B, Q). Returns ``boxes`` (B, Q, S, 4) normalised
    (y, x, h, w) (zeros on non-tables) and ``mask`` (B, Q, S) bool, True on furniture tokens.
    The object's (h, w) is that of its token in ``tokens`` (same descriptor, kind OBJECT); raises
    ``ValueError`` naming ``queries.descriptor`` if a queried object has no token in its map.
    """
    _check_pair(tokens, queries)
    counts = np.asarray(_object_matches(tokens, queries).sum(-1))
    if np.any(counts != 1):
        b, q = np.argwhere(counts != 1)[0]
        raise ValueError(f"queries.descriptor[{b}, {q}] must name exactly one object token of its "
                         f"map (its size places it on the tables); found {counts[b, q]}")
    return _table_boxes(tokens, queries)


# --------------------------------------------------------------------------- sampled priors


TABLE_METHODS = ("samples", "weights")
"""How :func:`table_probabilities` reads a model: by counting samples, or from explicit weights."""


def table_probabilities(predictor: Any, tokens: SceneTokens, queries: Queries,
                        num_samples: int, key: jax.Array, method: str = "samples",
                        **sample_kwargs) -> jnp.ndarray:
    """Mass on each table of the map from a sampling model → (B, Q, S + 1) float32.

    predictor: anything with :meth:`flowmaps_jax.predictor.Predictor.sample` (FlowMaps or the MLP
    baseline). tokens: SceneTokens (B, S). queries: Queries (B, Q). num_samples: N boxes per query.
    key: one typed PRNG key (``jax.random.key``) or one per scene (B,), as ``Predictor.sample``.
    Entry s < S is the fraction of the N samples assigned to furniture token s (see the module
    doc: tolerance :data:`ASSIGN_TOLERANCE`), entry S the fraction on no table. Extra keyword
    arguments (``num_steps``, ``solver``) go to ``predictor.sample`` (``solver`` as its
    ``method``).
    ``method="weights"``: a read-out head's explicit mixture weights instead
    (``predictor.table_weights``; ``num_samples`` and ``key`` unused), no sampling noise.
    """
    num_samples = check_table_method(predictor, method, num_samples)
    if method == "samples":
        table_boxes(tokens, queries)  # checks the pair: every queried object is on its map
    return table_probabilities_core(predictor, tokens, queries, num_samples, key, method,
                                    **sample_kwargs)


def check_table_method(predictor: Any, method: str, num_samples: int) -> int:
    """``ValueError`` unless ``predictor`` can give table probabilities by ``method``
    (:data:`TABLE_METHODS`); returns ``num_samples`` checked (≥ 1; "weights" does not use it,
    but it must still be an int ≥ 0)."""
    if method not in TABLE_METHODS:
        raise ValueError(f"method must be one of {TABLE_METHODS}; got {method!r}")
    if method == "weights":
        if not callable(getattr(predictor, "table_weights", None)):
            raise ValueError("method='weights' needs a predictor with table_weights (a FlowMaps "
                             f"Predictor with a read-out head); got {type(predictor).__name__}")
        return check_int("num_samples", num_samples, 0)
    if not callable(getattr(predictor, "sample", None)):
        raise ValueError(f"predictor must have a sample(tokens, queries, num_samples, key) method "
                         f"(a flowmaps_jax.predictor.Predictor); got {type(predictor).__name__}")
    return check_int("num_samples", num_samples)


def table_probabilities_core(predictor: Any, tokens: SceneTokens, queries: Queries,
                             num_samples: int, key: jax.Array, method: str = "samples",
                             **sample_kwargs) -> jnp.ndarray:
    """Core of :func:`table_probabilities`: no checks of the arguments (see
    :func:`check_table_method`) nor of the (tokens, queries) pair; the predictor's samples, its
    own output, are checked as they are assigned (:func:`.slots.empirical_slots`)."""
    if method == "weights":
        return predictor.table_weights(tokens, queries)
    boxes, mask = _table_boxes(tokens, queries)
    if "solver" in sample_kwargs:
        sample_kwargs["method"] = sample_kwargs.pop("solver")
    samples = predictor.sample(tokens, queries, num_samples, key, **sample_kwargs)
    return slot_metrics.empirical_slots(samples, boxes, mask, ASSIGN_TOLERANCE)


# --------------------------------------------------------------------------- exact priors


@functools.partial(jax.jit, static_argnames="num_tokens")
def _slots_to_tables(slot_probs, visit_order, num_tokens):
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
    probs = jnp.asarray(slot_probs, jnp.float32)
    order = np.shape(visit_order)
    if probs.shape[:-1] != order[:-1] or probs.shape[-1] not in (order[-1], order[-1] + 1):
        raise ValueError(f"slot_probs must have shape {order} or {(*order[:-1], order[-1] + 1)} "
                         f"to match visit_order; got {probs.shape}")
    if probs.shape[-1] == order[-1] + 1 and not bool(jnp.all(probs[..., -1] == 0)):
        raise ValueError("slot_probs has off mass; an exact prior puts all mass on slots")
    order_np = np.asarray(visit_order)
    if not np.issubdtype(order_np.dtype, np.integer) or np.any(order_np >= num_tokens):
        raise ValueError(f"visit_order must hold integer token indices < num_tokens={num_tokens} "
                         "(−1 for padding)")
    return slots_to_tables_core(probs, order_np, num_tokens)


def slots_to_tables_core(slot_probs, visit_order, num_tokens: int) -> jnp.ndarray:
    """Core of :func:`slots_to_tables` (no checks; an off bin, if any, is dropped)."""
    probs = jnp.asarray(slot_probs, jnp.float32)
    if probs.shape[-1] == np.shape(visit_order)[-1] + 1:
        probs = probs[..., :-1]
    return _slots_to_tables(probs, jnp.asarray(visit_order, jnp.int32), num_tokens)


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
