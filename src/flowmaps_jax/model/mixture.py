"""Mixture read-out: explicit table weights π_s, and a flow that places the object on table s
(docs/design.md, "The posterior at the floor"):

    p_θ(box | map, query) = Σ_s π_s(map, query, Δτ) · p_θ(box | s, map, query)

π (B, Q, S) is free of x_t and t (one CDiT row per map token, trained by cross-entropy against
the target's table). The placement flow runs in table s's local frame (:func:`to_local`):
z = (c(box) − μ_s) / scale, c the centre form, μ_s = (table s's centre, the object's h, w),
scale = ``LOCAL_SCALE`` × the object's (h, w, h, w), so log p(box | s) = log p(z) − Σ log scale.
The density sums the ``MIXTURE_TERMS`` tables nearest each box (:func:`nearest_tables`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from flowmaps_jax.boxes import from_centre, to_centre
from flowmaps_jax.model.route import object_box, start_table
from flowmaps_jax.tokens import FURNITURE, OBJECT

LOCAL_SCALE = (0.25, 0.25, 0.05, 0.05)
"""The local frame's unit, as fractions of the object's (h, w, h, w): the route head's initial
widths, so that placements of a few units cover an object's spread on its table."""

SMOOTH_FREQUENCY = 8.0
"""The highest angular frequency (radians per unit) at which the placement flow sees its local
coordinates z and the flow time t: their sinusoidal features are those of the model's own
``max_frequency`` (1000, tuned to resolve a pixel of a box in [0, 1]) applied to the inputs
scaled by ``SMOOTH_FREQUENCY / max_frequency``. A local unit is a fraction of an object's side,
so features at 1000 rad per unit made the field rough and its likelihood integral diverge."""

MIXTURE_TERMS = 2
"""Tables per box in the mixture density: the box's nearest tables (by centre)."""


def tables_of(context) -> jnp.ndarray:
    """(B, S) bool: the map's furniture tokens, the components of the mixture."""
    return context.mask & (context.kind == FURNITURE)


def placement_frame(context, query_descriptor):
    """The local frames of every (query, token): means (B, Q, S, 4) in centre form (the token's
    centre with the object's h, w), scale (B, Q, 4), and start (B, Q) the table the queried object
    stands on at τ (nearest table centre to its token)."""
    tables = tables_of(context)
    obj = object_box(context.boxes, context.descriptor, context.kind, context.mask,
                     query_descriptor)  # (B, Q, 4)
    size = jnp.maximum(obj[..., 2:], 1e-4)  # (B, Q, 2)
    centres = to_centre(context.boxes)[..., :2]  # (B, S, 2)
    b, q, s = obj.shape[0], obj.shape[1], centres.shape[1]
    means = jnp.concatenate([jnp.broadcast_to(centres[:, None], (b, q, s, 2)),
                             jnp.broadcast_to(size[:, :, None], (b, q, s, 2))], axis=-1)
    scale = jnp.asarray(LOCAL_SCALE, jnp.float32) * jnp.concatenate([size, size], axis=-1)
    start = jnp.argmax(start_table(context.boxes, tables, obj), axis=-1)
    return means, scale, start


def gather_rows(values, index):
    """values (B, Q, S, ...) at per-row token indices index (B, Q, N) → (B, Q, N, ...)."""
    return jax.vmap(jax.vmap(lambda v, i: v[i]))(values, index)


def gather_tokens(tokens, index):
    """tokens (B, S, D) at index (B, Q, N) → (B, Q, N, D)."""
    return jax.vmap(lambda t, i: t[i])(tokens, index)


def to_local(box, mean, scale):
    """Boxes (B, Q, N, 4) (y, x, h, w) → local coordinates z (B, Q, N, 4) of the frames with
    centre-form means (B, Q, N, 4) and scale (B, Q, 4)."""
    return (to_centre(box) - mean) / scale[:, :, None, :]


def from_local(z, mean, scale):
    """Inverse of :func:`to_local`."""
    return from_centre(mean + scale[:, :, None, :] * z)


def local_log_det(scale) -> jnp.ndarray:
    """log |det ∂z/∂box| (B, Q, 1) = −Σ log scale: add to log p(z) to get log p(box)."""
    return -jnp.sum(jnp.log(scale), axis=-1)[..., None]


def nearest_tables(box, context, terms: int = MIXTURE_TERMS):
    """The ``terms`` furniture tokens (B, Q, N, terms) whose centres are nearest each box's
    centre (B, Q, N, 4), nearest first, and valid (B, Q, N, terms): False where the map has
    fewer furniture tokens than ``terms``."""
    d = jnp.sum(jnp.square(to_centre(box)[..., None, :2]
                           - to_centre(context.boxes)[:, None, None, :, :2]), axis=-1)
    d = jnp.where(tables_of(context)[:, None, None, :], d, jnp.inf)  # (B, Q, N, S)
    k = min(terms, d.shape[-1])
    neg, index = jax.lax.top_k(-d, k)
    return index, jnp.isfinite(neg)


def scene_objects(tokens, num_objects: int):
    """Descriptors (B, num_objects) of the first ``num_objects`` object tokens of the current map
    (age 0), in token order."""
    current = tokens.mask.astype(bool) & (tokens.kind == OBJECT)
    if tokens.age is not None:
        current &= tokens.age == 0
    order = jnp.argsort(jnp.logical_not(current), axis=-1, stable=True)[:, :num_objects]
    return jnp.take_along_axis(jnp.asarray(tokens.descriptor), order, axis=-1)


GEOMETRY_FREQUENCIES = (1.0, 2.0, 4.0, 8.0)
"""Frequencies (× π) of :func:`relative_geometry`'s Fourier features of the centre offsets."""


def relative_geometry(boxes, start, angle: bool = True):
    """Each token's place relative to the table an object stands on, as features (B, R, S, F):
    the centre offset (dy, dx) and its sines and cosines at :data:`GEOMETRY_FREQUENCIES`, then
    with ``angle`` the sine and cosine of the angle around the map centre (0.5, 0.5) minus the
    start table's (and of twice it), without it the offset's length (the distance). boxes
    (B, S, 4) normalised, start (B, R) token indices."""
    centres = to_centre(boxes)[..., :2]  # (B, S, 2)
    here = gather_tokens(centres, start)  # (B, R, 2)
    offset = centres[:, None] - here[:, :, None]  # (B, R, S, 2)
    bearing = jnp.arctan2(centres[..., 1] - 0.5, -(centres[..., 0] - 0.5))  # (B, S)
    here_bearing = jnp.take_along_axis(bearing, start, axis=1)  # (B, R)
    turn = bearing[:, None] - here_bearing[:, :, None]  # (B, R, S)
    freqs = jnp.pi * jnp.asarray(GEOMETRY_FREQUENCIES, jnp.float32)
    waves = offset[..., None] * freqs  # (B, R, S, 2, K)
    waves = waves.reshape(*offset.shape[:-1], -1)
    if not angle:  # world-agnostic: offsets and distances only
        distance = jnp.sqrt(jnp.sum(offset ** 2, axis=-1, keepdims=True))
        return jnp.concatenate([offset, jnp.sin(waves), jnp.cos(waves), distance], axis=-1)
    turns = jnp.stack([turn, 2 * turn], axis=-1)
    return jnp.concatenate([offset, jnp.sin(waves), jnp.cos(waves), jnp.sin(turns),
                            jnp.cos(turns)], axis=-1)
