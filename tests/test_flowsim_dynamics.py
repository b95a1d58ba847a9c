"""FlowSim dynamics: transition frequencies (chi-square), exact posterior against rollouts and
against the matrix power, the schedule_jitter variant, input validation."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from flowmaps_jax.flowsim import FlowSimConfig, dynamics, exact_posterior, layout, transition_matrix
from flowmaps_jax.flowsim.config import sim_params, sim_shape

NUM_ROLLOUTS = 20_000
SLOTS = np.array([3, 4, 5])  # K of the three objects in every rollout environment
CHI2_CRITICAL_2DOF_P001 = 13.816  # chi-square quantile, 2 degrees of freedom, alpha = 0.001


@functools.partial(jax.jit, static_argnames=("shape", "num_envs"))
def _rollouts(key, params, shape, num_envs):
    words = layout.random_words(jax.random.split(key, num_envs),
                                dynamics.rollout_num_words(shape))
    num_slots = jnp.broadcast_to(jnp.asarray(SLOTS, jnp.int32)[:, None], (3, num_envs))
    return jnp.transpose(dynamics.rollout(words, num_slots, params, shape), (2, 0, 1))


def rollouts(config: FlowSimConfig, seed: int = 0) -> np.ndarray:
    """(NUM_ROLLOUTS, T, 3) slots simulated by the generator's own rollout code."""
    return np.asarray(_rollouts(jax.random.key(seed), sim_params(config), sim_shape(config),
                                NUM_ROLLOUTS))


@pytest.fixture(scope="module")
def markov_slots():
    return rollouts(FlowSimConfig())


@pytest.fixture(scope="module")
def jitter_slots():
    return rollouts(FlowSimConfig(dynamics="schedule_jitter"), seed=1)


def empirical(slots: np.ndarray, f: int = 10) -> np.ndarray:
    """(..., F) slot frequencies over the first axis."""
    return (slots[..., None] == np.arange(f)).mean(axis=0)


def chi_square(counts: np.ndarray, probs) -> float:
    expected = counts.sum() * np.asarray(probs)
    return float(np.sum((counts - expected) ** 2 / expected))


def test_transition_frequencies_chi_square(markov_slots):
    steps = np.mod(np.diff(markov_slots, axis=1), SLOTS)  # K >= 3: the step is identifiable
    assert set(np.unique(steps)) <= {0, 1, 2}
    counts = np.bincount(steps.ravel(), minlength=3)
    assert counts.sum() >= 100_000
    assert chi_square(counts, (0.2, 0.7, 0.1)) < CHI2_CRITICAL_2DOF_P001
    # The test has power: slightly wrong probabilities are rejected.
    assert chi_square(counts, (0.22, 0.68, 0.1)) > CHI2_CRITICAL_2DOF_P001


def test_generated_slots_move_by_allowed_steps(small_scenes):
    slot = np.asarray(small_scenes.slot)
    k = np.asarray(small_scenes.num_slots)[:, None, :]
    steps = np.mod(np.diff(slot, axis=1), k)
    assert np.isin(steps, [0, 1, 2]).all()
    assert (slot[:, 0] == 0).all()


def _assert_close(emp, exact, n):
    bound = 5 * np.sqrt(exact * (1 - exact) / n) + 2e-3
    assert np.all(np.abs(emp - exact) <= bound), np.max(np.abs(emp - exact) - bound)


def test_exact_posterior_matches_rollouts_every_horizon(markov_slots):
    horizons = np.arange(1, 20)
    exact = np.asarray(exact_posterior(SLOTS[None, :], 0, horizons[:, None]))  # (19, 3, F)
    emp = empirical(markov_slots[:, 1:])  # (19, 3, F)
    _assert_close(emp, exact, NUM_ROLLOUTS)
    np.testing.assert_allclose(exact.sum(-1), 1.0, atol=1e-5)
    assert np.all(exact[:, np.arange(10)[None, :] >= SLOTS[:, None]] == 0)


def test_exact_posterior_from_a_later_state(markov_slots):
    """Conditioning on the slot at tau = 5: the average exact posterior equals the empirical
    distribution at tau + h (this exercises the shift by slot_now)."""
    tau = 5
    for h in (1, 4, 14):
        exact = np.asarray(exact_posterior(SLOTS, markov_slots[:, tau], h)).mean(axis=0)
        _assert_close(empirical(markov_slots[:, tau + h]), exact, NUM_ROLLOUTS)


def test_exact_posterior_equals_matrix_power():
    config = FlowSimConfig()
    k = np.arange(1, 11)[:, None, None]  # every K = 1..10
    now = np.mod(np.arange(10)[None, :, None], k)  # slots 0..K-1 (repeated)
    horizon = np.arange(20)[None, None, :]
    exact = np.asarray(exact_posterior(k, now, horizon, config))  # (10, 10, 20, F)
    matrices = np.asarray(transition_matrix(np.arange(1, 11), config), np.float64)
    for i, matrix in enumerate(matrices):
        size = i + 1
        assert np.all(matrix[size:] == 0) and np.all(matrix[:, size:] == 0)
        np.testing.assert_allclose(matrix[:size].sum(axis=1), 1.0, atol=1e-6)
        for h in range(20):
            power = np.linalg.matrix_power(matrix, h)
            np.testing.assert_allclose(exact[i, :, h], power[now[i, :, 0]], atol=1e-5)


def test_exact_posterior_known_values():
    p = np.asarray(exact_posterior(4, 1, 2))
    # Two steps from slot 1 of 4: advances 0..4 with (0.04, 0.28, 0.53, 0.14, 0.01).
    # Landing on slots 1, 2, 3, 0, 1 -> P = (0.14, 0.04 + 0.01, 0.28, 0.53) for slots 0..3.
    np.testing.assert_allclose(p[:4], [0.14, 0.05, 0.28, 0.53], atol=1e-6)
    assert np.all(p[4:] == 0)


def test_schedule_jitter_posterior_matches_rollouts(jitter_slots):
    config = FlowSimConfig(dynamics="schedule_jitter")
    slots = jitter_slots
    assert (slots[:, 0] == 0).all()
    for tau in (0, 3, 10):
        for h in (1, 2, 9 - (tau == 10)):
            exact = np.asarray(exact_posterior(SLOTS, slots[:, tau], h, config, tau=tau))
            _assert_close(empirical(slots[:, tau + h]), exact.mean(axis=0), NUM_ROLLOUTS)
    # Known value: K = 4, tau_q = 6 -> slots (6 + {-1, 0, 1}) mod 4 = 1, 2, 3.
    np.testing.assert_allclose(np.asarray(exact_posterior(4, 3, 4, config, tau=2))[:4],
                               [0.0, 0.1, 0.7, 0.2], atol=1e-6)
    # The dynamics argument overrides the config's default.
    np.testing.assert_allclose(
        exact_posterior(4, 3, 4, FlowSimConfig(), dynamics="schedule_jitter", tau=2),
        exact_posterior(4, 3, 4, config, tau=2))


def test_exact_posterior_is_jittable_and_vmappable():
    fn = jax.jit(lambda k, s, h: exact_posterior(k, s, h))
    batched = jax.vmap(fn)(jnp.array([3, 5]), jnp.array([2, 4]), jnp.array([1, 7]))
    np.testing.assert_allclose(batched, exact_posterior(np.array([3, 5]), np.array([2, 4]),
                                                        np.array([1, 7])), atol=1e-6)


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"num_slots": 0, "slot_now": 0, "horizon": 1}, "num_slots"),
    ({"num_slots": 11, "slot_now": 0, "horizon": 1}, "num_slots"),
    ({"num_slots": 3, "slot_now": 3, "horizon": 1}, "slot_now"),
    ({"num_slots": 3, "slot_now": 0, "horizon": 20}, "horizon"),
    ({"num_slots": 3, "slot_now": 0, "horizon": -1}, "horizon"),
    ({"num_slots": 3.0, "slot_now": 0, "horizon": 1}, "num_slots"),
    ({"num_slots": 3, "slot_now": 0, "horizon": 1, "dynamics": "levy"}, "dynamics"),
    ({"num_slots": 3, "slot_now": 0, "horizon": 1, "dynamics": "schedule_jitter"}, "tau"),
    ({"num_slots": 3, "slot_now": 0, "horizon": 5, "dynamics": "schedule_jitter", "tau": 15},
     "tau"),
    ({"num_slots": 3, "slot_now": 0, "horizon": 1, "config": "paper"}, "config"),
])
def test_exact_posterior_bad_inputs(kwargs, match):
    with pytest.raises(ValueError, match=match):
        exact_posterior(**kwargs)


def test_transition_matrix_bad_inputs():
    with pytest.raises(ValueError, match="num_slots"):
        transition_matrix(0)
    with pytest.raises(ValueError, match="config"):
        transition_matrix(3, config=None)
