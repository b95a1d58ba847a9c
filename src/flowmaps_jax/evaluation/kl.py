"""The continuous KL(q‖p) of the protocol (docs/protocol.md): the ground-truth Gaussian mixture
q(x) = Σ_k q_k N(c(b_k), diag(σ_k²)) in centre coordinates c = (cy, cx, h, w) (a shear of unit
Jacobian, so log q at c(x) is the density of boxes x in (y, x, h, w)), and KL(q‖p) estimated
from draws of q. Shapes: ``...`` free leading dims, K slots, ``slot_mask`` (..., K). Public
functions validate once and run a jitted kernel that checks nothing.
"""

from __future__ import annotations

import math
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.boxes import from_centre, to_centre
from flowmaps_jax.tables import protocol_sigma  # the stds, shared with the assignment
from flowmaps_jax.validation import (
    PROB_ATOL,
    check_array,
    check_int,
    check_mask,
    check_probabilities,
    check_shape,
    is_concrete,
)

_LOG_2PI = math.log(2.0 * math.pi)
_DUMMY_BOX = (0.0, 0.0, 1.0, 1.0)  # stands in for padded slots so no NaN appears (masked anyway)


class Estimate(NamedTuple):
    """A Monte-Carlo mean and its standard error, each of shape (...)."""

    mean: jnp.ndarray
    stderr: jnp.ndarray


def _check_mixture(slot_probs, slot_boxes, slot_mask):
    """The mixture arguments of the public functions: ``slot_probs`` (..., K) slot weights;
    ``slot_mask`` (..., K) if given, no weight outside it; ``slot_boxes`` (..., K, 4), finite
    with positive h and w on the slots that carry weight (values of concrete arrays). Returns
    them checked (``slot_probs`` float64 and ``slot_mask`` bool when concrete)."""
    slot_probs = check_probabilities("slot_probs", slot_probs, (..., None), atol=PROB_ATOL,
                                     min_value=-PROB_ATOL)
    if slot_mask is not None:
        slot_mask = check_mask("slot_mask", slot_mask, tuple(slot_probs.shape))
        check_probabilities("slot_probs", slot_probs, atol=PROB_ATOL, min_value=-PROB_ATOL,
                            support=slot_mask, support_name="slot_mask")  # none outside it
    slot_boxes = check_array("slot_boxes", slot_boxes)
    check_shape("slot_boxes", tuple(slot_boxes.shape), (*slot_probs.shape, 4),
                "a box per entry of slot_probs")
    if is_concrete(slot_probs, slot_boxes, slot_mask):
        active = np.asarray(slot_probs) > 0
        if slot_mask is not None:
            active &= np.asarray(slot_mask, bool)
        boxes = np.asarray(slot_boxes, dtype=np.float64)[active]
        if not np.all(np.isfinite(boxes)):
            raise ValueError("slot_boxes contains NaN or inf on real slots")
        if np.any(boxes[:, 2:] <= 0.0):
            raise ValueError("slot_boxes must have positive h and w on real slots (boxes are "
                             "y, x, h, w)")
    return slot_probs, slot_boxes, slot_mask


def _full_mask(shape, slot_mask):
    return jnp.ones(shape, bool) if slot_mask is None else jnp.asarray(slot_mask, bool)


_sigma = protocol_sigma


def gt_mixture_sigma(slot_boxes: jnp.ndarray) -> jnp.ndarray:
    """Per-slot std of the ground-truth mixture, in centre coordinates.

    slot_boxes: (..., K, 4) boxes b_k (y, x, h, w).
    Returns (..., K, 4) std of (cy, cx, h, w): (0.35 h, 0.35 w, 0.02 h, 0.02 w).
    """
    slot_boxes = check_array("slot_boxes", slot_boxes, (..., 4))
    return _sigma(jnp.asarray(slot_boxes, jnp.float32))


def _active_components(slot_probs, slot_boxes, slot_mask):
    """Log-weights (-inf on unused slots), centre means and stds with safe values on padding."""
    probs = jnp.asarray(slot_probs, jnp.float32)
    active = (probs > 0) & slot_mask
    boxes = jnp.where(active[..., None], jnp.asarray(slot_boxes, jnp.float32),
                      jnp.asarray(_DUMMY_BOX, jnp.float32))
    log_w = jnp.where(active, jnp.log(jnp.where(active, probs, 1.0)), -jnp.inf)
    return log_w, to_centre(boxes), _sigma(boxes)


@jax.jit
def mixture_log_prob(x, slot_probs, slot_boxes, slot_mask):
    """The kernel of :func:`gt_mixture_log_prob` (no checks; ``x`` float32, ``slot_mask``
    required)."""
    log_w, mu, sigma = _active_components(slot_probs, slot_boxes, slot_mask)
    z = (to_centre(x)[..., :, None, :] - mu[..., None, :, :]) / sigma[..., None, :, :]
    log_comp = (-0.5 * jnp.sum(z**2, axis=-1) - jnp.sum(jnp.log(sigma), axis=-1)[..., None, :]
                - 2.0 * _LOG_2PI)  # 4 dims × ½ log 2π
    return jax.nn.logsumexp(log_comp + log_w[..., None, :], axis=-1)


def gt_mixture_log_prob(x: jnp.ndarray, slot_probs: jnp.ndarray, slot_boxes: jnp.ndarray,
                        slot_mask: jnp.ndarray | None = None) -> jnp.ndarray:
    """log q(x) of boxes under the ground-truth mixture (see module doc).

    x: (..., N, 4) boxes (y, x, h, w). slot_probs: (..., K) exact posterior q (or any slot
    weights: a slot predictor's density is this mixture with its weights).
    slot_boxes: (..., K, 4) b_k. slot_mask: optional (..., K) real slots (default: all).
    Returns (..., N) log-densities w.r.t. Lebesgue measure on (y, x, h, w).
    """
    slot_probs, slot_boxes, slot_mask = _check_mixture(slot_probs, slot_boxes, slot_mask)
    x = check_array("x", x)
    check_shape("x", tuple(x.shape), (*slot_probs.shape[:-1], None, 4),
                "leading dims as in slot_probs")
    return mixture_log_prob(jnp.asarray(x, jnp.float32), slot_probs, slot_boxes,
                            _full_mask(np.shape(slot_probs), slot_mask))


@partial(jax.jit, static_argnames="n")
def mixture_samples(key, slot_probs, slot_boxes, slot_mask, n):
    """The kernel of :func:`sample_gt_mixture` (no checks; ``slot_mask`` required)."""
    log_w, mu, sigma = _active_components(slot_probs, slot_boxes, slot_mask)
    k_slot, k_noise = jax.random.split(key)
    logits = jnp.broadcast_to(log_w[..., None, :], (*log_w.shape[:-1], n, log_w.shape[-1]))
    slot = jax.random.categorical(k_slot, logits)  # (..., n)
    mean = jnp.take_along_axis(mu, slot[..., None], axis=-2)  # (..., n, 4)
    std = jnp.take_along_axis(sigma, slot[..., None], axis=-2)
    eps = jax.random.normal(k_noise, mean.shape)
    return from_centre(mean + std * eps)


def sample_gt_mixture(key: jax.Array, slot_probs: jnp.ndarray, slot_boxes: jnp.ndarray, n: int,
                      slot_mask: jnp.ndarray | None = None) -> jnp.ndarray:
    """n draws from the ground-truth mixture q: pick slot k with prob q_k, then jitter.

    slot_probs: (..., K). slot_boxes: (..., K, 4). Returns (..., n, 4) boxes (y, x, h, w).
    """
    slot_probs, slot_boxes, slot_mask = _check_mixture(slot_probs, slot_boxes, slot_mask)
    n = check_int("n", n)
    return mixture_samples(key, slot_probs, slot_boxes, _full_mask(np.shape(slot_probs), slot_mask),
                           n)


@jax.jit
def _mean_and_stderr(diff):
    n = diff.shape[-1]
    return Estimate(jnp.mean(diff, axis=-1), jnp.std(diff, axis=-1, ddof=1) / math.sqrt(n))


def kl_estimate(log_q, log_p) -> Estimate:
    """The kernel of :func:`continuous_kl` (no checks): the mean of log q − log p over the last
    axis, and its standard error."""
    return _mean_and_stderr(jnp.asarray(log_q, jnp.float32) - jnp.asarray(log_p, jnp.float32))


def continuous_kl(log_q: jnp.ndarray, log_p: jnp.ndarray) -> Estimate:
    """KL(q‖p) ≈ mean over draws x_i ~ q of log q(x_i) − log p(x_i), with its standard error.

    log_q, log_p: (..., N) log-densities at the same N ≥ 2 draws from q (e.g. from
    :func:`sample_gt_mixture`; log p exact for the model). Returns Estimate (...).
    """
    log_q = check_array("log_q", log_q, (..., None))
    log_p = check_array("log_p", log_p, tuple(log_q.shape))
    if np.shape(log_q)[-1] < 2:
        raise ValueError(f"log_q needs at least 2 draws for a standard error; got "
                         f"{np.shape(log_q)[-1]}")
    return kl_estimate(log_q, log_p)
