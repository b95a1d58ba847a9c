"""Flow maths: path, t-samplers, CFM loss, ODE solvers (accuracy, evaluation count) and the exact
log-likelihood (closed-form affine flow, sample moments, importance weights, exact divergence)."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support import TINY, perturb, synthetic_queries, synthetic_tokens

from flowmaps_jax.flow import (
    divergence,
    integrate,
    linear_path,
    log_prob,
    sample_t,
    sample_with_log_prob,
    standard_normal_log_prob,
    target_velocity,
)
from flowmaps_jax.model import encode, init_params, make_velocity_fn
from flowmaps_jax.model.flowmaps_family import cfm_loss
from flowmaps_jax.tokens import TrainBatch

# An affine field v(x, t) = A x + b with non-diagonal A: x1 = e^A x0 + A⁻¹(e^A − I) b is Gaussian.
A = jnp.array([[-0.5, 0.3, 0.0, 0.1], [0.2, 0.4, -0.3, 0.0],
               [0.0, 0.1, -0.2, 0.2], [0.1, 0.0, 0.3, 0.1]])
BIAS = jnp.array([0.5, -1.0, 0.3, 0.2])
EXP_A = jax.scipy.linalg.expm(A)
MEAN1 = jnp.linalg.solve(A, (EXP_A - jnp.eye(4)) @ BIAS)
COV1 = EXP_A @ EXP_A.T


def affine_field(x, t):
    return x @ A.T + BIAS


def nonlinear_field(x, t):
    """A row-wise nonlinear field (rows independent), smooth in x and t."""
    return jnp.tanh(x @ A.T + BIAS * t) + 0.5 * jnp.sin(x[..., ::-1]) * (1.0 - t)


def test_linear_path_and_target():
    x0, x1 = jnp.zeros((2, 4)), jnp.ones((2, 4))
    np.testing.assert_allclose(linear_path(x0, x1, jnp.array([0.0, 1.0])), [[0] * 4, [1] * 4])
    np.testing.assert_allclose(linear_path(x0, x1, jnp.array([0.25, 0.5]))[:, 0], [0.25, 0.5])
    np.testing.assert_allclose(target_velocity(x0, x1), 1.0)


@pytest.mark.parametrize(("kind", "mean"), [("uniform", 0.5), ("beta", 0.999 * 0.4),
                                            ("logit_normal", 0.5)])
def test_sample_t_ranges_and_means(kind, mean):
    t = sample_t(jax.random.key(0), (20000,), kind)
    assert t.shape == (20000,) and float(t.min()) >= 0.0 and float(t.max()) <= 1.0
    assert abs(float(t.mean()) - mean) < 0.01
    if kind == "beta":  # u ~ Beta(1.5, 1) has P(u < 0.5) = 0.5^1.5, so P(t > 0.4995) = 0.354
        assert abs(float((t > 0.4995).mean()) - 0.5 ** 1.5) < 0.015


def test_sample_t_rejects_unknown_kind():
    with pytest.raises(ValueError, match="t_sampler"):
        sample_t(jax.random.key(0), (3,), "cosine")


def test_integrate_default_grid_uses_18_evaluations():
    calls = []

    def counting_field(x, t):
        jax.debug.callback(lambda tt: calls.append(float(tt)), t)
        return jnp.ones_like(x)

    out = integrate(counting_field, jnp.zeros((3, 4)))
    jax.block_until_ready(out)
    assert len(calls) == 18  # 10 grid points → 9 intervals × 2 (midpoint)
    np.testing.assert_allclose(out, 1.0, rtol=1e-6)
    calls.clear()
    jax.block_until_ready(integrate(counting_field, jnp.zeros((3, 4)), method="euler"))
    assert len(calls) == 9


@pytest.mark.parametrize(("method", "order"), [("midpoint", 2), ("euler", 1)])
def test_solver_accuracy_and_convergence_order(method, order):
    """dx/dt = cos(t)·x has x(1) = x0·exp(sin 1); halving the step divides the error by 2^order."""
    x0 = jnp.array([[1.0, -2.0, 0.5, 3.0]])
    exact = x0 * math.exp(math.sin(1.0))
    field = lambda x, t: jnp.cos(t) * x  # noqa: E731
    errors = [float(jnp.abs(integrate(field, x0, n, method) - exact).max()) for n in (11, 21, 41)]
    ratios = [errors[0] / errors[1], errors[1] / errors[2]]
    assert all(abs(math.log2(r) - order) < 0.2 for r in ratios), (errors, ratios)
    assert errors[-1] < (1e-3 if method == "midpoint" else 5e-2)


def test_solver_rejects_bad_arguments():
    with pytest.raises(ValueError, match="num_steps"):
        integrate(affine_field, jnp.zeros((1, 4)), num_steps=1)
    with pytest.raises(ValueError, match="method"):
        integrate(affine_field, jnp.zeros((1, 4)), method="rk4")
    with pytest.raises(ValueError, match="num_steps"):
        log_prob(affine_field, jnp.zeros((1, 4)), num_steps=2.5)


def test_divergence_is_exact_trace():
    @jax.jit  # one program, not one per operation
    def parts(x):
        v, div = divergence(nonlinear_field, x, jnp.float32(0.3))
        jac = jax.vmap(jax.jacfwd(lambda row: nonlinear_field(row, 0.3)))(x.reshape(-1, 4))
        _, div_affine = divergence(affine_field, x, jnp.float32(0.0))
        return v, nonlinear_field(x, 0.3), div, jnp.trace(jac, axis1=1, axis2=2), div_affine

    v, field, div, trace, div_affine = parts(jax.random.normal(jax.random.key(1), (2, 3, 4)))
    np.testing.assert_allclose(v, field, rtol=1e-6)
    np.testing.assert_allclose(div.reshape(-1), trace, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(div_affine, np.trace(A), rtol=1e-6)


def test_log_prob_of_affine_flow_matches_closed_form_gaussian():
    x1 = MEAN1 + jax.random.normal(jax.random.key(2), (64, 4)) * 1.5
    exact = jax.scipy.stats.multivariate_normal.logpdf(x1, MEAN1, COV1)
    fine = jax.jit(lambda x: log_prob(affine_field, x, num_steps=41))(x1)
    np.testing.assert_allclose(fine, exact, atol=2e-3)
    coarse = log_prob(affine_field, x1)  # default 10-point midpoint grid: close, not exact
    assert float(jnp.abs(coarse - exact).max()) < 0.05


def test_forward_log_prob_gives_the_samples_and_their_density_in_one_solve():
    """sample_with_log_prob: the same samples as integrate, and a density that matches the
    closed form (affine flow) and the backward solve of log_prob as the grid is refined."""
    x0 = jax.random.normal(jax.random.key(11), (64, 4))
    x1, log_p = jax.jit(lambda x: sample_with_log_prob(nonlinear_field, x, num_steps=41))(x0)
    np.testing.assert_allclose(x1, jax.jit(lambda x: integrate(nonlinear_field, x, num_steps=41))(
        x0), atol=1e-5)
    backward = jax.jit(lambda x: log_prob(nonlinear_field, x, num_steps=41))(x1)
    np.testing.assert_allclose(log_p, backward, atol=5e-3)
    y1, log_q = sample_with_log_prob(affine_field, x0, num_steps=41)
    exact = jax.scipy.stats.multivariate_normal.logpdf(y1, MEAN1, COV1)
    np.testing.assert_allclose(log_q, exact, atol=2e-3)
    with pytest.raises(ValueError, match="method"):
        sample_with_log_prob(affine_field, x0, method="rk4")


def test_samples_of_affine_flow_have_the_density_moments():
    x0 = jax.random.normal(jax.random.key(3), (20000, 4))
    x1 = integrate(affine_field, x0, num_steps=41)
    np.testing.assert_allclose(x1.mean(0), MEAN1, atol=0.05)
    np.testing.assert_allclose(jnp.cov(x1.T), COV1, atol=0.08)


def test_log_prob_of_nonlinear_flow_is_a_normalised_density():
    """Importance weights q(x)/p(x) with x ~ p (samples of the flow) average to 1 for any density q.

    A wrong log p (a missing or mis-signed divergence) breaks this by far more than MC error.
    """
    x0 = jax.random.normal(jax.random.key(4), (20000, 4))
    x1 = jax.jit(lambda x: integrate(nonlinear_field, x, num_steps=41))(x0)
    log_p = jax.jit(lambda x: log_prob(nonlinear_field, x, num_steps=41))(x1)
    mean, cov = x1.mean(0), jnp.cov(x1.T) * 1.5
    log_q = jax.scipy.stats.multivariate_normal.logpdf(x1, mean, cov)
    weights = jnp.exp(log_q - log_p)
    assert abs(float(weights.mean()) - 1.0) < 0.03, float(weights.mean())
    # and along each trajectory log p(x1) = log N(x0) − ∫ div: consistent with the forward solve
    assert float(jnp.abs(log_p - standard_normal_log_prob(x0)).mean()) > 0.1


@pytest.fixture(scope="module")
def tiny():
    """TINY, a batch of 2 scenes (5 and 12 real tokens) × 2 queries, fresh and perturbed params."""
    tokens = synthetic_tokens(5, (5, 12), tau=(1, 7))
    target = jax.random.uniform(jax.random.key(6), (2, 2, 4))
    batch = TrainBatch(tokens=tokens, queries=synthetic_queries(tokens, 2), target=target)
    params = init_params(jax.random.key(7), TINY)
    return TINY, batch, params, perturb(params, jax.random.key(8), 0.2)


def test_cfm_loss_at_zero_velocity_is_target_energy(tiny):
    cfg, batch, params, _ = tiny
    key = jax.random.key(9)
    loss, aux = cfm_loss(params, cfg, batch, key, "uniform", deterministic=True)
    assert aux["mse_per_query"].shape == (2, 2)
    # the zero-initialised model predicts v = 0, so the loss is mean((X1 − X0)²) for the same X0
    x0 = jax.random.normal(jax.random.split(key, 4)[0], batch.target.shape)
    np.testing.assert_allclose(loss, jnp.mean(jnp.square(batch.target - x0)), rtol=1e-5)
    with pytest.raises(ValueError, match="t_sampler"):
        cfm_loss(params, cfg, batch, key, "gaussian")


def test_cfm_loss_regresses_the_target_in_the_flow_space(tiny):
    """With box_offset/box_scale the data end of the path is box_scale · (box − box_offset)."""
    cfg, batch, params, _ = tiny
    scaled = dataclasses.replace(cfg, box_offset=0.5, box_scale=4.0)
    key = jax.random.key(9)
    loss, _ = cfm_loss(params, scaled, batch, key, "uniform", deterministic=True)
    x0 = jax.random.normal(jax.random.split(key, 4)[0], batch.target.shape)
    np.testing.assert_allclose(loss, jnp.mean(jnp.square(4.0 * (batch.target - 0.5) - x0)),
                               rtol=1e-5)


def test_model_divergence_is_exact_and_log_prob_runs(tiny):
    """The model's query rows are independent, so the shared-basis JVP trace is the exact one."""
    cfg, batch, _, active = tiny
    context = encode(active, cfg, batch.tokens)
    field = make_velocity_fn(active, cfg, context, batch.queries)
    x = jax.random.normal(jax.random.key(10), (2, 2, 3, 4))
    _, div = divergence(field, x, jnp.float32(0.4))

    def row_field(row, b, q):  # one row alone through the model
        full = jnp.zeros_like(x).at[b, q, 0].set(row)
        return field(full, jnp.float32(0.4))[b, q, 0]

    for b, q, n in [(0, 0, 0), (1, 1, 2), (0, 1, 1)]:
        jac = jax.jacfwd(row_field)(x[b, q, n], b, q)
        np.testing.assert_allclose(div[b, q, n], jnp.trace(jac), rtol=1e-4, atol=1e-5)
    lp = jax.jit(lambda x: log_prob(field, x))(x)
    assert lp.shape == (2, 2, 3) and bool(jnp.all(jnp.isfinite(lp)))
    samples = jax.jit(lambda x: integrate(field, x))(x)
    assert samples.shape == x.shape
