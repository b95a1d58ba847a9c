"""FlowSim homes' ground truth at the edges of its parameters: a ``preference_mass`` of 0 or 1
(refused: the posterior would take log 0) and the frequent regime's sampler at a small
``frequent_length`` (a uniform of exactly 0 must not send an object to a place of negligible
mass). Tiny homes: 2 to 4 homes, 48 hours."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from flowmaps_jax.flowsim.homes import (
    HomesConfig,
    generate_homes,
    homes_history_posterior,
    schedules,
)
from flowmaps_jax.flowsim.homes.rollout import sample_paths
from flowmaps_jax.flowsim.homes.world import FIELDS


@pytest.mark.parametrize("mass", [0.0, 1.0, 1])
def test_a_preference_mass_of_0_or_1_is_refused(mass):
    with pytest.raises(ValueError, match=r"preference_mass must be in \(0\.0, 1\.0\)"):
        HomesConfig(preference_mass=mass)


def test_the_history_posterior_is_a_distribution_near_the_edge():
    config = HomesConfig(regime="preferences", num_hours=48, preference_mass=0.999)
    home = jax.tree.map(lambda a: a[0], generate_homes(jax.random.key(0), config, 2))
    objects = np.flatnonzero(np.asarray(home.object_valid))
    post = jax.vmap(lambda m: homes_history_posterior(home, m, 40, 44, 24, config))(
        jnp.asarray(objects))
    assert np.all(np.isfinite(post))
    np.testing.assert_allclose(np.asarray(post).sum(-1), 1.0, atol=1e-5)


@functools.partial(jax.jit, static_argnames="config")
def _first_move_rates(homes, config: HomesConfig):
    """(E, M): the law's probability of the place each object goes to from hour 8 when its
    uniform is exactly 0 (a move: m > 0); NaN for objects of fewer than 3 places."""
    def one(home):
        start = home.receptacle[8]
        u = jnp.zeros((1, start.shape[0]), jnp.float32)
        went = sample_paths({f: getattr(home, f) for f in FIELDS}, start, 8, u, config)[0]
        kernel = jax.vmap(lambda reg, cyc, num, allowed: schedules.move_kernel(
            reg, cyc, num, allowed, home.receptacle_distance, config))(
                home.regime, home.cycle, home.num_allowed, home.object_allowed)
        rate = kernel[jnp.arange(start.shape[0]), start, went]
        return jnp.where(home.object_valid & (home.num_allowed >= 3), rate, jnp.nan)
    return jax.vmap(one)(homes)


def _first_moves(config: HomesConfig) -> np.ndarray:
    rates = np.asarray(_first_move_rates(generate_homes(jax.random.key(3), config, 4), config))
    return rates[np.isfinite(rates)]


def test_a_uniform_of_0_follows_the_frequent_law_at_a_small_length():
    # at 0.1 m the first allowed place is often 1e-10 .. 1e-25 likely: u = 0 went there
    rates = _first_moves(HomesConfig(regime="frequent", num_hours=48, frequent_length=0.1))
    assert rates.size >= 8 and rates.min() > 2.0**-18, rates
    # at the default 3 m every row's first place has more than the half cell: unchanged there
    rates = _first_moves(HomesConfig(regime="frequent", num_hours=48))
    assert rates.min() > 2.0**-16
