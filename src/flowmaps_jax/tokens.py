"""The arrays that cross from the simulator to the model: scene tokens and query batches.

This module is the contract between :mod:`flowmaps_jax.flowsim` (which produces these pytrees) and
:mod:`flowmaps_jax.model` / :mod:`flowmaps_jax.flow` (which consume them). It knows nothing of
either.

Conventions
-----------
* A box is ``(y, x, h, w)``: top-left corner and size, normalised to [0, 1] by dividing pixels by
  ``map_size - 1`` (as the reference code does). Centres are ``(y + h/2, x + w/2)``.
* Token order inside one scene: the F furniture pieces, then the M objects, then padding.
  ``mask`` is True for real tokens and False for padding.
* ``kind`` is the token's type flag: 0 = furniture, 1 = object.
* ``descriptor`` is the integer descriptor id (colour id in FlowSim: fork 0, bottle 1, remote 2,
  kitchen_table 3, office_desk 4, dining_table 5).
* Times ``tau`` (state time of the map) and ``tau_q`` (query time) are integer timesteps with
  ``0 <= tau < tau_q < num_timesteps``.
"""

from __future__ import annotations

import chex
import jax.numpy as jnp
import numpy as np
from flax import struct

from flowmaps_jax.validation import check_int

FURNITURE = 0
OBJECT = 1


def to_centre(boxes: jnp.ndarray) -> jnp.ndarray:
    """(..., 4) boxes (y, x, h, w) → (cy, cx, h, w). A shear with unit Jacobian."""
    boxes = jnp.asarray(boxes)
    y, x, h, w = jnp.moveaxis(boxes, -1, 0)
    return jnp.stack([y + h / 2, x + w / 2, h, w], axis=-1)


def from_centre(centres: jnp.ndarray) -> jnp.ndarray:
    """(..., 4) (cy, cx, h, w) → boxes (y, x, h, w); inverse of :func:`to_centre`."""
    centres = jnp.asarray(centres)
    cy, cx, h, w = jnp.moveaxis(centres, -1, 0)
    return jnp.stack([cy - h / 2, cx - w / 2, h, w], axis=-1)


@struct.dataclass
class SceneTokens:
    """One map at state time τ as padded tokens. Leading batch dims ``...`` are free.

    boxes: (..., S, 4) float32, normalised (y, x, h, w); zeros on padding.
    descriptor: (..., S) int32 descriptor ids; 0 on padding (masked out anyway).
    kind: (..., S) int32 type flag, FURNITURE or OBJECT; 0 on padding.
    mask: (..., S) bool, True for real tokens.
    tau: (...,) int32 state time of the map.
    """

    boxes: jnp.ndarray
    descriptor: jnp.ndarray
    kind: jnp.ndarray
    mask: jnp.ndarray
    tau: jnp.ndarray

    @property
    def num_tokens(self) -> int:
        return self.mask.shape[-1]


@struct.dataclass
class Queries:
    """Q queries per scene. Leading batch dims match the SceneTokens they refer to.

    descriptor: (..., Q) int32 descriptor id of the queried object.
    tau_q: (..., Q) int32 query time, strictly greater than the scene's tau.
    """

    descriptor: jnp.ndarray
    tau_q: jnp.ndarray


@struct.dataclass
class TrainBatch:
    """What one training step consumes: B scenes, Q queries each, with their ground truth.

    tokens: SceneTokens with leading dim (B,).
    queries: Queries with dims (B, Q).
    target: (B, Q, 4) float32 normalised (y, x, h, w) box of the queried object at tau_q.
    """

    tokens: SceneTokens
    queries: Queries
    target: jnp.ndarray


def validate_tokens(tokens: SceneTokens, num_descriptors: int, max_tokens: int | None = None,
                    name: str = "tokens") -> None:
    """Raise ``ValueError`` naming the field if ``tokens`` is malformed.

    Checks shapes agree, boxes lie in [0, 1] on real tokens, descriptors are known
    (``0 <= id < num_descriptors``), kinds are 0/1 and the token axis equals ``max_tokens``.
    Works on concrete (numpy or jax) arrays only; call it at public API boundaries, outside jit.
    """
    boxes = np.asarray(tokens.boxes)
    desc = np.asarray(tokens.descriptor)
    kind = np.asarray(tokens.kind)
    mask = np.asarray(tokens.mask)
    tau = np.asarray(tokens.tau)
    if boxes.ndim < 2 or boxes.shape[-1] != 4:
        raise ValueError(f"{name}.boxes must have shape (..., S, 4); got {boxes.shape}")
    lead = boxes.shape[:-1]
    for field, arr in (("descriptor", desc), ("kind", kind), ("mask", mask)):
        if arr.shape != lead:
            raise ValueError(
                f"{name}.{field} must have shape {lead} to match boxes; got {arr.shape}")
    if tau.shape != lead[:-1]:
        raise ValueError(f"{name}.tau must have shape {lead[:-1]}; got {tau.shape}")
    if max_tokens is not None and lead[-1] != max_tokens:
        raise ValueError(
            f"{name} has {lead[-1]} token slots but the model expects max_tokens={max_tokens}")
    if not np.issubdtype(desc.dtype, np.integer):
        raise ValueError(f"{name}.descriptor must be integer; got {desc.dtype}")
    real = mask.astype(bool)
    if not np.all(np.isfinite(boxes)):
        raise ValueError(f"{name}.boxes contains NaN or inf")
    if np.any((boxes < 0.0)[real] | (boxes > 1.0)[real]):
        raise ValueError(f"{name}.boxes must lie in [0, 1] (normalised y, x, h, w)")
    if np.any(((desc < 0) | (desc >= num_descriptors))[real]):
        bad = np.unique(desc[real & ((desc < 0) | (desc >= num_descriptors))])
        raise ValueError(f"{name}.descriptor has unknown ids {bad.tolist()} "
                         f"(known: 0..{num_descriptors - 1})")
    if np.any(((kind != FURNITURE) & (kind != OBJECT))[real]):
        raise ValueError(f"{name}.kind must be 0 (furniture) or 1 (object)")
    if not np.all(real.any(axis=-1)):
        raise ValueError(f"{name}.mask: every scene needs at least one real token")


def validate_queries(queries: Queries, tau: np.ndarray, num_descriptors: int, tau_max: int,
                     name: str = "queries") -> None:
    """Raise ``ValueError`` if a descriptor is unknown or ``tau_q`` is outside (tau, tau_max)."""
    desc = np.asarray(queries.descriptor)
    tau_q = np.asarray(queries.tau_q)
    tau = np.asarray(tau)
    if desc.shape != tau_q.shape:
        raise ValueError(f"{name}.descriptor {desc.shape} and {name}.tau_q {tau_q.shape} differ")
    if desc.shape[: tau.ndim] != tau.shape:
        raise ValueError(f"{name} leading dims {desc.shape} do not match tau {tau.shape}")
    if np.any((desc < 0) | (desc >= num_descriptors)):
        raise ValueError(f"{name}.descriptor has unknown ids (known: 0..{num_descriptors - 1})")
    tau_b = tau.reshape(tau.shape + (1,) * (tau_q.ndim - tau.ndim))
    if np.any(tau_q <= tau_b):
        raise ValueError(f"{name}.tau_q must be strictly greater than tau")
    if np.any(tau_q >= tau_max):
        raise ValueError(f"{name}.tau_q must be < tau_max={tau_max}")


def assert_batch_shapes(batch: TrainBatch) -> None:
    """chex shape assertions for a TrainBatch (usable inside jit: shapes are static)."""
    b, s = batch.tokens.mask.shape
    q = batch.queries.tau_q.shape[1]
    chex.assert_shape(batch.tokens.boxes, (b, s, 4))
    chex.assert_shape([batch.tokens.descriptor, batch.tokens.kind], (b, s))
    chex.assert_shape(batch.tokens.tau, (b,))
    chex.assert_shape([batch.queries.descriptor, batch.queries.tau_q], (b, q))
    chex.assert_shape(batch.target, (b, q, 4))


def trim_padding(tokens: SceneTokens, num_tokens: int) -> SceneTokens:
    """Keep the first ``num_tokens`` token slots, dropping trailing padding.

    Padding is masked out of every attention and pooling, so a model's output is unchanged as long
    as only padding is dropped (FlowSim scenes have F + M real tokens first). Training and
    inference call this with ``num_tokens = F + M`` to skip the attention work on empty slots.
    ``num_tokens`` must be static (a Python int). Shapes: (..., S, ·) → (..., num_tokens, ·).
    """
    if check_int("num_tokens", num_tokens) > tokens.num_tokens:
        raise ValueError(f"num_tokens must be in 1..{tokens.num_tokens}; got {num_tokens}")
    return tokens.replace(boxes=tokens.boxes[..., :num_tokens, :],
                          descriptor=tokens.descriptor[..., :num_tokens],
                          kind=tokens.kind[..., :num_tokens],
                          mask=tokens.mask[..., :num_tokens])
