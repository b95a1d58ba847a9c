"""The known-parameters filter (``flowsim.homes.filtered_posterior``, issue 47 item 6): an observer
who knows each object's law and sees it only at some hours."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from flowmaps_jax.flowsim.homes import (
    REGIMES,
    HomesConfig,
    filtered_posterior,
    generate_homes,
    homes_posterior,
    transition_matrix,
)

CONFIG = HomesConfig(regime="mixed", num_hours=48,
                     rooms=("kitchen", "living_room", "bedroom", "bathroom"),
                     objects_per_home=(4, 6))


@pytest.fixture(scope="module")
def homes():
    """Four homes as numpy arrays: one home is then taken without a program per field."""
    return jax.tree.map(np.asarray, generate_homes(jax.random.key(3), CONFIG, 4))


def _objects(homes, max_allowed=18):
    """(home, object) pairs: every valid object with 2 … ``max_allowed`` places."""
    valid, num = np.asarray(homes.object_valid), np.asarray(homes.num_allowed)
    return [(int(e), int(m)) for e, m in np.argwhere(valid & (num >= 2) & (num <= max_allowed))]


def _matrices(home, m):
    """(T − 1, R, R) float64: P_t of object m at every hour (the public transition_matrix)."""
    return np.asarray(_every_hour(home, np.int32(m)), np.float64)


@jax.jit  # one program for every home and object
def _every_hour(home, m):
    hours = jnp.arange(CONFIG.num_hours - 1)
    return jax.vmap(lambda t: transition_matrix(home, m, t, CONFIG))(hours)


def _brute_filter(home, m, observed, tau, tau_q):
    """A NumPy forward filter, float64: uniform over the allowed places at hour 0, p ← p P_t,
    conditioned on every sighting at hours <= τ."""
    mats = _matrices(home, m)
    allowed = np.asarray(home.object_allowed[m])
    where = np.asarray(home.receptacle[:, m])
    p = allowed / allowed.sum()
    for t in range(tau_q + 1):
        if t > 0:
            p = p @ mats[t - 1]
        if t <= tau and observed[t, m]:
            p = np.where(np.arange(p.size) == where[t], p, 0.0)
            p = p / p.sum()
    return p


def test_the_filter_matches_a_numpy_forward_filter_on_a_random_mask(homes):
    rng = np.random.default_rng(0)
    seen_regimes = set()
    for e, m in _objects(homes):
        home = homes.home(e)
        observed = rng.random((CONFIG.num_hours, CONFIG.max_objects)) < 0.6
        for tau, tau_q in ((0, 1), (13, 14), (20, 33), (40, 47)):
            want = _brute_filter(home, m, observed, tau, tau_q)
            got = np.asarray(filtered_posterior(home, m, observed, tau, tau_q, CONFIG))
            np.testing.assert_allclose(got, want, atol=1e-6, err_msg=f"home {e} object {m}")
        seen_regimes.add(int(home.regime[m]))
    assert seen_regimes == set(range(len(REGIMES))), seen_regimes


def test_the_filter_matches_enumeration_of_all_paths(homes):
    """Every path from hour 0 over the allowed places, weighted by the law and kept where it
    agrees with the sightings: independent of the filter's recursion."""
    rng = np.random.default_rng(1)
    for e, m in _objects(homes, max_allowed=3)[:4]:
        home = homes.home(e)
        mats = _matrices(home, m)
        allowed = np.flatnonzero(np.asarray(home.object_allowed[m]))
        where = np.asarray(home.receptacle[:, m])
        observed = rng.random((CONFIG.num_hours, CONFIG.max_objects)) < 0.5
        tau, tau_q = 6, 9  # 3^10 paths at most
        brute = np.zeros(CONFIG.max_receptacles)
        for path in itertools.product(allowed, repeat=tau_q + 1):
            if any(observed[t, m] and path[t] != where[t] for t in range(tau + 1)):
                continue
            brute[path[-1]] += np.prod([mats[t, path[t], path[t + 1]] for t in range(tau_q)])
        brute /= brute.sum()
        got = np.asarray(filtered_posterior(home, m, observed, tau, tau_q, CONFIG))
        np.testing.assert_allclose(got, brute, atol=1e-6)


def test_every_hour_observed_is_the_posterior_with_the_law_known(homes):
    observed = np.ones((CONFIG.num_hours, CONFIG.max_objects), bool)
    for e, m in _objects(homes):
        home = homes.home(e)
        for tau, tau_q in ((0, 5), (17, 30), (46, 47)):
            np.testing.assert_allclose(
                filtered_posterior(home, m, observed, tau, tau_q, CONFIG),
                homes_posterior(home, m, tau, tau_q, CONFIG), atol=1e-6)


def test_the_filter_jits_and_vmaps_over_queries_and_homes(homes):
    e, m = _objects(homes)[0]
    home = homes.home(e)
    observed = np.random.default_rng(2).random((CONFIG.num_hours, CONFIG.max_objects)) < 0.5
    taus, tau_qs = jnp.asarray([0, 10, 30]), jnp.asarray([5, 11, 47])
    batched = jax.jit(jax.vmap(lambda a, b: filtered_posterior(home, m, observed, a, b,
                                                               CONFIG)))(taus, tau_qs)
    for i in range(3):
        np.testing.assert_allclose(batched[i], filtered_posterior(
            home, m, observed, int(taus[i]), int(tau_qs[i]), CONFIG), atol=1e-6)
    over_homes = jax.vmap(lambda h: filtered_posterior(h, 0, observed, 3, 9, CONFIG))(homes)
    assert over_homes.shape == (4, CONFIG.max_receptacles)
    np.testing.assert_allclose(np.asarray(over_homes).sum(-1), 1.0, atol=1e-5)
    bad = jax.jit(lambda a, b: filtered_posterior(home, m, observed, a, b, CONFIG))(
        jnp.int32(9), jnp.int32(9))
    assert np.all(np.isnan(np.asarray(bad)))


@pytest.mark.parametrize(("change", "message"), [
    ({"observed": np.ones((47, 15), bool)}, "observed"),
    ({"observed": np.full((48, 15), 0.5)}, "observed"),
    ({"tau_q": 3}, "tau_q"),
    ({"object_index": 15}, "object_index"),
])
def test_bad_arguments_name_themselves(homes, change, message):
    e, m = _objects(homes)[0]
    args = {"object_index": m, "observed": np.ones((48, 15), bool), "tau": 5, "tau_q": 9,
            **change}
    with pytest.raises(ValueError, match=message):
        filtered_posterior(homes.home(e), args["object_index"], args["observed"],
                           args["tau"], args["tau_q"], CONFIG)
