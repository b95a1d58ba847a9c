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

from collections.abc import Collection

import chex
import jax.numpy as jnp
import numpy as np
from flax import struct

from flowmaps_jax.validation import (
    check_array,
    check_fields,
    check_instance,
    check_int,
    check_int_array,
    check_real_array,
)
from flowmaps_jax.validation.fields import IntArray, Mask

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
    age: None (one map, the paper's input), or (..., S) int32 how many steps before τ each
        token was seen: 0 for the map at τ, a for the object tokens of the map at τ − a (a
        model with ``ModelConfig.history`` = H reads the last H maps this way).
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
                    name: str = "tokens", num_timesteps: int | None = None) -> None:
    """Raise ``ValueError`` naming the field if ``tokens`` is malformed.

    Every field must be an array (numpy or jax, not a list): boxes real and finite, in [0, 1] on
    real tokens; descriptor, kind and tau integers; mask booleans (or 0/1 only). Shapes must
    agree, descriptors be known (``0 <= id < num_descriptors``), kinds 0/1, every scene hold a
    real token, the token axis equal ``max_tokens`` and, if ``num_timesteps`` is given, tau lie
    in 0..num_timesteps − 2. Works on concrete (numpy or jax) arrays; call it at public API
    boundaries, outside jit.
    """
    check_instance(name, tokens, SceneTokens)
    fields = {field: check_array(f"{name}.{field}", getattr(tokens, field))
              for field in ("boxes", "descriptor", "kind", "mask", "tau")}
    boxes = check_real_array(f"{name}.boxes", fields["boxes"], (..., None, 4))
    lead = boxes.shape[:-1]
    rules = {"descriptor": IntArray(shape=lead), "kind": IntArray(shape=lead),
             "mask": Mask(lead), "tau": IntArray(shape=lead[:-1])}
    checked = check_fields(tokens, rules, prefix=f"{name}.", store=False)
    desc, kind = np.asarray(checked["descriptor"]), np.asarray(checked["kind"])
    real = checked["mask"]
    if tokens.age is not None:
        check_int_array(f"{name}.age", check_array(f"{name}.age", tokens.age), 0, None,
                        shape=lead)
    if max_tokens is not None and lead[-1] != max_tokens:
        raise ValueError(
            f"{name} has {lead[-1]} token slots but the model expects max_tokens={max_tokens}")
    if np.any((boxes < 0.0)[real] | (boxes > 1.0)[real]):
        raise ValueError(f"{name}.boxes must lie in [0, 1] (normalised y, x, h, w)")
    unknown = real & ((desc < 0) | (desc >= num_descriptors))
    if np.any(unknown):
        raise ValueError(f"{name}.descriptor has unknown ids {np.unique(desc[unknown]).tolist()} "
                         f"(known: 0..{num_descriptors - 1})")
    if np.any(((kind != FURNITURE) & (kind != OBJECT))[real]):
        raise ValueError(f"{name}.kind must be 0 (furniture) or 1 (object)")
    if not np.all(real.any(axis=-1)):
        raise ValueError(f"{name}.mask: every scene needs at least one real token")
    if num_timesteps is not None:
        check_int_array(f"{name}.tau", fields["tau"], 0, num_timesteps - 2)


def validate_queries(queries: Queries, tau, num_descriptors: int, tau_max: int,
                     name: str = "queries",
                     object_descriptors: Collection[int] | None = None) -> None:
    """Raise ``ValueError`` if ``queries`` is malformed: fields not integer arrays, shapes that
    do not match ``tau`` (the scenes' state times), a descriptor unknown or, when
    ``object_descriptors`` is given, not one of them (a query names an object category, not a
    furniture kind), or ``tau_q`` outside (tau, tau_max)."""
    check_instance(name, queries, Queries)
    desc = check_int_array(f"{name}.descriptor",
                           check_array(f"{name}.descriptor", queries.descriptor),
                           0, num_descriptors - 1)
    tau_q = check_int_array(f"{name}.tau_q", check_array(f"{name}.tau_q", queries.tau_q),
                            None, tau_max - 1)
    tau = np.asarray(check_int_array("tau", tau))
    if desc.shape != tau_q.shape:
        raise ValueError(f"{name}.descriptor {desc.shape} and {name}.tau_q {tau_q.shape} differ")
    if desc.shape[: tau.ndim] != tau.shape:
        raise ValueError(f"{name} leading dims {desc.shape} do not match tau {tau.shape}")
    if object_descriptors is not None:
        check_query_roles(queries, object_descriptors, name)
    tau_b = np.reshape(tau, tau.shape + (1,) * (tau_q.ndim - tau.ndim))
    if np.any(tau_q <= tau_b):
        raise ValueError(f"{name}.tau_q must be strictly greater than tau")


def check_query_roles(queries: Queries, object_descriptors: Collection[int],
                      name: str = "queries") -> None:
    """Raise ``ValueError`` unless every query descriptor is one of ``object_descriptors``
    (e.g. ``FlowSimConfig.object_descriptors``): a query asks where an object is, so a
    furniture kind's descriptor (a table) is not a query."""
    desc = np.asarray(check_int_array(f"{name}.descriptor", queries.descriptor))
    wrong = ~np.isin(desc, np.asarray(list(object_descriptors), np.int64))
    if np.any(wrong):
        raise ValueError(f"{name}.descriptor must name object categories "
                         f"{sorted(int(d) for d in object_descriptors)}; got "
                         f"{np.unique(desc[wrong]).tolist()} (furniture or unknown)")


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
    check_int("num_tokens", num_tokens, 1, tokens.num_tokens)
    return tokens.replace(boxes=tokens.boxes[..., :num_tokens, :],
                          descriptor=tokens.descriptor[..., :num_tokens],
                          kind=tokens.kind[..., :num_tokens],
                          mask=tokens.mask[..., :num_tokens],
                          age=None if tokens.age is None else tokens.age[..., :num_tokens])
