"""Checks of the evaluation's batched array arguments that ``flowmaps_jax.validation`` does not
cover: shapes that must agree with each other, probability vectors over the last axis (with a
tolerance and a slot mask) and boxes on real slots.

Shape checks are static, so they also run under ``jit``/``vmap``; value checks run only on
concrete arrays and are skipped for tracers. Each public function runs them once on its inputs;
the jitted cores never do.
"""

from __future__ import annotations

import numpy as np

from flowmaps_jax.validation import is_concrete

PROB_ATOL = 1e-4
"""Tolerance for probabilities summing to 1 (and for zero mass on padded slots)."""


def check_same(name: str, shape: tuple[int, ...], expected: tuple[int, ...], what: str) -> None:
    """``shape`` must equal ``expected`` (``what`` says why, for the message)."""
    if tuple(shape) != tuple(expected):
        raise ValueError(f"{name} must have shape {tuple(expected)} ({what}); got {tuple(shape)}")


def check_distribution(name: str, probs, mask=None) -> None:
    """Values of a probability vector over the last axis: finite, ≥ 0, sums to 1, 0 on padding."""
    if not is_concrete(probs, mask):
        return
    p = np.asarray(probs, dtype=np.float64)
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name} contains NaN or inf")
    if np.any(p < -PROB_ATOL):
        raise ValueError(f"{name} has negative probabilities (min {p.min():.3g})")
    total = p.sum(axis=-1)
    if np.any(np.abs(total - 1.0) > PROB_ATOL):
        worst = total.ravel()[np.argmax(np.abs(total - 1.0).ravel())]
        raise ValueError(f"{name} must sum to 1 over its last axis; found a sum of {worst:.6g}")
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if np.any(np.abs(p[..., : m.shape[-1]][~m]) > PROB_ATOL):
            raise ValueError(f"{name} puts probability on slots where slot_mask is False")


def check_boxes_values(name: str, boxes, active) -> None:
    """Boxes (..., K, 4): finite and with positive sides where ``active`` (..., K)."""
    if not is_concrete(boxes, active):
        return
    b = np.asarray(boxes, dtype=np.float64)
    act = np.asarray(active, bool)
    if not np.all(np.isfinite(b[act])):
        raise ValueError(f"{name} contains NaN or inf on real slots")
    if np.any(b[act][:, 2:] <= 0.0):
        raise ValueError(f"{name} must have positive h and w on real slots (boxes are y, x, h, w)")
