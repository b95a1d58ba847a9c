"""Where boxes land, shared by evaluation and search: the protocol's assignment of boxes to
slots (protocol v2, docs/protocol.md; :func:`empirical_slots`, the share (..., K + 1) of samples
(..., N, 4) on each slot, then off) and a model's table masses (:func:`table_probabilities`,
(B, Q, S + 1) over every table of the map, the last entry off). Public functions check once;
the jitted kernels check nothing.
"""

from __future__ import annotations

from functools import partial
from typing import Any, Protocol, runtime_checkable

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.tokens import FURNITURE, OBJECT, Queries, SceneTokens
from flowmaps_jax.validation import (
    check_array,
    check_choice,
    check_concrete,
    check_instance,
    check_int,
    check_mask,
    check_real,
)

CENTRE_SIGMA_SCALE = 0.35
"""Centre std of a mixture component of the protocol's q as a fraction of the box side (h for
cy, w for cx); the assignment radius grows with it."""
SIZE_SIGMA_SCALE = 0.02
"""Size std of a mixture component of the protocol's q as a fraction of the box side (h, w)."""
ASSIGN_RADIUS = 0.05
"""The least assignment radius (normalised units): a sample whose centre lies this close to a slot's
centre always counts for the nearest slot."""
ASSIGN_SIGMAS = 3.0
"""The radius grows to this many centre stds σ_c of the smoothed q (0.35 × the longer side)."""
ASSIGN_TOLERANCE = ASSIGN_RADIUS
"""The least assignment radius (normalised units; the evaluation protocol's)."""


@jax.jit
def protocol_sigma(boxes: jnp.ndarray) -> jnp.ndarray:
    """Boxes (..., 4) (y, x, h, w) → (..., 4) std of (cy, cx, h, w) of the protocol's smoothed q
    around each: (0.35 h, 0.35 w, 0.02 h, 0.02 w). Unchecked."""
    h, w = boxes[..., 2], boxes[..., 3]
    return jnp.stack([CENTRE_SIGMA_SCALE * h, CENTRE_SIGMA_SCALE * w,
                      SIZE_SIGMA_SCALE * h, SIZE_SIGMA_SCALE * w], axis=-1)


# --------------------------------------------------------------------------- the assignment


def assign_radius(slot_boxes: jnp.ndarray) -> jnp.ndarray:
    """Per-slot radius of the assignment: max(ASSIGN_RADIUS, ASSIGN_SIGMAS · 0.35 · max(h, w)).

    slot_boxes (..., K, 4) (y, x, h, w) → (..., K)."""
    side = jnp.maximum(slot_boxes[..., 2], slot_boxes[..., 3])
    return jnp.maximum(ASSIGN_RADIUS, ASSIGN_SIGMAS * CENTRE_SIGMA_SCALE * side)


@jax.jit
def assign_slots(samples, slot_boxes, slot_mask, radius=ASSIGN_RADIUS):
    """(..., N) int slot index of each sample: the slot with the nearest object centre, K ("off")
    beyond its :func:`assign_radius`; no checks (samples and slot_boxes float32, slot_mask bool)."""
    centre = lambda b: b[..., :2] + 0.5 * b[..., 2:]  # noqa: E731
    diff = centre(samples)[..., :, None, :] - centre(slot_boxes)[..., None, :, :]  # (..., N, K, 2)
    limit = jnp.maximum(radius, assign_radius(slot_boxes))  # (..., K)
    dist = jnp.sqrt(jnp.sum(diff**2, axis=-1))
    dist = jnp.where(slot_mask[..., None, :], dist, jnp.inf)
    nearest = jnp.argmin(dist, axis=-1)
    closest = jnp.min(dist, axis=-1)
    within = closest < jnp.take_along_axis(limit[..., None, :], nearest[..., None], axis=-1)[..., 0]
    return jnp.where(within, nearest, slot_boxes.shape[-2]).astype(jnp.int32)


@partial(jax.jit, static_argnames="num_slots")
def histogram(assignment, num_slots):
    """(..., K + 1) float32 share of the N assignments (..., N) in each of K slots + off."""
    return jnp.mean(jax.nn.one_hot(assignment, num_slots + 1), axis=-2)


def empirical_slots(samples: jnp.ndarray, slot_boxes: jnp.ndarray, slot_mask: jnp.ndarray,
                    radius: float = ASSIGN_RADIUS) -> jnp.ndarray:
    """p̂ of samples under the protocol's assignment (:func:`assign_slots`), else off.

    samples: (..., N, 4). slot_boxes: (..., K, 4), the same leading dims. slot_mask: (..., K)
    bool (or 0/1). radius: the least radius, > 0.
    Returns (..., K + 1) float32 counts / N: the K slots then the off bin.
    """
    check_array("samples", samples, (..., None, 4))
    lead = tuple(samples.shape[:-2])
    check_array("slot_boxes", slot_boxes, (*lead, None, 4))
    num_slots = slot_boxes.shape[-2]
    slot_mask = check_mask("slot_mask", slot_mask, (*lead, num_slots))
    radius = check_real("radius", radius, 0.0, low_open=True)
    assignment = assign_slots(jnp.asarray(samples, jnp.float32),
                              jnp.asarray(slot_boxes, jnp.float32), jnp.asarray(slot_mask, bool),
                              radius)
    return histogram(assignment, num_slots)


# --------------------------------------------------------------------------- table masses


@jax.jit  # one program, not one per operation (check_query_objects calls it eagerly)
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
    The object's (h, w) is that of its token (:func:`check_query_objects`).
    """
    check_query_objects(tokens, queries)
    return _table_boxes(tokens, queries)


def check_query_objects(tokens: SceneTokens, queries: Queries) -> None:
    """``ValueError`` naming ``queries.descriptor`` unless every queried object has exactly one
    token in its map at τ (``age`` 0)."""
    check_concrete("the table masses", tokens, queries)
    check_instance("tokens", tokens, SceneTokens)
    check_array("tokens.boxes", tokens.boxes, (None, None, 4))
    check_instance("queries", queries, Queries)
    check_array("queries.descriptor", queries.descriptor, (tokens.boxes.shape[0], None))
    matches = np.asarray(_object_matches(tokens, queries))
    if tokens.age is not None:  # a history's past maps hold the object again: its map is age 0
        matches = matches & (np.asarray(tokens.age) == 0)[:, None, :]
    counts = matches.sum(-1)
    if np.any(counts != 1):
        b, q = np.argwhere(counts != 1)[0]
        raise ValueError(f"queries.descriptor[{b}, {q}] must name exactly one object token of its "
                         f"map (its size places it on the tables); found {counts[b, q]}")


# --------------------------------------------------------------------------- sampled priors


TABLE_METHODS = ("samples", "weights")
"""How :func:`table_probabilities` reads a model: by counting samples, or from explicit weights."""


@runtime_checkable
class SamplingModel(Protocol):
    """What ``method="samples"`` reads: a model with ``sample`` (a
    :class:`flowmaps_jax.predictor.Predictor`: FlowMaps or the MLP baseline)."""

    def sample(self, tokens, queries, num_samples, key, **kwargs): ...


@runtime_checkable
class WeightsModel(Protocol):
    """What ``method="weights"`` reads: a model with ``table_weights`` (a FlowMaps
    :class:`flowmaps_jax.predictor.Predictor` with a read-out head)."""

    def table_weights(self, tokens, queries): ...


_MODELS = {"samples": SamplingModel, "weights": WeightsModel}


def table_probabilities(predictor: Any, tokens: SceneTokens, queries: Queries,
                        num_samples: int, key: jax.Array, method: str = "samples",
                        **sample_kwargs) -> jnp.ndarray:
    """Mass on each table of the map from a sampling model → (B, Q, S + 1) float32.

    predictor: a :class:`SamplingModel`; tokens (B, S); queries (B, Q); num_samples N per query;
    key: one typed PRNG key or one per scene (B,). Entry s < S is the fraction of samples on
    furniture token s, entry S off every table. ``method="weights"``: a read-out head's mixture
    weights instead (:class:`WeightsModel`; ``num_samples`` and ``key`` unused).
    """
    method = check_choice("method", method, TABLE_METHODS)
    # "weights" does not use num_samples: >= 0 will do
    num_samples = check_int("num_samples", num_samples, 0 if method == "weights" else 1)
    check_instance("predictor", predictor, _MODELS[method])
    check_query_objects(tokens, queries)  # every method: every queried object is on its map
    if method == "weights":
        return predictor.table_weights(tokens, queries)
    boxes, mask = table_boxes(tokens, queries)
    if "solver" in sample_kwargs:
        sample_kwargs["method"] = sample_kwargs.pop("solver")
    samples = predictor.sample(tokens, queries, num_samples, key, **sample_kwargs)
    return empirical_slots(samples, boxes, mask, ASSIGN_TOLERANCE)  # checks the model's samples

