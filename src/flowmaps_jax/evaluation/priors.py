"""Reference rows as priors: ``prior(homes, queries) -> (E, Q, R)`` float32 (:mod:`.queries`).

Each row's probabilities over the home's R receptacle slots for the queried object at τ_q, with
mass only on the object's allowed receptacles (rows sum to 1). All are pure functions of the
homes and the queries, jitted and vmapped over homes and queries (no Python loop over either):

* :func:`exact_prior` — the exact posterior given the map at τ and the object's last
  ``history`` hours (``flowsim.homes.homes_history_posterior``: the preferences regime's hidden
  favourites marginalised, the window's first state included; for the other regimes the plain
  posterior). The window is min(history, τ + 1) hours. ``history=1`` is "what one map can
  give": where the object stands at τ also weighs the current contexts' favourites.
* :func:`uniform_prior` — 1/n on each of the object's n allowed receptacles.
* :func:`last_seen_prior` — "nothing moves": 1 − ε where the object is at τ, ε spread evenly
  over its other allowed receptacles, so that KL(q ‖ p) is finite. ε = ``LAST_SEEN_EPS`` = 0.01
  by default (the 2-D protocol scores last-seen through a smoothed density and has no discrete ε;
  this one is ours, and a smaller ε only raises last-seen's KL: log(1/ε) per unit of q's mass
  away from where the object was).
* :func:`frequency_prior` — SGM's / HOMER's counting: (count_r + 1) / (H + n) over the allowed
  receptacles, count_r the hours of the window τ − H + 1 … τ (H = min(history, τ + 1)) the
  object stood on r (add-one, Laplace, so nothing allowed has zero mass).
* :func:`oracle_samples_prior` — ``num_samples`` draws from the exact posterior, histogrammed:
  a perfect sampler seen through N samples, the floor of any sampler's TV (the 2-D protocol's
  "oracle samples").

"Nearest first" needs no prior: it is a navigation policy (:mod:`.navigation`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp

from flowmaps_jax.flowsim.homes import HomesConfig, homes_history_posterior
from flowmaps_jax.flowsim.homes.queries import HomesQueries
from flowmaps_jax.flowsim.homes.world import Homes
from flowmaps_jax.validation import check_instance, check_int, check_key, check_real

LAST_SEEN_EPS = 0.01
"""Mass last-seen leaves to the object's other allowed receptacles (KL stays finite)."""
DEFAULT_HISTORY = 168
"""Hours of the object's past the exact and frequency rows read (a week)."""

Prior = Callable[[Homes, HomesQueries], jax.Array]
"""``prior(homes, queries) -> (E, Q, R)`` float32 probabilities over receptacle slots."""


def allowed_slots(homes: Homes, queries: HomesQueries) -> jax.Array:
    """(E, Q, R) bool: the queried object's allowed receptacles."""
    return jnp.take_along_axis(homes.object_allowed, queries.object_index[..., None], axis=1)


def receptacle_at(homes: Homes, hour, object_index) -> jax.Array:
    """(E, Q) int32: where object ``object_index`` (E, Q) stands at ``hour`` (E, Q)."""
    e = jnp.arange(homes.receptacle.shape[0])[:, None]
    return homes.receptacle[e, hour, object_index]


def _per_query(fn):
    """``fn(home, object_index, tau, tau_q) -> (R,)`` over homes (E) and their queries (Q)."""
    over_queries = jax.vmap(fn, in_axes=(None, 0, 0, 0))
    return jax.vmap(over_queries)


@functools.partial(jax.jit, static_argnames=("config", "history"))
def _exact(homes: Homes, queries: HomesQueries, config: HomesConfig, history: int):
    def one(home, i, tau, tau_q):
        return homes_history_posterior(home, i, tau, tau_q, jnp.minimum(history, tau + 1),
                                       config)

    return _per_query(one)(homes, queries.object_index, queries.tau, queries.tau_q)


def exact_prior(config: HomesConfig, history: int = DEFAULT_HISTORY) -> Prior:
    """The exact posterior given the map at τ and the last min(history, τ + 1) hours."""
    check_instance("config", config, HomesConfig)
    history = check_int("history", history, 1, config.num_hours)
    return functools.partial(_exact, config=config, history=history)


@jax.jit
def uniform_prior(homes: Homes, queries: HomesQueries) -> jax.Array:
    """(E, Q, R): uniform over the object's allowed receptacles."""
    allowed = allowed_slots(homes, queries).astype(jnp.float32)
    return allowed / jnp.maximum(allowed.sum(-1, keepdims=True), 1.0)


@functools.partial(jax.jit, static_argnames="eps")
def _last_seen(homes: Homes, queries: HomesQueries, eps: float):
    allowed = allowed_slots(homes, queries)
    now = receptacle_at(homes, queries.tau, queries.object_index)
    here = jax.nn.one_hot(now, allowed.shape[-1], dtype=jnp.float32)
    others = allowed.sum(-1, keepdims=True) - 1
    spread = jnp.where(others > 0, eps / jnp.maximum(others, 1), 0.0)
    stay = jnp.where(others > 0, 1.0 - eps, 1.0)
    return jnp.where(allowed, here * stay + (1.0 - here) * spread, 0.0)


def last_seen_prior(eps: float = LAST_SEEN_EPS) -> Prior:
    """All mass but ε where the object is at τ; ε evenly over its other allowed receptacles."""
    eps = check_real("eps", eps, 0.0, 1.0, high_open=True)
    return functools.partial(_last_seen, eps=eps)


@functools.partial(jax.jit, static_argnames="history")
def _frequency(homes: Homes, queries: HomesQueries, history: int):
    allowed = allowed_slots(homes, queries)
    back = jnp.arange(history)  # hours τ, τ − 1, …, τ − history + 1
    hours = queries.tau[..., None] - back  # (E, Q, H)
    inside = hours >= 0  # the window is min(history, τ + 1) hours
    e = jnp.arange(hours.shape[0])[:, None, None]
    where = homes.receptacle[e, jnp.maximum(hours, 0), queries.object_index[..., None]]
    counts = jnp.sum(jnp.where(inside[..., None],
                               where[..., None] == jnp.arange(allowed.shape[-1]), False),
                     axis=-2).astype(jnp.float32)  # (E, Q, R)
    counts = jnp.where(allowed, counts + 1.0, 0.0)
    return counts / counts.sum(-1, keepdims=True)


def frequency_prior(history: int = DEFAULT_HISTORY) -> Prior:
    """Add-one counts of where the object stood over the window of ``history`` hours up to τ."""
    history = check_int("history", history)
    return functools.partial(_frequency, history=history)


@functools.partial(jax.jit, static_argnames=("num_samples",))
def histogram_draws(key, probs, num_samples: int) -> jax.Array:
    """(..., R): counts / N of ``num_samples`` categorical draws from ``probs`` (..., R)."""
    draws = jax.random.categorical(key, jnp.log(probs)[..., None, :],
                                   shape=(*probs.shape[:-1], num_samples))
    hits = draws[..., None] == jnp.arange(probs.shape[-1])
    return jnp.mean(hits, axis=-2, dtype=jnp.float32)


def oracle_samples_prior(config: HomesConfig, key, num_samples: int = 100,
                         history: int = DEFAULT_HISTORY) -> Prior:
    """``num_samples`` draws from the exact posterior (``exact_prior(config, history)``,
    which checks ``config`` and ``history``), histogrammed; ``key`` fixes the draws."""
    key = check_key(key)
    num_samples = check_int("num_samples", num_samples)
    exact = exact_prior(config, history)

    def prior(homes: Homes, queries: HomesQueries) -> jax.Array:
        return histogram_draws(key, exact(homes, queries), num_samples)

    return prior
