"""The arrays that cross from the simulator to the model (the contract; it knows neither): scene
tokens and query batches. A box is ``(y, x, h, w)`` normalised by ``map_size - 1``; tokens are
the F furniture pieces, then the M objects, then padding (``mask`` False); ``kind`` 0 furniture,
1 object; ``descriptor`` an integer id; ``0 <= tau < tau_q < num_timesteps``.
"""

from __future__ import annotations

from collections.abc import Collection

import jax.numpy as jnp
import numpy as np
from flax import struct

from flowmaps_jax.validation import (
    check_array,
    check_instance,
    check_int,
    check_int_array,
    check_mask,
    check_real_array,
    check_shape,
    is_concrete,
)

FURNITURE = 0
OBJECT = 1


@struct.dataclass
class SceneTokens:
    """One map at state time τ as padded tokens. Leading batch dims ``...`` are free.

    boxes: (..., S, 4) float32, normalised (y, x, h, w); zeros on padding.
    descriptor: (..., S) int32 descriptor ids; 0 on padding (masked out anyway).
    kind: (..., S) int32 type flag, FURNITURE or OBJECT; 0 on padding.
    mask: (..., S) bool, True for real tokens.
    tau: (...,) int32 state time of the map.
    age: None (one map), or (..., S) int32 how many steps before τ each token was seen.
    """

    boxes: jnp.ndarray
    descriptor: jnp.ndarray
    kind: jnp.ndarray
    mask: jnp.ndarray
    tau: jnp.ndarray
    age: jnp.ndarray | None = None

    @property
    def num_tokens(self) -> int:
        return np.shape(self.mask)[-1]


@struct.dataclass
class Queries:
    """Q queries per scene: descriptor (..., Q) int32 of the queried object, tau_q (..., Q) int32
    query time > the scene's tau."""

    descriptor: jnp.ndarray
    tau_q: jnp.ndarray


@struct.dataclass
class TrainBatch:
    """One training step's input: tokens (B,), queries (B, Q) and target (B, Q, 4) float32, the
    queried object's box at tau_q."""

    tokens: SceneTokens
    queries: Queries
    target: jnp.ndarray


def _array(name: str, value):
    """``value`` itself, an array (numpy or jax, not a list) unless it is None (then the check
    of its kind names it)."""
    return value if value is None else check_array(name, value)


def validate_tokens(tokens: SceneTokens, num_descriptors: int, max_tokens: int | None = None,
                    num_timesteps: int | None = None) -> None:
    """Raise ``ValueError`` naming the field if ``tokens`` (concrete arrays) is malformed: shapes,
    boxes in [0, 1], known descriptors and kinds on real tokens, tau in 0..num_timesteps − 2,
    a real token in every scene."""
    num_descriptors = check_int("num_descriptors", num_descriptors)
    if max_tokens is not None:
        max_tokens = check_int("max_tokens", max_tokens)
    if num_timesteps is not None:
        num_timesteps = check_int("num_timesteps", num_timesteps)
    check_instance("tokens", tokens, SceneTokens)
    boxes = check_real_array("tokens.boxes", _array("tokens.boxes", tokens.boxes),
                             (..., max_tokens, 4))
    *lead, s = boxes.shape[:-1]
    per_token = (*lead, s)
    descriptor = check_int_array("tokens.descriptor",
                                 _array("tokens.descriptor", tokens.descriptor), shape=per_token)
    kind = check_int_array("tokens.kind", _array("tokens.kind", tokens.kind), shape=per_token)
    mask = check_mask("tokens.mask", _array("tokens.mask", tokens.mask), per_token)
    check_int_array("tokens.tau", _array("tokens.tau", tokens.tau), 0,
                    None if num_timesteps is None else num_timesteps - 2, shape=tuple(lead))
    if tokens.age is not None:
        check_int_array("tokens.age", _array("tokens.age", tokens.age), 0, shape=per_token)
    if is_concrete(boxes, descriptor, kind, mask):  # the bounds hold on real tokens only
        real = np.asarray(mask, bool)
        check_real_array("tokens.boxes", np.asarray(boxes)[real], low=0.0, high=1.0,
                         what="normalised y, x, h, w")
        check_int_array("tokens.descriptor", np.asarray(descriptor)[real], 0,
                        num_descriptors - 1)
        check_int_array("tokens.kind", np.asarray(kind)[real], FURNITURE, OBJECT)
    if not np.all(np.asarray(tokens.mask, bool).any(axis=-1)):
        raise ValueError("tokens.mask: every scene needs at least one real token")


def validate_queries(queries: Queries, tau, num_descriptors: int, tau_max: int,
                     object_descriptors: Collection[int] | None = None) -> None:
    """Raise ``ValueError`` if ``queries`` are not (*B, Q) integers for scenes at ``tau`` (*B,),
    with known descriptors (``object_descriptors`` when given) and tau < tau_q < tau_max."""
    num_descriptors = check_int("num_descriptors", num_descriptors)
    tau_max = check_int("tau_max", tau_max)
    tau = check_int_array("tau", tau)
    check_instance("queries", queries, Queries)
    descriptor = check_int_array("queries.descriptor",
                                 _array("queries.descriptor", queries.descriptor), 0,
                                 num_descriptors - 1, shape=(*np.shape(tau), None))
    check_int_array("queries.tau_q", _array("queries.tau_q", queries.tau_q), None, tau_max - 1,
                    shape=np.shape(descriptor))
    if object_descriptors is not None:
        desc = np.asarray(queries.descriptor)
        wrong = ~np.isin(desc, np.asarray(list(object_descriptors), np.int64))
        if np.any(wrong):
            raise ValueError(f"queries.descriptor must name object categories "
                             f"{sorted(int(d) for d in object_descriptors)}; got "
                             f"{np.unique(desc[wrong]).tolist()} (furniture or unknown)")
    if np.any(np.asarray(queries.tau_q) <= np.asarray(tau)[..., None]):
        raise ValueError("queries.tau_q must be strictly greater than tau")


def check_train_batch(batch: TrainBatch) -> None:
    """A :class:`TrainBatch` whose arrays agree on B, S and Q, else a ValueError naming the array
    (shapes only: runs on tracers)."""
    if not isinstance(batch, TrainBatch):
        raise ValueError(f"batch must be a TrainBatch; got {type(batch).__name__}")
    tokens, queries = batch.tokens, batch.queries
    if not isinstance(tokens, SceneTokens) or not isinstance(queries, Queries):
        raise ValueError("batch must hold SceneTokens and Queries (batch.tokens, "
                         "batch.queries)")
    check_shape("batch.tokens.mask", np.shape(tokens.mask), (None, None))
    b, s = np.shape(tokens.mask)
    for name, value, shape in (("batch.tokens.boxes", tokens.boxes, (b, s, 4)),
                               ("batch.tokens.descriptor", tokens.descriptor, (b, s)),
                               ("batch.tokens.kind", tokens.kind, (b, s)),
                               ("batch.tokens.tau", tokens.tau, (b,)),
                               ("batch.queries.descriptor", queries.descriptor, (b, None))):
        check_shape(name, np.shape(value), shape)
    q = np.shape(queries.descriptor)[1]
    check_shape("batch.queries.tau_q", np.shape(queries.tau_q), (b, q))
    check_shape("batch.target", np.shape(batch.target), (b, q, 4))


def trim_padding(tokens: SceneTokens, num_tokens: int) -> SceneTokens:
    """Keep the first ``num_tokens`` (static) token slots, (..., S, ·) → (..., num_tokens, ·):
    the output is unchanged as long as only padding is dropped."""
    return tokens.replace(boxes=tokens.boxes[..., :num_tokens, :],
                          descriptor=tokens.descriptor[..., :num_tokens],
                          kind=tokens.kind[..., :num_tokens],
                          mask=tokens.mask[..., :num_tokens],
                          age=None if tokens.age is None else tokens.age[..., :num_tokens])
