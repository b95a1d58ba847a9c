"""Tests for flowmaps_jax.evaluation.slots: slot assignment, the slot scores (TV, top-1, search
cost) with known answers and brute force, the reference slot predictors."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support import BOXES, MASK, Q  # two real slots of a 3-slot padded problem

from flowmaps_jax import tables as A  # the assignment rule
from flowmaps_jax.evaluation import priors as P
from flowmaps_jax.evaluation import slots as S


def scores(p_hat, q, mask=None) -> dict:
    """slot_scores with every slot real unless a mask is given."""
    return S.slot_scores(p_hat, q, np.ones(np.shape(q), bool) if mask is None else mask)


def random_distributions(rng, batch, k, zeros=True):
    """(batch, k) random probability vectors, some entries exactly zero, some exact ties."""
    p = rng.dirichlet(np.ones(k), size=batch)
    if zeros:
        p = np.where(rng.random((batch, k)) < 0.25, 0.0, p)
        p[:, 0] += 1e-3  # never all zero
    p = np.round(p * 8) / 8  # coarse values → many exact ties
    p = np.where(p.sum(-1, keepdims=True) > 0, p, 1.0)
    return (p / p.sum(-1, keepdims=True)).astype(np.float32)


def brute_force_cost(order, q):
    """Σ rank_k q_k for one explicit visiting order (a permutation of slot indices)."""
    return sum((pos + 1) * q[k] for pos, k in enumerate(order))


# --------------------------------------------------------------------------- assignment


def test_assignment_v2_nearest_centre_within_three_centre_sigmas():
    # BOXES are 0.1-sided objects: the v2 radius is max(0.05, 3 · 0.35 · 0.1) = 0.105.
    np.testing.assert_allclose(A.assign_radius(BOXES[:2]), [0.105, 0.105], rtol=1e-6)
    samples = np.array([
        BOXES[1],                                   # exactly on slot 1
        BOXES[0] + [0.1, 0.0, 0.0, 0.0],            # centre 0.1 away: inside slot 0's radius
        BOXES[0] + [0.0, 0.11, 0.0, 0.0],           # centre 0.11 away: off
        [0.0, 0.0, 0.0, 0.01],                      # next to the padded slot only → off
        (BOXES[0] + BOXES[1]) / 2,                  # far from both → off
        [0.15, 0.25, 0.2, 0.2],                     # slot 0's centre, another size: slot 0
    ], np.float32)
    one_each = A.empirical_slots(samples[:, None], np.broadcast_to(BOXES, (6, 3, 4)),
                                 np.broadcast_to(MASK, (6, 3)))  # one sample per query
    np.testing.assert_array_equal(np.argmax(one_each, -1), [1, 0, 3, 3, 3, 0])
    np.testing.assert_allclose(A.empirical_slots(samples, BOXES, MASK), [2 / 6, 1 / 6, 0, 3 / 6],
                               rtol=1e-6)
    # Nearest centre wins when two slots are within their radius.
    close = np.array([[0.2, 0.3, 0.1, 0.1], [0.2, 0.33, 0.1, 0.1]], np.float32)
    np.testing.assert_allclose(
        A.empirical_slots(np.array([[0.2, 0.32, 0.1, 0.1]], np.float32), close, np.ones(2, bool)),
        [0.0, 1.0, 0.0])
    # A larger least radius captures the far sample; small objects keep the 0.05 floor.
    np.testing.assert_allclose(A.empirical_slots(samples[2:3], BOXES, MASK, radius=0.12),
                               [1.0, 0.0, 0.0, 0.0])
    tiny = np.array([[0.2, 0.3, 0.02, 0.02]], np.float32)
    np.testing.assert_allclose(A.assign_radius(tiny), [0.05])
    moved = tiny + np.float32([0.049, 0, 0, 0])
    np.testing.assert_allclose(A.empirical_slots(moved, tiny, np.ones(1, bool)), [1.0, 0.0])


def test_histogram_counts_over_n():
    samples = np.stack([BOXES[0], BOXES[0], BOXES[1], BOXES[2] + 0.5])
    np.testing.assert_allclose(A.empirical_slots(samples, BOXES, MASK), [0.5, 0.25, 0.0, 0.25])


# --------------------------------------------------------------------------- scores


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(0.0, 1.0), min_size=4, max_size=4).filter(lambda v: sum(v) > 1e-3),
       st.integers(0, 3))
def test_last_seen_tv_is_one_minus_q_now(weights, now):
    q = np.asarray(weights, np.float32) / np.float32(sum(weights))
    q = q / q.sum()
    tv = scores(P.last_seen_slots(now, 4), q)["tv"]
    assert float(tv) == pytest.approx(1.0 - q[now], abs=1e-5)


def test_uniform_and_oracle_tv():
    q = np.array([[0.1, 0.6, 0.3, 0.0], [0.5, 0.5, 0.0, 0.0]], np.float32)
    tv = scores(P.uniform_slots(np.array([3, 2]), 4), q)["tv"]
    want = [0.5 * (abs(1 / 3 - 0.1) + abs(1 / 3 - 0.6) + abs(1 / 3 - 0.3)), 0.0]
    np.testing.assert_allclose(tv, want, atol=1e-6)
    np.testing.assert_allclose(scores(P.oracle_slots(q), q)["tv"], 0.0, atol=1e-7)
    all_off = np.array([0, 0, 0, 0, 1.0], np.float32)
    assert float(scores(all_off, q[0])["tv"]) == pytest.approx(1.0)


def test_top1_and_ties():
    q = np.array([0.2, 0.5, 0.3], np.float32)
    clear = np.array([0.1, 0.6, 0.2, 0.1], np.float32)
    wrong = np.array([0.6, 0.1, 0.2, 0.1], np.float32)
    tie = np.array([0.4, 0.4, 0.0, 0.2], np.float32)         # slots 0 and 1 tied best
    tie_rev = np.array([0.0, 0.4, 0.4, 0.2], np.float32)     # slots 1 and 2 tied best
    off = np.array([0.0, 0.0, 0.0, 1.0], np.float32)         # every sample off
    batch = np.stack([clear, wrong, tie, tie_rev, off])
    np.testing.assert_allclose(scores(batch, np.broadcast_to(q, (5, 3)))["top1"],
                               [1, 0, 0.5, 0.5, 1 / 3], atol=1e-6)
    # Ties in q: any mode counts; padded slots never compete.
    q_tie = np.array([0.5, 0.5, 0.0], np.float32)
    assert float(scores(np.array([0, 1.0, 0, 0], np.float32), q_tie)["top1"]) == 1.0
    assert float(scores(off, q_tie, np.array([True, True, False]))["top1"]) == 1.0


def test_search_cost_ratio_known_values():
    q = np.array([0.2, 0.5, 0.3, 0.0], np.float32)
    mask = np.array([True, True, True, False])
    oracle_cost = 1 * 0.5 + 2 * 0.3 + 3 * 0.2  # visiting by decreasing q
    p_hat = np.array([0.6, 0.0, 0.4, 0.0, 0.0], np.float32)  # order 0, 2, 1
    assert float(scores(p_hat, q, mask)["search_cost_ratio"]) == pytest.approx(
        (1 * 0.2 + 2 * 0.3 + 3 * 0.5) / oracle_cost, rel=1e-6)
    # All off: every order equally likely → each real slot has mean rank 2; the padded slot is
    # excluded from the tie (without the mask it would join it and inflate the cost to 2.5).
    off = np.array([0, 0, 0, 0, 1.0], np.float32)
    assert float(scores(off, q, mask)["search_cost_ratio"]) == pytest.approx(2.0 / oracle_cost)
    assert float(scores(off, q)["search_cost_ratio"]) == pytest.approx(2.5 / oracle_cost)


@pytest.mark.parametrize("k", [1, 2, 3, 4, 5])
def test_search_cost_ratio_against_every_permutation(k):
    """Numerator: the mean cost over the visiting orders consistent with p̂ (ties broken at
    random); denominator: the least cost over all k! orders."""
    rng = np.random.default_rng(k)
    q = random_distributions(rng, 64, k)
    p_hat = np.concatenate([random_distributions(rng, 64, k), np.zeros((64, 1), np.float32)], -1)
    ratio = scores(p_hat, q)["search_cost_ratio"]
    perms = list(itertools.permutations(range(k)))
    for i in range(64):
        s = p_hat[i, :k]
        consistent = [o for o in perms if all(s[a] >= s[b] for a, b in itertools.pairwise(o))]
        mean_cost = np.mean([brute_force_cost(o, q[i]) for o in consistent])
        least = min(brute_force_cost(o, q[i]) for o in perms)
        assert ratio[i] == pytest.approx(mean_cost / least, rel=1e-5)
        assert ratio[i] >= 1 - 1e-6


# --------------------------------------------------------------------------- reference predictors


def test_reference_predictors():
    np.testing.assert_allclose(P.uniform_slots(np.array(2), 3), [0.5, 0.5, 0, 0])
    np.testing.assert_allclose(P.last_seen_slots(np.array([0, 2]), 3),
                               [[1, 0, 0, 0], [0, 0, 1, 0]])
    np.testing.assert_allclose(P.oracle_slots(Q), [0.3, 0.7, 0.0, 0.0], atol=1e-7)


def test_sampled_oracle_is_an_unbiased_noisy_histogram_of_q():
    q = jnp.asarray([[0.5, 0.3, 0.2, 0.0], [0.1, 0.0, 0.9, 0.0]])
    one = P.sampled_oracle_slots(jax.random.PRNGKey(0), q, 1)  # a single draw: one-hot
    np.testing.assert_allclose(one.sum(-1), 1.0)
    assert set(np.unique(np.asarray(one))) <= {0.0, 1.0}
    qs = jnp.broadcast_to(q, (500, 2, 4))
    p_hat = {n: np.asarray(P.sampled_oracle_slots(jax.random.PRNGKey(2), qs, n)) for n in (25, 100)}
    np.testing.assert_allclose(p_hat[100].mean(0)[:, :-1], q, atol=0.01)  # 50,000 draws
    for n, p in p_hat.items():
        np.testing.assert_allclose(p * n, np.round(p * n), atol=1e-4)  # counts / n
        assert np.all(p[..., 3] == 0.0) and np.all(p[..., 1, 1] == 0.0)  # q = 0: never drawn
        assert np.all(p[..., -1] == 0.0)  # nothing "off"
    # finite-sample TV shrinks like 1/sqrt(n)
    tv = {n: float(np.mean(scores(p, qs)["tv"])) for n, p in p_hat.items()}
    assert 1.6 < tv[25] / tv[100] < 2.4


def test_route_offset_mass_of_the_exact_posterior_one_step_ahead():
    q = jnp.array([[0.0, 0.2, 0.7, 0.1, 0.0, 0.0],     # now at slot 1 of 5
                   [0.7, 0.1, 0.0, 0.0, 0.2, 0.0]])    # now at slot 4 of 5: wraps around
    mass = S.route_offset_mass(P.oracle_slots(q), jnp.array([1, 4]), jnp.array([5, 5]))
    np.testing.assert_allclose(mass, [[0.2, 0.7, 0.1, 0.0, 0.0, 0.0]] * 2, atol=1e-6)
    # a 3-slot route: offset +3 is offset 0 again, so it is not counted twice
    p3 = jnp.array([[0.5, 0.25, 0.0, 0.0, 0.25]])
    mass3 = S.route_offset_mass(p3, jnp.array([0]), jnp.array([3]))
    np.testing.assert_allclose(mass3, [[0.5, 0.25, 0.0, 0.0, 0.0, 0.25]], atol=1e-6)
    assert len(S.ROUTE_OFFSET_LABELS) == mass3.shape[-1]


# --------------------------------------------------------------------------- bad inputs


P2 = np.array([0.5, 0.5, 0.0])


@pytest.mark.parametrize("call, match", [
    (lambda: scores(np.array([0.5, 0.4, 0.0]), np.array([0.5, 0.5])), "p_hat must sum"),
    (lambda: scores(P2, np.array([1.5, -0.5])), "q has negative"),
    (lambda: scores(np.array([0.5, 0.5]), np.array([0.5, 0.5])), "p_hat must have shape"),
    (lambda: S.slot_scores(np.array([1.0, 0, 0]), np.array([0.5, 0.5]), np.array([2, 1])),
     "slot_mask"),
    (lambda: S.slot_scores(np.array([1.0, 0, 0]), np.array([0.5, 0.5]), np.array([True, False])),
     "q puts probability"),
    (lambda: A.empirical_slots(np.zeros((2, 4)), BOXES, MASK, radius=0.0), "radius"),
    (lambda: A.empirical_slots(np.zeros((2, 3)), BOXES, MASK), "samples must have shape"),
    (lambda: P.last_seen_slots(np.array([3]), 3), "slot_now"),
    (lambda: P.uniform_slots(np.array([0]), 3), "count"),
    (lambda: P.sampled_oracle_slots(jax.random.PRNGKey(0), jnp.asarray([0.5, 0.6]), 4), "q"),
    (lambda: P.sampled_oracle_slots(jax.random.PRNGKey(0), jnp.asarray([0.5, 0.5]), 0), "n"),
    (lambda: S.route_offset_mass(np.full((2, 6), 1 / 6), np.array([1, 9]), np.array([5, 5])),
     "slot_now"),
    (lambda: S.route_offset_mass(np.full((2, 6), 1 / 6), np.array([1, 1]), np.array([5, 0])),
     "num_slots"),
])
def test_bad_slot_inputs_raise_value_error(call, match):
    with pytest.raises(ValueError, match=match):
        call()
