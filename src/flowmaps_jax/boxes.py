"""Box geometry, pure jnp, no checks: corners ``(y0, x0, y1, x1)`` in pixels (y1/x1 exclusive),
boxes ``(y, x, h, w)`` normalised by ``map_size - 1``, centre form ``(cy, cx, h, w)``.
"""

from __future__ import annotations

import jax.numpy as jnp


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


def normalise(corners: jnp.ndarray, map_size) -> jnp.ndarray:
    """(..., 4) pixel corners (y0, x0, y1, x1) → normalised (y, x, h, w) / (map_size − 1)."""
    yx, far = corners[..., :2], corners[..., 2:]
    return jnp.concatenate([yx, far - yx], axis=-1) / (map_size - 1)


def denormalise(boxes: jnp.ndarray, map_size) -> jnp.ndarray:
    """Inverse of :func:`normalise`: (..., 4) normalised (y, x, h, w) → pixel corners."""
    px = boxes * (map_size - 1)
    return jnp.concatenate([px[..., :2], px[..., :2] + px[..., 2:]], axis=-1)


def corner_centres(corners: jnp.ndarray) -> jnp.ndarray:
    """(..., 2) centres (cy, cx) of (..., 4) pixel corners (y0, x0, y1, x1)."""
    return 0.5 * (corners[..., :2] + corners[..., 2:])


def centred_squares(centres: jnp.ndarray, half: jnp.ndarray) -> jnp.ndarray:
    """(..., 4) corners of squares with half-side ``half`` (broadcast against ``centres``
    (..., 2)) centred on ``centres``: how objects sit on their tables."""
    return jnp.concatenate([centres - half, centres + half], axis=-1)
