"""Tests for flowmaps_jax.evaluation.kl: the ground-truth mixture q (σ, density, sampler) and the
KL(q‖p) estimate, against densities written out by hand and closed-form KLs."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support import BOXES, MASK, SHEAR, Q, mixture_log_density, protocol_sd

from flowmaps_jax.boxes import from_centre, to_centre
from flowmaps_jax.evaluation import kl
from flowmaps_jax.tables import empirical_slots

# --------------------------------------------------------------------------- the mixture


def test_sigma_follows_protocol():
    box = np.array([[0.1, 0.2, 0.3, 0.4]], np.float32)
    np.testing.assert_allclose(kl.gt_mixture_sigma(box), [[0.105, 0.14, 0.006, 0.008]], rtol=1e-6)


def test_centre_round_trip():
    boxes = np.random.default_rng(0).random((5, 4)).astype(np.float32)
    c = to_centre(boxes)
    np.testing.assert_allclose(c[:, 0], boxes[:, 0] + boxes[:, 2] / 2, rtol=1e-6)
    np.testing.assert_allclose(from_centre(c), boxes, rtol=1e-6, atol=1e-7)


def test_log_prob_matches_direct_formula():
    rng = np.random.default_rng(1)
    x = (BOXES[:2][rng.integers(0, 2, 7)] + 0.02 * rng.standard_normal((7, 4))).astype(np.float32)
    np.testing.assert_allclose(kl.gt_mixture_log_prob(x, Q, BOXES, MASK),
                               mixture_log_density(x, Q, BOXES), rtol=1e-4, atol=1e-3)


def test_log_prob_integrates_to_one():
    # Riemann sum over a 4-D grid in (y, x, h, w). The trapezoid rule on a Gaussian is accurate to
    # ~1e-8 with spacing σ, and ±8σ leaves no tail mass. Both slots have side 0.1:
    # σ_c = 0.035, σ_s = 0.002.
    step_c, step_s = 0.035, 0.002
    y = np.arange(-0.1, 0.9, step_c)
    s = np.arange(0.1 - 0.016, 0.1 + 0.016 + 1e-9, step_s)
    grid = np.stack(np.meshgrid(y, y, s, s, indexing="ij"), -1).reshape(-1, 4).astype(np.float32)
    log_q = kl.gt_mixture_log_prob(grid, Q, BOXES, MASK)
    total = float(jnp.sum(jnp.exp(log_q))) * step_c**2 * step_s**2
    assert total == pytest.approx(1.0, abs=1e-3)


def test_sampler_weights_moments_and_padding():
    n = 40_000
    x = np.asarray(kl.sample_gt_mixture(jax.random.key(0), Q, BOXES, n, MASK))
    assert x.shape == (n, 4)
    # within 0.3 of a real slot (8σ of the centre): nothing comes from the padded slot (q = 0)
    p_hat = np.asarray(empirical_slots(x, BOXES, MASK, radius=0.3))
    assert p_hat[0] == pytest.approx(0.3, abs=4 * math.sqrt(0.21 / n))
    assert p_hat[2] == 0.0 and p_hat[3] == 0.0
    near_second = np.linalg.norm(x - BOXES[1], axis=-1) < np.linalg.norm(x - BOXES[0], axis=-1)
    c = np.asarray(to_centre(x))[near_second]
    sd = protocol_sd(BOXES[1])
    np.testing.assert_allclose(c.mean(0), np.asarray(to_centre(BOXES[1])),
                               atol=4 * sd.max() / math.sqrt(len(c)))
    np.testing.assert_allclose(c.std(0), sd, rtol=0.03)


# --------------------------------------------------------------------------- KL


def test_continuous_kl_known_values():
    est = kl.continuous_kl(jnp.array([1.0, 2.0, 3.0]), jnp.zeros(3))
    assert float(est.mean) == pytest.approx(2.0)
    assert float(est.stderr) == pytest.approx(1 / math.sqrt(3), rel=1e-5)


def analytic_kl_single_component(box, mean, var) -> float:
    """KL(N(μ_q, Σ_q) ‖ N(m, diag var)) with q's covariance mapped to (y, x, h, w)."""
    cov = SHEAR @ np.diag(protocol_sd(box) ** 2) @ SHEAR.T
    d = np.asarray(mean, np.float64) - np.asarray(box, np.float64)
    return 0.5 * (np.sum(np.diag(cov) / var) + np.sum(d**2 / var) - 4
                  + np.sum(np.log(var)) - np.linalg.slogdet(cov)[1])


@pytest.mark.parametrize("shift", [0.0, 0.1])
def test_kl_of_a_gaussian_model_matches_closed_form(shift):
    """The MLP row's path: draws of q, log q, the model's diagonal-Gaussian log p, their mean."""
    box = BOXES[0]
    q = np.array([1.0, 0.0, 0.0], np.float32)
    mean = box + np.array([shift, -shift, 0.0, 0.0], np.float32)
    var = np.array([0.04, 0.04, 0.01, 0.01])
    x = kl.sample_gt_mixture(jax.random.key(3), q, BOXES, 4000, MASK)
    log_p = -0.5 * np.sum((np.asarray(x, np.float64) - mean) ** 2 / var + np.log(2 * np.pi * var),
                          axis=-1)
    est = kl.continuous_kl(kl.gt_mixture_log_prob(x, q, BOXES, MASK), log_p)
    want = analytic_kl_single_component(box, mean, var)
    assert float(est.mean) == pytest.approx(want, abs=4 * float(est.stderr) + 1e-3)
    assert want > 0


def test_kl_of_a_slot_model_is_positive_and_exact_against_q_itself():
    """A slot predictor's density is the mixture with its weights: last-seen (all on slot 0) is far
    from q = (0.3, 0.7); with q's own weights log q − log p vanishes draw by draw."""
    x = kl.sample_gt_mixture(jax.random.key(2), Q, BOXES, 4000, MASK)
    log_q = kl.gt_mixture_log_prob(x, Q, BOXES, MASK)
    last = kl.continuous_kl(log_q, kl.gt_mixture_log_prob(x, np.array([1.0, 0, 0], np.float32),
                                                           BOXES, MASK))
    assert float(last.mean) > 10 * float(last.stderr) > 0
    np.testing.assert_allclose(log_q, mixture_log_density(x, Q, BOXES), rtol=1e-4, atol=1e-3)


# --------------------------------------------------------------------------- jit / vmap


def test_jit_and_vmap_match_the_batched_call():
    rng = np.random.default_rng(7)
    q = rng.dirichlet(np.ones(3), size=6).astype(np.float32)
    boxes = np.broadcast_to([*BOXES[:2].tolist(), [0.8, 0.1, 0.1, 0.1]], (6, 3, 4)).astype(
        np.float32)
    mask = np.ones((6, 3), bool)
    x = (boxes[:, :2] + 0.02 * rng.standard_normal((6, 2, 4))).astype(np.float32)
    batched = kl.gt_mixture_log_prob(x, q, boxes, mask)  # leading batch dims, no vmap
    np.testing.assert_allclose(jax.jit(jax.vmap(kl.gt_mixture_log_prob))(x, q, boxes, mask),
                               batched, rtol=1e-5, atol=1e-5)
    # The sampler under jit + vmap (one key per query) gives the same draws as eagerly.
    keys = jax.random.split(jax.random.key(0), 6)
    drawn = jax.jit(jax.vmap(lambda k, qq, b: kl.sample_gt_mixture(k, qq, b, 4)))(keys, q, boxes)
    assert drawn.shape == (6, 4, 4)
    np.testing.assert_allclose(drawn[2], kl.sample_gt_mixture(keys[2], q[2], boxes[2], 4),
                               rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="x must have shape"):  # shapes are checked under jit
        jax.jit(kl.gt_mixture_log_prob)(x[..., :3], q, boxes, mask)


# --------------------------------------------------------------------------- bad inputs


@pytest.mark.parametrize("call, match", [
    (lambda: kl.gt_mixture_log_prob(np.zeros((4, 3)), Q, BOXES), "x must have shape"),
    (lambda: kl.gt_mixture_log_prob(np.zeros((2, 4, 4)), Q, BOXES),
     r"x must have shape \(\*, 4\) \(leading dims as in slot_probs\)"),
    (lambda: kl.gt_mixture_log_prob(np.zeros((4, 4)), Q, BOXES[:2]), "slot_boxes must have shape"),
    (lambda: kl.gt_mixture_log_prob(np.zeros((4, 4)), Q, BOXES, MASK[:2]), "slot_mask"),
    (lambda: kl.gt_mixture_log_prob(np.zeros((4, 4)), np.array([0.5, 0.0, 0.5]), BOXES),
     "positive h and w"),
    (lambda: kl.gt_mixture_log_prob(np.zeros((4, 4)), np.array([0.5, 0.6, 0.0]), BOXES),
     "slot_probs must sum"),
    (lambda: kl.gt_mixture_log_prob(np.zeros((4, 4)), Q, BOXES, np.array([True, False, False])),
     "slot_probs puts probability"),
    (lambda: kl.sample_gt_mixture(jax.random.key(0), Q, BOXES, 0), "n must be"),
    (lambda: kl.continuous_kl(np.zeros(3), np.zeros(4)), "log_p"),
    (lambda: kl.continuous_kl(np.zeros(1), np.zeros(1)), "at least 2 draws"),
])
def test_bad_mixture_inputs_raise_value_error(call, match):
    with pytest.raises(ValueError, match=match):
        call()
