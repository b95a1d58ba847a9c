"""Evaluation metrics against the exact posterior: pure functions over arrays.

Implements the evaluation protocol of ``DESIGN.md`` (issue 4). Nothing here knows about the model
or the simulator: inputs are the exact slot posterior ``q``, the candidate boxes ``b_k`` and model
samples or log-densities.

Shapes and conventions
----------------------
* ``...`` are free leading batch dims (usually one per query); every array of one call shares them.
* ``K`` slots per query, padded to a common size; ``slot_mask`` (..., K) is True on real slots.
  Padded slots carry zero probability in ``q``. Functions that order or count slots take the mask;
  the mixture functions also accept it but only need ``q_k = 0`` on padding.
* Boxes are normalised ``(y, x, h, w)``; centres are ``(y + h/2, x + w/2)``.
* Slot distributions of predictors ("p-hat") have ``K + 1`` entries: the K slots then the "off" bin
  (samples that landed on no slot). The reference predictors below return the same layout.

Ground-truth mixture q(x)
-------------------------
``q = Σ_k q_k N(c(b_k), diag(σ_k²))`` lives in centre coordinates ``c = (cy, cx, h, w)`` with
``σ_k = (0.35 h_k, 0.35 w_k, 0.02 h_k, 0.02 w_k)``. The map ``(y, x, h, w) → (cy, cx, h, w)`` is a
shear with unit Jacobian, so ``log q`` evaluated at ``c(x)`` *is* the log-density of boxes
``x`` in ``(y, x, h, w)``: samples are drawn in centre coordinates and returned as ``(y, x, h, w)``,
and densities are evaluated the other way round, always consistently.

Validation
----------
Public functions check shapes (static, so also under ``jit``/``vmap``) and raise ``ValueError``
naming the argument. Value checks (probabilities ≥ 0 summing to 1, finite boxes, ...) run when
the inputs are concrete arrays and are skipped for tracers, so the same functions can be used
inside ``jax.jit`` / ``jax.vmap``. The array work happens in ``jit``-compiled cores.

Ties
----
``top1`` and ``search_cost`` break ties between slots with equal p-hat *uniformly at random* and
report the expectation (``tie_break="average"``, the default): deterministic, and independent of
how slots happen to be numbered. ``tie_break="index"`` instead visits tied slots by increasing slot
index. Values within ``TIE_ATOL`` of each other count as tied.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Hashable
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.tokens import from_centre, to_centre
from flowmaps_jax.validation import check_int, is_concrete

CENTRE_SIGMA_SCALE = 0.35
"""Centre std of a mixture component as a fraction of the box side (h for cy, w for cx)."""
SIZE_SIGMA_SCALE = 0.02
"""Size std of a mixture component as a fraction of the box side (h for h, w for w)."""
ASSIGN_RADIUS = 0.05
"""A sample counts for slot k if its L2 distance to b_k (4 numbers) is below this."""
PROB_ATOL = 1e-4
"""Tolerance for probabilities summing to 1 (and for zero mass on padded slots)."""
TIE_ATOL = 1e-6
"""Two slot scores closer than this are tied."""
TIE_BREAKS = ("average", "index")

_LOG_2PI = math.log(2.0 * math.pi)
_DUMMY_BOX = (0.0, 0.0, 1.0, 1.0)  # stands in for padded slots so no NaN appears (masked anyway)


class Estimate(NamedTuple):
    """A Monte-Carlo mean and its standard error, each of shape (...)."""

    mean: jnp.ndarray
    stderr: jnp.ndarray


# --------------------------------------------------------------------------- validation helpers


def _check_last(name: str, arr, size: int | None, min_ndim: int = 1) -> tuple[int, ...]:
    shape = tuple(np.shape(arr))
    if len(shape) < min_ndim:
        raise ValueError(f"{name} must have at least {min_ndim} dims; got shape {shape}")
    if size is not None and shape[-1] != size:
        raise ValueError(f"{name} must have last dim {size}; got shape {shape}")
    return shape


def _check_same(name: str, shape: tuple[int, ...], expected: tuple[int, ...], what: str) -> None:
    if tuple(shape) != tuple(expected):
        raise ValueError(f"{name} must have shape {tuple(expected)} ({what}); got {tuple(shape)}")


def _check_distribution(name: str, probs, mask=None, atol: float = PROB_ATOL) -> None:
    """Values of a probability vector over the last axis: finite, ≥ 0, sums to 1, 0 on padding."""
    if not is_concrete(probs, mask):
        return
    p = np.asarray(probs, dtype=np.float64)
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name} contains NaN or inf")
    if np.any(p < -atol):
        raise ValueError(f"{name} has negative probabilities (min {p.min():.3g})")
    total = p.sum(axis=-1)
    if np.any(np.abs(total - 1.0) > atol):
        worst = total.ravel()[np.argmax(np.abs(total - 1.0).ravel())]
        raise ValueError(f"{name} must sum to 1 over its last axis; found a sum of {worst:.6g}")
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if np.any(np.abs(p[..., : m.shape[-1]][~m]) > atol):
            raise ValueError(f"{name} puts probability on slots where slot_mask is False")


def _check_boxes_values(name: str, boxes, active=None) -> None:
    """Boxes (..., K, 4): finite and with positive sides where ``active`` (default: everywhere)."""
    if not is_concrete(boxes, active):
        return
    b = np.asarray(boxes, dtype=np.float64)
    act = np.ones(b.shape[:-1], bool) if active is None else np.asarray(active, bool)
    if not np.all(np.isfinite(b[act])):
        raise ValueError(f"{name} contains NaN or inf on real slots")
    if np.any(b[act][:, 2:] <= 0.0):
        raise ValueError(f"{name} must have positive h and w on real slots (boxes are y, x, h, w)")


def _check_mask(name: str, mask, expected: tuple[int, ...]):
    if mask is None:
        return None
    _check_same(name, np.shape(mask), expected, "one flag per slot")
    if is_concrete(mask) and not np.issubdtype(np.asarray(mask).dtype, np.bool_):
        raise ValueError(f"{name} must be boolean; got dtype {np.asarray(mask).dtype}")
    return mask


def _check_int_range(name: str, values, low: int, high: int, what: str) -> None:
    """Concrete ``values`` must be integers in low..high (inclusive); tracers pass unchecked."""
    if not is_concrete(values):
        return
    v = np.asarray(values)
    if not np.issubdtype(v.dtype, np.integer):
        raise ValueError(f"{name} must be integer {what}; got dtype {v.dtype}")
    if np.any((v < low) | (v > high)):
        raise ValueError(f"{name} must lie in {low}..{high}")


def _check_tie_break(tie_break: str) -> None:
    if tie_break not in TIE_BREAKS:
        raise ValueError(f"tie_break must be one of {TIE_BREAKS}; got {tie_break!r}")


def _check_mixture(slot_probs, slot_boxes, slot_mask) -> tuple[int, ...]:
    """Shapes and values of (q, b, mask); returns the shape (..., K) of q."""
    q_shape = _check_last("slot_probs", slot_probs, None)
    b_shape = _check_last("slot_boxes", slot_boxes, 4, min_ndim=2)
    _check_same("slot_boxes", b_shape, (*q_shape, 4), "slot_probs.shape + (4,)")
    _check_mask("slot_mask", slot_mask, q_shape)
    _check_distribution("slot_probs", slot_probs, slot_mask)
    if is_concrete(slot_probs, slot_mask):
        active = np.asarray(slot_probs) > 0
        if slot_mask is not None:
            active &= np.asarray(slot_mask, bool)
        _check_boxes_values("slot_boxes", slot_boxes, active)
    return q_shape


def _full_mask(shape, slot_mask):
    return jnp.ones(shape, bool) if slot_mask is None else jnp.asarray(slot_mask, bool)


# --------------------------------------------------------------------------- box coordinates


# to_centre / from_centre live in tokens.py (the box convention); re-exported here.


# --------------------------------------------------------------------------- ground-truth mixture


@jax.jit
def _sigma(boxes):
    h, w = boxes[..., 2], boxes[..., 3]
    return jnp.stack([CENTRE_SIGMA_SCALE * h, CENTRE_SIGMA_SCALE * w,
                      SIZE_SIGMA_SCALE * h, SIZE_SIGMA_SCALE * w], axis=-1)


def gt_mixture_sigma(slot_boxes: jnp.ndarray) -> jnp.ndarray:
    """Per-slot std of the ground-truth mixture, in centre coordinates.

    slot_boxes: (..., K, 4) boxes b_k (y, x, h, w).
    Returns (..., K, 4) std of (cy, cx, h, w): (0.35 h, 0.35 w, 0.02 h, 0.02 w).
    """
    _check_last("slot_boxes", slot_boxes, 4)
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
def _mixture_log_prob(x, slot_probs, slot_boxes, slot_mask):
    log_w, mu, sigma = _active_components(slot_probs, slot_boxes, slot_mask)
    z = (to_centre(x)[..., :, None, :] - mu[..., None, :, :]) / sigma[..., None, :, :]
    log_comp = (-0.5 * jnp.sum(z**2, axis=-1) - jnp.sum(jnp.log(sigma), axis=-1)[..., None, :]
                - 2.0 * _LOG_2PI)  # 4 dims × ½ log 2π
    return jax.nn.logsumexp(log_comp + log_w[..., None, :], axis=-1)


def gt_mixture_log_prob(x: jnp.ndarray, slot_probs: jnp.ndarray, slot_boxes: jnp.ndarray,
                        slot_mask: jnp.ndarray | None = None) -> jnp.ndarray:
    """log q(x) of boxes under the ground-truth mixture (see module doc).

    x: (..., N, 4) boxes (y, x, h, w). slot_probs: (..., K) exact posterior q.
    slot_boxes: (..., K, 4) b_k. slot_mask: optional (..., K) real slots (default: all).
    Returns (..., N) log-densities w.r.t. Lebesgue measure on (y, x, h, w).
    """
    q_shape = _check_mixture(slot_probs, slot_boxes, slot_mask)
    x_shape = _check_last("x", x, 4, min_ndim=2)
    _check_same("x.shape[:-2]", x_shape[:-2], q_shape[:-1], "the leading dims of slot_probs")
    return _mixture_log_prob(jnp.asarray(x, jnp.float32), slot_probs, slot_boxes,
                             _full_mask(q_shape, slot_mask))


@partial(jax.jit, static_argnames="n")
def _sample_mixture(key, slot_probs, slot_boxes, slot_mask, n):
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
    q_shape = _check_mixture(slot_probs, slot_boxes, slot_mask)
    n = check_int("n", n)
    return _sample_mixture(key, slot_probs, slot_boxes, _full_mask(q_shape, slot_mask), n)


# --------------------------------------------------------------------------- continuous KL


@jax.jit
def _mean_and_stderr(diff):
    n = diff.shape[-1]
    return Estimate(jnp.mean(diff, axis=-1), jnp.std(diff, axis=-1, ddof=1) / math.sqrt(n))


def continuous_kl(log_q: jnp.ndarray, log_p: jnp.ndarray) -> Estimate:
    """KL(q‖p) ≈ mean over draws x_i ~ q of log q(x_i) − log p(x_i), with its standard error.

    log_q, log_p: (..., N) log-densities at the same N ≥ 2 draws from q. Returns Estimate (...).
    """
    shape = _check_last("log_q", log_q, None)
    _check_same("log_p", np.shape(log_p), shape, "same as log_q")
    if shape[-1] < 2:
        raise ValueError(f"log_q needs at least 2 draws for a standard error; got {shape[-1]}")
    return _mean_and_stderr(jnp.asarray(log_q, jnp.float32) - jnp.asarray(log_p, jnp.float32))


def kl_from_log_prob_fn(key: jax.Array, slot_probs: jnp.ndarray, slot_boxes: jnp.ndarray,
                        log_prob_fn: Callable[[jnp.ndarray], jnp.ndarray], n: int,
                        slot_mask: jnp.ndarray | None = None) -> Estimate:
    """KL(q‖p) for any model with a log-density (e.g. a flow's exact likelihood).

    Draws x (..., n, 4) from q and calls ``log_prob_fn(x)`` → (..., n) log p(x) in (y, x, h, w).
    The callable should close over the model and its conditioning. Returns Estimate (...).
    """
    q_shape = _check_mixture(slot_probs, slot_boxes, slot_mask)
    n = check_int("n", n)
    if n < 2:
        raise ValueError(f"n must be at least 2 for a standard error; got {n}")
    mask = _full_mask(q_shape, slot_mask)
    x = _sample_mixture(key, slot_probs, slot_boxes, mask, n)
    log_p = log_prob_fn(x)
    _check_same("log_prob_fn(x)", np.shape(log_p), x.shape[:-1], "one log-density per draw")
    log_q = _mixture_log_prob(x, slot_probs, slot_boxes, mask)
    return _mean_and_stderr(log_q - jnp.asarray(log_p, jnp.float32))


@jax.jit
def _diag_gaussian_log_prob(x, mean, log_var):
    mean = mean[..., None, :]
    log_var = log_var[..., None, :]
    return -0.5 * jnp.sum((x - mean) ** 2 * jnp.exp(-log_var) + log_var + _LOG_2PI, axis=-1)


def gaussian_log_prob(x: jnp.ndarray, mean: jnp.ndarray, log_var: jnp.ndarray) -> jnp.ndarray:
    """Log-density of x (..., N, 4) under a diagonal Gaussian over (y, x, h, w).

    mean: (..., 4). log_var: log-variances broadcastable to mean (e.g. 0.0 for unit variance).
    Returns (..., N).
    """
    x_shape = _check_last("x", x, 4, min_ndim=2)
    m_shape = _check_last("mean", mean, 4)
    _check_same("mean.shape[:-1]", m_shape[:-1], x_shape[:-2], "the leading dims of x")
    try:
        np.broadcast_shapes(np.shape(log_var), m_shape)
    except ValueError:
        raise ValueError(f"log_var of shape {np.shape(log_var)} does not broadcast to mean "
                         f"{m_shape}") from None
    mean = jnp.asarray(mean, jnp.float32)
    log_var = jnp.broadcast_to(jnp.asarray(log_var, jnp.float32), m_shape)
    return _diag_gaussian_log_prob(jnp.asarray(x, jnp.float32), mean, log_var)


def kl_gaussian_model(key: jax.Array, slot_probs: jnp.ndarray, slot_boxes: jnp.ndarray,
                      mean: jnp.ndarray, log_var: jnp.ndarray, n: int,
                      slot_mask: jnp.ndarray | None = None) -> Estimate:
    """KL(q‖p) for a diagonal Gaussian over (y, x, h, w) (the MLP baseline); log p in closed form.

    mean: (..., 4). log_var: broadcastable to mean (0.0 = the reference's unit variance).
    Returns Estimate (...).
    """
    q_shape = _check_mixture(slot_probs, slot_boxes, slot_mask)
    m_shape = _check_last("mean", mean, 4)
    _check_same("mean.shape[:-1]", m_shape[:-1], q_shape[:-1], "the leading dims of slot_probs")
    return kl_from_log_prob_fn(key, slot_probs, slot_boxes,
                               lambda x: gaussian_log_prob(x, mean, log_var), n, slot_mask)


def kl_slot_model(key: jax.Array, slot_probs: jnp.ndarray, slot_boxes: jnp.ndarray,
                  model_probs: jnp.ndarray, n: int,
                  slot_mask: jnp.ndarray | None = None) -> Estimate:
    """KL(q‖p) for a slot predictor (oracle / last-seen / uniform), turned into a density.

    p is the same Gaussian mixture as q, with the predictor's weights ``model_probs`` (..., K)
    instead of q (drop the off bin of a (K+1) slot distribution first). The oracle gives exactly 0.
    Returns Estimate (...).
    """
    q_shape = _check_mixture(slot_probs, slot_boxes, slot_mask)
    _check_same("model_probs", np.shape(model_probs), q_shape, "same as slot_probs")
    _check_mixture(model_probs, slot_boxes, slot_mask)
    mask = _full_mask(q_shape, slot_mask)
    return kl_from_log_prob_fn(
        key, slot_probs, slot_boxes,
        lambda x: _mixture_log_prob(x, model_probs, slot_boxes, mask), n, slot_mask)


# --------------------------------------------------------------------------- slot assignment


@jax.jit
def _assign(samples, slot_boxes, slot_mask, radius):
    diff = samples[..., :, None, :] - slot_boxes[..., None, :, :]  # (..., N, K, 4)
    dist = jnp.sqrt(jnp.sum(diff**2, axis=-1))
    dist = jnp.where(slot_mask[..., None, :], dist, jnp.inf)
    nearest = jnp.argmin(dist, axis=-1)
    closest = jnp.min(dist, axis=-1)
    return jnp.where(closest < radius, nearest, slot_boxes.shape[-2]).astype(jnp.int32)


def assign_slots(samples: jnp.ndarray, slot_boxes: jnp.ndarray, slot_mask: jnp.ndarray,
                 radius: float = ASSIGN_RADIUS) -> jnp.ndarray:
    """Slot index of each sample: the nearest real b_k (L2 on the 4 numbers) if closer than radius.

    samples: (..., N, 4). slot_boxes: (..., K, 4). slot_mask: (..., K) bool.
    Returns (..., N) int32 in 0..K, where K is the "off" bin (no slot within ``radius``).
    """
    s_shape = _check_last("samples", samples, 4, min_ndim=2)
    b_shape = _check_last("slot_boxes", slot_boxes, 4, min_ndim=2)
    _check_same("samples.shape[:-2]", s_shape[:-2], b_shape[:-2], "the leading dims of slot_boxes")
    _check_mask("slot_mask", slot_mask, b_shape[:-1])
    if is_concrete(radius) and not float(radius) > 0:
        raise ValueError(f"radius must be positive; got {radius}")
    return _assign(jnp.asarray(samples, jnp.float32), jnp.asarray(slot_boxes, jnp.float32),
                   jnp.asarray(slot_mask, bool), radius)


@partial(jax.jit, static_argnames="num_slots")
def _histogram(assignment, num_slots):
    return jnp.mean(jax.nn.one_hot(assignment, num_slots + 1), axis=-2)


def slot_histogram(assignment: jnp.ndarray, num_slots: int) -> jnp.ndarray:
    """Empirical slot distribution p-hat = counts / N.

    assignment: (..., N) ints in 0..num_slots (num_slots = K = the off bin), from assign_slots.
    Returns (..., K + 1) float32: the K slots then the off bin.
    """
    num_slots = check_int("num_slots", num_slots)
    _check_last("assignment", assignment, None)
    _check_int_range("assignment", assignment, 0, num_slots,
                     "slot indices (num_slots is the off bin)")
    return _histogram(jnp.asarray(assignment), num_slots)


def empirical_slots(samples: jnp.ndarray, slot_boxes: jnp.ndarray, slot_mask: jnp.ndarray,
                    radius: float = ASSIGN_RADIUS) -> jnp.ndarray:
    """p-hat (..., K + 1) of samples (..., N, 4): :func:`assign_slots`, then :func:`slot_histogram`.
    """
    assignment = assign_slots(samples, slot_boxes, slot_mask, radius)
    return _histogram(assignment, np.shape(slot_boxes)[-2])


# --------------------------------------------------------------------------- slot metrics


def _check_slot_pair(p_hat, q, slot_mask) -> tuple[int, ...]:
    """p-hat (..., K+1) and q (..., K) over the same slots; returns q's shape."""
    q_shape = _check_last("q", q, None)
    p_shape = _check_last("p_hat", p_hat, None)
    _check_same("p_hat", p_shape, (*q_shape[:-1], q_shape[-1] + 1),
                "q's K slots plus the off bin")
    _check_mask("slot_mask", slot_mask, q_shape)
    _check_distribution("q", q, slot_mask)
    _check_distribution("p_hat", p_hat, slot_mask)
    return q_shape


@jax.jit
def _tv(p_hat, q):
    return 0.5 * jnp.sum(jnp.abs(p_hat[..., :-1] - q), axis=-1) + 0.5 * p_hat[..., -1]


def slot_tv(p_hat: jnp.ndarray, q: jnp.ndarray) -> jnp.ndarray:
    """Total variation ½Σ_k|p̂_k − q_k| + ½p̂_off between p-hat (..., K+1) and q (..., K) → (...)."""
    _check_slot_pair(p_hat, q, None)
    return _tv(jnp.asarray(p_hat, jnp.float32), jnp.asarray(q, jnp.float32))


def _modes(scores, valid):
    """(..., K) bool: the real slots whose score is within TIE_ATOL of the best real score."""
    best = jnp.max(jnp.where(valid, scores, -jnp.inf), axis=-1, keepdims=True)
    return valid & (scores >= best - TIE_ATOL)


@partial(jax.jit, static_argnames="tie_break")
def _top1(p_hat, q, slot_mask, tie_break):
    p_modes = _modes(p_hat[..., :-1], slot_mask)
    q_modes = _modes(q, slot_mask)
    if tie_break == "average":
        hits = jnp.sum(p_modes & q_modes, axis=-1)
        return hits / jnp.sum(p_modes, axis=-1)
    first = jnp.argmax(p_modes, axis=-1)  # lowest slot index among the tied best
    return jnp.take_along_axis(q_modes, first[..., None], axis=-1)[..., 0].astype(jnp.float32)


def top1(p_hat: jnp.ndarray, q: jnp.ndarray, slot_mask: jnp.ndarray | None = None,
         tie_break: str = "average") -> jnp.ndarray:
    """Top-1 accuracy: is the predicted best slot a mode of q?  (..., K+1), (..., K) → (...) float.

    The off bin is ignored; only real slots (``slot_mask``, default all) compete. Ties in q: any
    mode counts. Ties in p-hat: "average" returns the fraction of p-hat's tied best slots that are
    modes of q (the expected accuracy of a random pick among them); "index" takes the lowest slot
    index. If every sample is off, all real slots tie (a blind guess).
    """
    _check_tie_break(tie_break)
    q_shape = _check_slot_pair(p_hat, q, slot_mask)
    return _top1(jnp.asarray(p_hat, jnp.float32), jnp.asarray(q, jnp.float32),
                 _full_mask(q_shape, slot_mask), tie_break)


def _visit_ranks(scores, valid, tie_break):
    """(..., K) float rank (1 = visited first) of each real slot when visiting by decreasing score.

    Padded slots are visited after all real ones (they carry no probability, so their rank never
    matters) and do not push real slots back.
    """
    k = scores.shape[-1]
    s_i, s_j = scores[..., :, None], scores[..., None, :]
    real_j = valid[..., None, :]
    higher = real_j & (s_j > s_i + TIE_ATOL)
    tied = real_j & (jnp.abs(s_j - s_i) <= TIE_ATOL) & ~jnp.eye(k, dtype=bool)
    if tie_break == "average":
        rank = 1.0 + jnp.sum(higher, axis=-1) + 0.5 * jnp.sum(tied, axis=-1)
    else:
        before = tied & (jnp.arange(k)[None, :] < jnp.arange(k)[:, None])
        rank = 1.0 + jnp.sum(higher, axis=-1) + jnp.sum(before, axis=-1)
    return jnp.where(valid, rank, jnp.sum(valid, axis=-1, keepdims=True) + 1.0)


@partial(jax.jit, static_argnames="tie_break")
def _search_cost(scores, q, slot_mask, tie_break):
    return jnp.sum(_visit_ranks(scores, slot_mask, tie_break) * q, axis=-1)


def search_cost(p_hat: jnp.ndarray, q: jnp.ndarray, slot_mask: jnp.ndarray | None = None,
                tie_break: str = "average") -> jnp.ndarray:
    """Expected number of slots searched, Σ_k rank_k q_k, visiting slots by decreasing p-hat.

    p_hat: (..., K+1) (off bin ignored). q: (..., K). slot_mask: (..., K) real slots (default all;
    pass it so padded slots never tie with real ones). Ties: see :func:`top1`; "average" uses the
    mean rank of a tied group. Returns (...) float, ≥ :func:`oracle_search_cost`.
    """
    _check_tie_break(tie_break)
    q_shape = _check_slot_pair(p_hat, q, slot_mask)
    return _search_cost(jnp.asarray(p_hat, jnp.float32)[..., :-1], jnp.asarray(q, jnp.float32),
                        _full_mask(q_shape, slot_mask), tie_break)


def oracle_search_cost(q: jnp.ndarray, slot_mask: jnp.ndarray | None = None) -> jnp.ndarray:
    """The least expected search cost: visit slots by decreasing q. q: (..., K) → (...)."""
    q_shape = _check_last("q", q, None)
    _check_mask("slot_mask", slot_mask, q_shape)
    _check_distribution("q", q, slot_mask)
    q = jnp.asarray(q, jnp.float32)
    return _search_cost(q, q, _full_mask(q_shape, slot_mask), "average")


def search_cost_ratio(p_hat: jnp.ndarray, q: jnp.ndarray, slot_mask: jnp.ndarray | None = None,
                      tie_break: str = "average") -> jnp.ndarray:
    """search_cost / oracle_search_cost (≥ 1; 1 means the oracle's order). Shapes as search_cost."""
    _check_tie_break(tie_break)
    q_shape = _check_slot_pair(p_hat, q, slot_mask)
    p_hat = jnp.asarray(p_hat, jnp.float32)
    q = jnp.asarray(q, jnp.float32)
    mask = _full_mask(q_shape, slot_mask)
    return (_search_cost(p_hat[..., :-1], q, mask, tie_break)
            / _search_cost(q, q, mask, "average"))


# --------------------------------------------------------------------------- reference predictors


def oracle_slots(q: jnp.ndarray) -> jnp.ndarray:
    """The oracle predictor: q itself. (..., K) → (..., K + 1) with an empty off bin."""
    _check_last("q", q, None)
    _check_distribution("q", q)
    q = jnp.asarray(q, jnp.float32)
    return jnp.concatenate([q, jnp.zeros_like(q[..., :1])], axis=-1)


@partial(jax.jit, static_argnames="n")
def _sampled_slots(key, q, n):
    draws = jax.random.categorical(key, jnp.log(q)[..., None, :], shape=(*q.shape[:-1], n))
    return _histogram(draws, q.shape[-1])  # (..., K + 1); draws never hit the off bin


def sampled_oracle_slots(key: jax.Array, q: jnp.ndarray, n: int) -> jnp.ndarray:
    """A perfect sampler seen through n samples: slot counts / n of n draws from q itself.

    (..., K) → (..., K + 1) (off bin empty). Its slot TV / top-1 / search cost are the best any
    sampler can expect from n samples: the gap to the exact oracle is pure finite-sample noise.
    """
    _check_last("q", q, None)
    _check_distribution("q", q)
    n = check_int("n", n, 1)
    return _sampled_slots(key, jnp.asarray(q, jnp.float32), n)


@partial(jax.jit, static_argnames="num_slots")
def _one_hot_slots(slot_now, num_slots):
    return jax.nn.one_hot(slot_now, num_slots + 1)


def last_seen_slots(slot_now: jnp.ndarray, num_slots: int) -> jnp.ndarray:
    """Last-seen predictor: the object stays where it is. slot_now (...) ints → (..., K + 1).

    num_slots: K, the padded slot count. slot_now indexes the same slot axis as q.
    """
    num_slots = check_int("num_slots", num_slots)
    _check_int_range("slot_now", slot_now, 0, num_slots - 1, "slot indices")
    return _one_hot_slots(jnp.asarray(slot_now), num_slots)


@partial(jax.jit, static_argnames="num_slots")
def _uniform_slots(count, num_slots):
    real = jnp.arange(num_slots) < count[..., None]
    probs = jnp.where(real, 1.0 / count[..., None], 0.0)
    return jnp.concatenate([probs, jnp.zeros_like(probs[..., :1])], axis=-1)


def uniform_slots(count: jnp.ndarray, num_slots: int) -> jnp.ndarray:
    """Uniform predictor over the real slots. count (...) ints in 1..K → (..., K + 1).

    Real slots are the first ``count`` of the K padded ones (as in ``Scenes.visit_order``).
    """
    num_slots = check_int("num_slots", num_slots)
    _check_int_range("count", count, 1, num_slots, "numbers of slots")
    return _uniform_slots(jnp.asarray(count), num_slots)


# --------------------------------------------------------------------------- aggregation


# --------------------------------------------------------------------------- routines

ROUTE_OFFSETS = 4
"""Route offsets reported by :func:`route_offset_mass`: 0 (stays), +1, +2, +3."""


@jax.jit
def _route_offset_mass(p_hat, slot_now, num_slots):
    k = p_hat.shape[-1] - 1
    offsets = jnp.arange(ROUTE_OFFSETS)
    slot = (slot_now[..., None] + offsets) % jnp.maximum(num_slots[..., None], 1)  # (..., 4)
    mass = jnp.take_along_axis(p_hat[..., :k], slot, axis=-1)
    mass = jnp.where(offsets < num_slots[..., None], mass, 0.0)  # offset ≥ K wraps: not counted
    off = p_hat[..., k:]
    beyond = jnp.clip(1.0 - mass.sum(-1, keepdims=True) - off, 0.0, 1.0)
    return jnp.concatenate([mass, beyond, off], axis=-1)


def route_offset_mass(p_hat: jnp.ndarray, slot_now: jnp.ndarray,
                      num_slots: jnp.ndarray) -> jnp.ndarray:
    """Where along the visiting order a slot distribution puts its mass, relative to now.

    p_hat: (..., K + 1) slot distribution (positions along the object's visiting order, last bin
    "off"), e.g. :func:`empirical_slots` or :func:`oracle_slots`. slot_now: (...) int position
    at τ. num_slots: (...) int number of real slots.
    Returns (..., 6): mass at route offsets 0, +1, +2, +3 (offsets ≥ the route length are not
    counted there), at every larger offset ("beyond"), and off every slot. One step ahead the
    exact posterior gives 0.2 / 0.7 / 0.1 / 0 / 0 / 0.
    """
    shape = _check_last("p_hat", p_hat, None)
    k = shape[-1] - 1
    _check_int_range("slot_now", slot_now, 0, k - 1, "a slot position")
    _check_int_range("num_slots", num_slots, 1, k, "a slot count")
    _check_same("slot_now.shape", tuple(np.shape(slot_now)), shape[:-1], "p_hat.shape[:-1]")
    _check_same("num_slots.shape", tuple(np.shape(num_slots)), shape[:-1], "p_hat.shape[:-1]")
    return _route_offset_mass(jnp.asarray(p_hat, jnp.float32), jnp.asarray(slot_now, jnp.int32),
                              jnp.asarray(num_slots, jnp.int32))


def _stats(values: np.ndarray) -> dict:
    n = values.size
    stderr = float(values.std(ddof=1) / math.sqrt(n)) if n > 1 else float("nan")
    return {"mean": float(values.mean()), "stderr": stderr, "count": int(n)}


def summarise(values, groups=None) -> dict:
    """Mean, standard error and count, overall and per group id (numpy; not a hot path).

    values: (Q,) or any shape, per-query numbers. groups: same shape, group ids (ints or strings,
    e.g. category or horizon Δτ), or None. Returns
    ``{"overall": {"mean", "stderr", "count"}, "by_group": {id: {...}}}`` (``by_group`` only with
    groups; ids as Python scalars, sorted). stderr is NaN for a group of one.
    """
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        raise ValueError("values is empty")
    out: dict = {"overall": _stats(v.ravel())}
    if groups is None:
        return out
    g = np.asarray(groups)
    if g.shape != v.shape:
        raise ValueError(f"groups must have the shape of values {v.shape}; got {g.shape}")
    by_group: dict[Hashable, dict] = {}
    for gid in np.unique(g):
        by_group[gid.item()] = _stats(v[g == gid])
    out["by_group"] = by_group
    return out
