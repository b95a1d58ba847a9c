"""Slot metrics (docs/protocol.md): a slot distribution p̂ (..., K + 1) (K slots, then "off")
against the exact posterior q (..., K): total variation, top-1 and the search-cost ratio (ties
within ``TIE_ATOL`` broken uniformly, the expectation reported). ``slot_mask`` (..., K) True on
real slots. Public functions validate once and run a jitted kernel that checks nothing.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.validation import (
    PROB_ATOL,
    check_array,
    check_int_array,
    check_mask,
    check_probabilities,
)

TIE_ATOL = 1e-6
"""Two slot scores closer than this are tied."""
SLOT_METRICS = ("tv", "top1", "search_cost_ratio")
"""The keys of :func:`slot_scores`."""
ROUTE_OFFSET_LABELS = ("0", "+1", "+2", "+3", "beyond", "off")
"""The entries of :func:`route_offset_mass`: route offsets 0 (stays) to +3, larger ones, off."""
_ROUTE_OFFSETS = 4  # offsets reported one by one: 0, +1, +2, +3


# --------------------------------------------------------------------------- scores against q


@jax.jit
def _tv(p_hat, q):
    return 0.5 * jnp.sum(jnp.abs(p_hat[..., :-1] - q), axis=-1) + 0.5 * p_hat[..., -1]


def _modes(scores, valid):
    """(..., K) bool: the real slots whose score is within TIE_ATOL of the best real score."""
    best = jnp.max(jnp.where(valid, scores, -jnp.inf), axis=-1, keepdims=True)
    return valid & (scores >= best - TIE_ATOL)


@jax.jit
def _top1(p_hat, q, slot_mask):
    p_modes = _modes(p_hat[..., :-1], slot_mask)
    q_modes = _modes(q, slot_mask)
    return jnp.sum(p_modes & q_modes, axis=-1) / jnp.sum(p_modes, axis=-1)


def _visit_ranks(scores, valid):
    """(..., K) mean rank (1 = visited first) of each real slot, visiting by decreasing score.

    Tied slots share their group's mean rank; padded slots come after all real ones.
    """
    k = scores.shape[-1]
    s_i, s_j = scores[..., :, None], scores[..., None, :]
    real_j = valid[..., None, :]
    higher = real_j & (s_j > s_i + TIE_ATOL)
    tied = real_j & (jnp.abs(s_j - s_i) <= TIE_ATOL) & ~jnp.eye(k, dtype=bool)
    rank = 1.0 + jnp.sum(higher, axis=-1) + 0.5 * jnp.sum(tied, axis=-1)
    return jnp.where(valid, rank, jnp.sum(valid, axis=-1, keepdims=True) + 1.0)


@jax.jit
def _search_cost(scores, q, slot_mask):
    return jnp.sum(_visit_ranks(scores, slot_mask) * q, axis=-1)


def score_slots(p_hat, q, slot_mask) -> dict[str, np.ndarray]:
    """The kernels of :func:`slot_scores` (no checks): p̂ (..., K + 1), q (..., K) float32,
    slot_mask (..., K) bool. Slicing and dividing on the host: no program per shape for them."""
    ratio = (np.asarray(_search_cost(np.asarray(p_hat)[..., :-1], q, slot_mask))
             / np.asarray(_search_cost(q, q, slot_mask)))
    return {"tv": np.asarray(_tv(p_hat, q)), "top1": np.asarray(_top1(p_hat, q, slot_mask)),
            "search_cost_ratio": ratio}


def slot_scores(p_hat: jnp.ndarray, q: jnp.ndarray, slot_mask: jnp.ndarray
                ) -> dict[str, np.ndarray]:
    """The protocol's slot metrics of p̂ (..., K + 1) against q (..., K); slot_mask (..., K) bool.

    Returns ``{"tv", "top1", "search_cost_ratio"}`` (:data:`SLOT_METRICS`), each (...) numpy:

    * tv: total variation ½Σ_k|p̂_k − q_k| + ½p̂_off.
    * top1: is p̂'s best real slot a mode of q? Ties in q: any mode counts; ties in p̂: the fraction
      of p̂'s tied best slots that are modes of q. All samples off: every real slot ties.
    * search_cost_ratio: Σ_k rank_k q_k visiting slots by decreasing p̂ (tied groups share their
      mean rank), over the same sum visiting by decreasing q (the least possible); ≥ 1.
    """
    q = check_probabilities("q", q, (..., None), atol=PROB_ATOL, min_value=-PROB_ATOL)
    *batch, k = q.shape  # the queries' dims, the K slots
    slot_mask = check_mask("slot_mask", slot_mask, (*batch, k))
    check_probabilities("q", q,  # no mass where slot_mask is False
                        atol=PROB_ATOL, min_value=-PROB_ATOL, support=slot_mask,
                        support_name="slot_mask")
    p_hat = check_probabilities("p_hat", p_hat, (*batch, k + 1), atol=PROB_ATOL,
                                min_value=-PROB_ATOL, support=slot_mask,
                                support_name="slot_mask")
    return score_slots(np.asarray(p_hat, np.float32), np.asarray(q, np.float32),
                       np.asarray(slot_mask, bool))


# --------------------------------------------------------------------------- routines


@jax.jit
def offset_mass(p_hat, slot_now, num_slots):
    """The kernel of :func:`route_offset_mass` (no checks; p̂ float32, the rest int32)."""
    k = p_hat.shape[-1] - 1
    offsets = jnp.arange(_ROUTE_OFFSETS)
    slot = (slot_now[..., None] + offsets) % jnp.maximum(num_slots[..., None], 1)  # (..., 4)
    mass = jnp.take_along_axis(p_hat[..., :k], slot, axis=-1)
    mass = jnp.where(offsets < num_slots[..., None], mass, 0.0)  # offset ≥ K wraps: not counted
    off = p_hat[..., k:]
    beyond = jnp.clip(1.0 - mass.sum(-1, keepdims=True) - off, 0.0, 1.0)
    return jnp.concatenate([mass, beyond, off], axis=-1)


def route_offset_mass(p_hat: jnp.ndarray, slot_now: jnp.ndarray,
                      num_slots: jnp.ndarray) -> jnp.ndarray:
    """Where along the visiting order a slot distribution puts its mass, relative to now.

    p_hat: (..., K + 1) slot distribution (last bin "off"); slot_now: (...) int position at τ;
    num_slots: (...) int. Returns (..., 6) (:data:`ROUTE_OFFSET_LABELS`): mass at route offsets
    0, +1, +2, +3, beyond, and off every slot.
    """
    p_hat = check_array("p_hat", p_hat, (..., None))
    batch, k = tuple(p_hat.shape[:-1]), p_hat.shape[-1] - 1
    slot_now = check_int_array("slot_now", slot_now, 0, k - 1, shape=batch)
    num_slots = check_int_array("num_slots", num_slots, 1, k, shape=batch)
    return offset_mass(jnp.asarray(p_hat, jnp.float32), jnp.asarray(slot_now, jnp.int32),
                       jnp.asarray(num_slots, jnp.int32))
