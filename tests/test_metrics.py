"""Tests for flowmaps_jax.metrics: known answers for every metric of the evaluation protocol."""

from __future__ import annotations

import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flowmaps_jax import metrics as M

# Two real slots of a 3-slot padded problem: boxes (y, x, h, w), square objects like FlowSim's.
BOXES = np.array([[0.20, 0.30, 0.10, 0.10],
                  [0.60, 0.50, 0.10, 0.10],
                  [0.00, 0.00, 0.00, 0.00]], np.float32)
MASK = np.array([True, True, False])
Q = np.array([0.3, 0.7, 0.0], np.float32)


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


# --------------------------------------------------------------------------- mixture


def test_sigma_follows_protocol():
    box = np.array([[0.1, 0.2, 0.3, 0.4]], np.float32)
    np.testing.assert_allclose(M.gt_mixture_sigma(box), [[0.105, 0.14, 0.006, 0.008]], rtol=1e-6)


def test_centre_round_trip():
    boxes = np.random.default_rng(0).random((5, 4)).astype(np.float32)
    c = M.to_centre(boxes)
    np.testing.assert_allclose(c[:, 0], boxes[:, 0] + boxes[:, 2] / 2, rtol=1e-6)
    np.testing.assert_allclose(M.from_centre(c), boxes, rtol=1e-6, atol=1e-7)


def test_log_prob_matches_direct_formula():
    rng = np.random.default_rng(1)
    x = (BOXES[:2][rng.integers(0, 2, 7)] + 0.02 * rng.standard_normal((7, 4))).astype(np.float32)
    got = M.gt_mixture_log_prob(x, Q, BOXES, MASK)

    def component(xi, b):  # diagonal Gaussian in centre coordinates, written out by hand
        cx = np.array([xi[0] + xi[2] / 2, xi[1] + xi[3] / 2, xi[2], xi[3]], np.float64)
        mu = np.array([b[0] + b[2] / 2, b[1] + b[3] / 2, b[2], b[3]], np.float64)
        sd = np.array([0.35 * b[2], 0.35 * b[3], 0.02 * b[2], 0.02 * b[3]], np.float64)
        return np.prod(np.exp(-0.5 * ((cx - mu) / sd) ** 2) / (sd * np.sqrt(2 * np.pi)))

    want = [np.log(0.3 * component(xi, BOXES[0]) + 0.7 * component(xi, BOXES[1])) for xi in x]
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-3)


def test_log_prob_integrates_to_one():
    # Riemann sum over a 4-D grid in (y, x, h, w). The trapezoid rule on a Gaussian is accurate to
    # ~1e-8 with spacing σ, and ±8σ leaves no tail mass. Both slots have side 0.1:
    # σ_c = 0.035, σ_s = 0.002.
    step_c, step_s = 0.035, 0.002
    y = np.arange(-0.1, 0.9, step_c)
    s = np.arange(0.1 - 0.016, 0.1 + 0.016 + 1e-9, step_s)
    grid = np.stack(np.meshgrid(y, y, s, s, indexing="ij"), -1).reshape(-1, 4).astype(np.float32)
    log_q = M.gt_mixture_log_prob(grid, Q, BOXES, MASK)
    total = float(jnp.sum(jnp.exp(log_q))) * step_c**2 * step_s**2
    assert total == pytest.approx(1.0, abs=1e-3)


def test_sampler_moments_and_padding():
    n = 40_000
    x = M.sample_gt_mixture(jax.random.key(0), Q, BOXES, n, MASK)
    assert x.shape == (n, 4)
    slot = M.assign_slots(x, BOXES, MASK, radius=0.3)
    frac_first = float(jnp.mean(slot == 0))
    assert frac_first == pytest.approx(0.3, abs=4 * math.sqrt(0.21 / n))
    assert not bool(jnp.any(slot == 2))  # the padded slot is never drawn
    c = np.asarray(M.to_centre(x))[np.asarray(slot) == 1]
    mu = np.asarray(M.to_centre(BOXES[1]))
    sd = np.asarray(M.gt_mixture_sigma(BOXES[1:2]))[0]
    np.testing.assert_allclose(c.mean(0), mu, atol=4 * sd.max() / math.sqrt(len(c)))
    np.testing.assert_allclose(c.std(0), sd, rtol=0.03)


# --------------------------------------------------------------------------- KL


def test_continuous_kl_known_values():
    est = M.continuous_kl(jnp.array([1.0, 2.0, 3.0]), jnp.zeros(3))
    assert float(est.mean) == pytest.approx(2.0)
    assert float(est.stderr) == pytest.approx(1 / math.sqrt(3), rel=1e-5)


def test_oracle_kl_is_zero():
    qb = np.stack([Q, np.array([1.0, 0.0, 0.0], np.float32)])
    bb = np.stack([BOXES, BOXES])
    mask = np.stack([MASK, MASK])
    est = M.kl_from_log_prob_fn(jax.random.key(1), qb, bb,
                                lambda x: M.gt_mixture_log_prob(x, qb, bb, mask), 256, mask)
    np.testing.assert_allclose(est.mean, 0.0, atol=1e-5)
    oracle = M.kl_slot_model(jax.random.key(1), qb, bb, qb, 256, mask)
    np.testing.assert_allclose(oracle.mean, 0.0, atol=1e-5)


def test_kl_slot_model_last_seen_is_positive():
    last = np.array([1.0, 0.0, 0.0], np.float32)
    est = M.kl_slot_model(jax.random.key(2), Q, BOXES, last, 4000, MASK)
    assert float(est.mean) > 10 * float(est.stderr) > 0


def analytic_kl_single_component(box, mean, var):
    """KL(N(μ_q, Σ_q) ‖ N(m, diag var)) with q's covariance mapped to (y, x, h, w)."""
    sd = np.array([0.35 * box[2], 0.35 * box[3], 0.02 * box[2], 0.02 * box[3]], np.float64)
    shear = np.array([[1, 0, -0.5, 0], [0, 1, 0, -0.5], [0, 0, 1, 0], [0, 0, 0, 1]], np.float64)
    cov = shear @ np.diag(sd**2) @ shear.T
    mu = np.asarray(box, np.float64)
    d = np.asarray(mean, np.float64) - mu
    return 0.5 * (np.sum(np.diag(cov) / var) + np.sum(d**2 / var) - 4
                  + np.sum(np.log(var)) - np.linalg.slogdet(cov)[1])


@pytest.mark.parametrize("shift", [0.0, 0.1])
def test_gaussian_model_kl_matches_closed_form(shift):
    box = BOXES[0]
    q = np.array([1.0, 0.0, 0.0], np.float32)
    mean = box + np.array([shift, -shift, 0.0, 0.0], np.float32)
    log_var = np.log(np.array([0.04, 0.04, 0.01, 0.01], np.float32))
    est = M.kl_gaussian_model(jax.random.key(3), q, BOXES, mean, log_var, 4000, MASK)
    want = analytic_kl_single_component(box, mean, np.exp(log_var))
    assert float(est.mean) == pytest.approx(want, abs=4 * float(est.stderr) + 1e-3)
    assert want > 0


def test_shifted_gaussian_has_larger_kl():
    q = np.array([1.0, 0.0, 0.0], np.float32)
    kls = [float(M.kl_gaussian_model(jax.random.key(4), q, BOXES, BOXES[0] + d, 0.0, 4000,
                                     MASK).mean) for d in (0.0, 0.3)]
    assert 0 < kls[0] < kls[1]


# --------------------------------------------------------------------------- assignment


def test_assignment_radius_and_off_bin():
    samples = np.array([
        BOXES[1],                                   # exactly on slot 1
        BOXES[0] + [0.049, 0.0, 0.0, 0.0],          # inside the radius of slot 0
        BOXES[0] + [0.0, 0.051, 0.0, 0.0],          # just outside → off
        [0.0, 0.0, 0.0, 0.01],                      # next to the padded slot only → off
        (BOXES[0] + BOXES[1]) / 2,                  # far from both → off
    ], np.float32)
    got = M.assign_slots(samples, BOXES, MASK)
    np.testing.assert_array_equal(got, [1, 0, 3, 3, 3])
    # Nearest wins when two slots are within the radius.
    close = np.array([[0.2, 0.3, 0.1, 0.1], [0.2, 0.33, 0.1, 0.1]], np.float32)
    np.testing.assert_array_equal(
        M.assign_slots(np.array([[0.2, 0.32, 0.1, 0.1]], np.float32), close, np.ones(2, bool)),
        [1])
    # A wider radius captures the far sample.
    assert int(M.assign_slots(samples[2:3], BOXES, MASK, radius=0.06)[0]) == 0


def test_histogram_counts_over_n():
    p = M.slot_histogram(jnp.array([[0, 0, 1, 3], [3, 3, 3, 3]]), 3)
    np.testing.assert_allclose(p, [[0.5, 0.25, 0.0, 0.25], [0, 0, 0, 1.0]])
    samples = np.stack([BOXES[0], BOXES[0], BOXES[1], BOXES[2] + 0.5])
    np.testing.assert_allclose(M.empirical_slots(samples, BOXES, MASK), [0.5, 0.25, 0.0, 0.25])


# --------------------------------------------------------------------------- slot metrics


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(0.0, 1.0), min_size=4, max_size=4).filter(lambda v: sum(v) > 1e-3),
       st.integers(0, 3))
def test_last_seen_tv_is_one_minus_q_now(weights, now):
    q = np.asarray(weights, np.float32) / np.float32(sum(weights))
    q = q / q.sum()
    tv = M.slot_tv(M.last_seen_slots(now, 4), q)
    assert float(tv) == pytest.approx(1.0 - q[now], abs=1e-5)


def test_uniform_and_oracle_tv():
    q = np.array([[0.1, 0.6, 0.3, 0.0], [0.5, 0.5, 0.0, 0.0]], np.float32)
    count = np.array([3, 2])
    tv = M.slot_tv(M.uniform_slots(count, 4), q)
    want = [0.5 * (abs(1 / 3 - 0.1) + abs(1 / 3 - 0.6) + abs(1 / 3 - 0.3)), 0.0]
    np.testing.assert_allclose(tv, want, atol=1e-6)
    np.testing.assert_allclose(M.slot_tv(M.oracle_slots(q), q), 0.0, atol=1e-7)
    all_off = np.array([0, 0, 0, 0, 1.0], np.float32)
    assert float(M.slot_tv(all_off, q[0])) == pytest.approx(1.0)


def test_reference_predictors():
    np.testing.assert_allclose(M.uniform_slots(np.array(2), 3), [0.5, 0.5, 0, 0])
    np.testing.assert_allclose(M.last_seen_slots(np.array([0, 2]), 3),
                               [[1, 0, 0, 0], [0, 0, 1, 0]])
    np.testing.assert_allclose(M.oracle_slots(Q), [0.3, 0.7, 0.0, 0.0], atol=1e-7)


def test_sampled_oracle_is_an_unbiased_noisy_histogram_of_q():
    q = jnp.asarray([[0.5, 0.3, 0.2, 0.0], [0.1, 0.0, 0.9, 0.0]])
    one = M.sampled_oracle_slots(jax.random.PRNGKey(0), q, 1)  # a single draw: one-hot
    np.testing.assert_allclose(one.sum(-1), 1.0)
    assert set(np.unique(np.asarray(one))) <= {0.0, 1.0}
    many = jax.vmap(lambda k: M.sampled_oracle_slots(k, q, 25))(
        jax.random.split(jax.random.PRNGKey(1), 4000))  # (4000, 2, 5)
    np.testing.assert_allclose(many.mean(0)[:, :-1], q, atol=0.01)
    assert np.all(many[..., 3] == 0.0) and np.all(many[..., 1, 1] == 0.0)  # q = 0: never drawn
    assert np.all(many[..., -1] == 0.0)  # nothing "off"
    # finite-sample TV shrinks like 1/sqrt(n)
    qs = jnp.broadcast_to(q, (500, 2, 4))
    tv = lambda n: float(jnp.mean(M.slot_tv(  # noqa: E731
        M.sampled_oracle_slots(jax.random.PRNGKey(2), qs, n), qs)))
    assert 1.6 < tv(25) / tv(100) < 2.4
    with pytest.raises(ValueError, match="q"):
        M.sampled_oracle_slots(jax.random.PRNGKey(0), jnp.asarray([0.5, 0.6]), 4)
    with pytest.raises(ValueError, match="n"):
        M.sampled_oracle_slots(jax.random.PRNGKey(0), q, 0)


def test_top1_and_ties():
    q = np.array([0.2, 0.5, 0.3], np.float32)
    mask = np.ones(3, bool)
    clear = np.array([0.1, 0.6, 0.2, 0.1], np.float32)
    wrong = np.array([0.6, 0.1, 0.2, 0.1], np.float32)
    tie = np.array([0.4, 0.4, 0.0, 0.2], np.float32)         # slots 0 and 1 tied best
    tie_rev = np.array([0.0, 0.4, 0.4, 0.2], np.float32)     # slots 1 and 2 tied best
    off = np.array([0.0, 0.0, 0.0, 1.0], np.float32)         # every sample off
    batch = np.stack([clear, wrong, tie, tie_rev, off])
    qb = np.broadcast_to(q, (5, 3))
    np.testing.assert_allclose(M.top1(batch, qb), [1, 0, 0.5, 0.5, 1 / 3], atol=1e-6)
    np.testing.assert_allclose(M.top1(batch, qb, np.broadcast_to(mask, (5, 3)), "index"),
                               [1, 0, 0, 1, 0])
    # Ties in q: any mode counts; padded slots never compete.
    q_tie = np.array([0.5, 0.5, 0.0], np.float32)
    assert float(M.top1(np.array([0, 1.0, 0, 0], np.float32), q_tie)) == 1.0
    assert float(M.top1(off, q_tie, np.array([True, True, False]))) == 1.0


def test_search_cost_known_values():
    q = np.array([0.2, 0.5, 0.3, 0.0], np.float32)
    mask = np.array([True, True, True, False])
    p_hat = np.array([0.6, 0.0, 0.4, 0.0, 0.0], np.float32)  # order 0, 2, 1
    assert float(M.search_cost(p_hat, q, mask)) == pytest.approx(1 * 0.2 + 2 * 0.3 + 3 * 0.5)
    assert float(M.oracle_search_cost(q, mask)) == pytest.approx(1 * 0.5 + 2 * 0.3 + 3 * 0.2)
    assert float(M.search_cost_ratio(p_hat, q, mask)) == pytest.approx(2.3 / 1.7, rel=1e-6)
    # All off: every order equally likely → each real slot has mean rank 2; the padded slot is
    # excluded from the tie (without the mask it would join it and inflate the cost).
    off = np.array([0, 0, 0, 0, 1.0], np.float32)
    assert float(M.search_cost(off, q, mask)) == pytest.approx(2.0)
    assert float(M.search_cost(off, q)) == pytest.approx(2.5)
    assert float(M.search_cost(off, q, mask, "index")) == pytest.approx(1 * 0.2 + 2 * 0.5 + 3 * 0.3)


@pytest.mark.parametrize("k", [1, 2, 3, 4, 5])
def test_oracle_order_is_minimal_over_all_permutations(k):
    rng = np.random.default_rng(k)
    q = random_distributions(rng, 64, k)
    p_hat = np.concatenate([random_distributions(rng, 64, k), np.zeros((64, 1), np.float32)], -1)
    oracle = np.asarray(M.oracle_search_cost(q))
    perms = list(itertools.permutations(range(k)))
    best = np.array([min(brute_force_cost(o, qi) for o in perms) for qi in q])
    np.testing.assert_allclose(oracle, best, rtol=1e-5)
    ratio = np.asarray(M.search_cost_ratio(p_hat, q))
    assert np.all(ratio >= 1 - 1e-6)
    # "index" = the visiting order sorted by (−p̂, slot index); "average" = mean over tied orders.
    index = np.asarray(M.search_cost(p_hat, q, tie_break="index"))
    average = np.asarray(M.search_cost(p_hat, q))
    for i in range(64):
        scores = p_hat[i, :k]
        assert index[i] == pytest.approx(
            brute_force_cost(sorted(range(k), key=lambda j: (-scores[j], j)), q[i]), rel=1e-5)
        consistent = [o for o in perms
                      if all(scores[a] >= scores[b] for a, b in itertools.pairwise(o))]
        want = np.mean([brute_force_cost(o, q[i]) for o in consistent])
        assert average[i] == pytest.approx(want, rel=1e-5)


# --------------------------------------------------------------------------- jit / vmap


def test_jit_and_vmap_match_batched_call():
    rng = np.random.default_rng(7)
    q = random_distributions(rng, 6, 3)
    p_hat = np.concatenate([random_distributions(rng, 6, 3), np.zeros((6, 1), np.float32)], -1)
    mask = np.ones((6, 3), bool)
    boxes = np.broadcast_to([*BOXES[:2].tolist(), [0.8, 0.1, 0.1, 0.1]], (6, 3, 4)).astype(
        np.float32)
    x = (boxes[:, :2] + 0.02 * rng.standard_normal((6, 2, 4))).astype(np.float32)

    def all_metrics(p, qq, m, b, xx):
        return (M.slot_tv(p, qq), M.top1(p, qq, m), M.search_cost_ratio(p, qq, m),
                M.gt_mixture_log_prob(xx, qq, b, m), M.empirical_slots(xx, b, m))

    batched = all_metrics(p_hat, q, mask, boxes, x)  # leading batch dims, no vmap
    jitted = jax.jit(jax.vmap(all_metrics))(p_hat, q, mask, boxes, x)
    for b, j in zip(batched, jitted, strict=True):
        np.testing.assert_allclose(b, j, rtol=1e-5, atol=1e-5)
    # The sampler under jit + vmap (one key per query) gives the same draws as eagerly.
    keys = jax.random.split(jax.random.key(0), 6)
    sample = jax.jit(jax.vmap(lambda k, qq, b: M.sample_gt_mixture(k, qq, b, 4)))
    drawn = sample(keys, q, boxes)
    assert drawn.shape == (6, 4, 4)
    np.testing.assert_allclose(drawn[2], M.sample_gt_mixture(keys[2], q[2], boxes[2], 4),
                               rtol=1e-5, atol=1e-6)


# --------------------------------------------------------------------------- bad inputs


@pytest.mark.parametrize("call, match", [
    (lambda: M.slot_tv(np.array([0.5, 0.4, 0.0]), np.array([0.5, 0.5])), "p_hat must sum"),
    (lambda: M.slot_tv(np.array([0.5, 0.5, 0.0]), np.array([1.5, -0.5])), "q has negative"),
    (lambda: M.slot_tv(np.array([0.5, 0.5]), np.array([0.5, 0.5])), "p_hat must have shape"),
    (lambda: M.top1(np.array([1.0, 0, 0]), np.array([0.5, 0.5]), np.array([1, 1])),
     "slot_mask must be boolean"),
    (lambda: M.search_cost(np.array([1.0, 0, 0]), np.array([0.5, 0.5]), np.array([True, False])),
     "q puts probability"),
    (lambda: M.search_cost(np.array([1.0, 0, 0]), np.array([1.0, 0]), tie_break="random"),
     "tie_break"),
    (lambda: M.gt_mixture_log_prob(np.zeros((4, 3)), Q, BOXES), "x must have last dim 4"),
    (lambda: M.gt_mixture_log_prob(np.zeros((2, 4, 4)), Q, BOXES), r"x.shape\[:-2\]"),
    (lambda: M.gt_mixture_log_prob(np.zeros((4, 4)), Q, BOXES[:2]), "slot_boxes must have shape"),
    (lambda: M.gt_mixture_log_prob(np.zeros((4, 4)), Q, BOXES, MASK[:2]), "slot_mask"),
    (lambda: M.gt_mixture_log_prob(np.zeros((4, 4)), np.array([0.5, 0.0, 0.5]), BOXES),
     "positive h and w"),
    (lambda: M.sample_gt_mixture(jax.random.key(0), Q, BOXES, 0), "n must be"),
    (lambda: M.kl_gaussian_model(jax.random.key(0), Q, BOXES, np.zeros(3), 0.0, 8), "mean"),
    (lambda: M.kl_gaussian_model(jax.random.key(0), Q, BOXES, np.zeros(4), np.zeros(3), 8),
     "log_var"),
    (lambda: M.kl_from_log_prob_fn(jax.random.key(0), Q, BOXES, lambda x: x, 8),
     "log_prob_fn"),
    (lambda: M.continuous_kl(np.zeros(3), np.zeros(4)), "log_p"),
    (lambda: M.assign_slots(np.zeros((2, 4)), BOXES, MASK, radius=0.0), "radius"),
    (lambda: M.slot_histogram(np.array([0, 4]), 3), "assignment"),
    (lambda: M.last_seen_slots(np.array([3]), 3), "slot_now"),
    (lambda: M.uniform_slots(np.array([0]), 3), "count"),
    (lambda: M.summarise(np.zeros(3), np.zeros(2)), "groups"),
])
def test_bad_inputs_raise_value_error(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_shape_errors_raise_under_jit():
    with pytest.raises(ValueError, match="p_hat"):
        jax.jit(M.slot_tv)(jnp.ones(3) / 3, jnp.ones(3) / 3)


# --------------------------------------------------------------------------- aggregation


def test_summarise_overall_and_by_group():
    values = np.array([1.0, 3.0, 2.0, 4.0, 10.0])
    groups = np.array([1, 1, 2, 2, 3])
    out = M.summarise(values, groups)
    assert out["overall"]["mean"] == pytest.approx(4.0)
    assert out["overall"]["stderr"] == pytest.approx(np.std(values, ddof=1) / math.sqrt(5))
    assert out["overall"]["count"] == 5
    assert out["by_group"][1] == {"mean": 2.0, "stderr": pytest.approx(1.0), "count": 2}
    assert out["by_group"][2]["mean"] == pytest.approx(3.0)
    assert math.isnan(out["by_group"][3]["stderr"])
    assert set(M.summarise(values, np.array(list("aabbc")))["by_group"]) == {"a", "b", "c"}
    assert "by_group" not in M.summarise(values)
