"""The reference priors of every world, one module: what a model is compared with.

**2-D maps** (slot distributions (..., K + 1): the K slots of the object's kind, then "off";
:mod:`.slots` scores them): :func:`oracle_slots` (q itself), :func:`sampled_oracle_slots` (n
draws from q, histogrammed: the floor of any sampler), :func:`last_seen_slots` (the object
stays), :func:`uniform_slots` (1/n on the real slots); each validates once and runs its jitted
kernel (:func:`with_off_bin`, :func:`draw_slot_histogram`, :func:`one_hot_slots`,
:func:`uniform_over_slots`), which the protocol and the search call on arrays they built. The
exact posterior itself comes from the simulator (``flowsim.dynamics``, ``flowsim.habits``).

**Receptacle worlds (FlowSim homes)**: priors ``prior(homes, queries) -> (E, Q, R)`` float32
(:mod:`flowmaps_jax.flowsim.homes.queries`). Each row's probabilities over the home's R
receptacle slots for the queried object at τ_q, with mass only on the object's allowed
receptacles (rows sum to 1). All are pure functions of the homes and the queries, jitted and
vmapped over homes and queries (no Python loop over either):

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

"Nearest first" needs no prior: it is a navigation policy (:mod:`flowmaps_jax.search.navigation`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from functools import partial

import jax
import jax.numpy as jnp

from flowmaps_jax.flowsim.homes import HomesConfig, homes_history_posterior
from flowmaps_jax.flowsim.homes.queries import HomesQueries
from flowmaps_jax.flowsim.homes.world import Homes
from flowmaps_jax.tables import histogram
from flowmaps_jax.validation import (
    PROB_ATOL,
    check_instance,
    check_int,
    check_int_array,
    check_key,
    check_probabilities,
    check_real,
)

LAST_SEEN_EPS = 0.01
"""Mass last-seen leaves to the object's other allowed receptacles (KL stays finite)."""
DEFAULT_HISTORY = 168
"""Hours of the object's past the exact and frequency rows read (a week)."""

Prior = Callable[[Homes, HomesQueries], jax.Array]
"""``prior(homes, queries) -> (E, Q, R)`` float32 probabilities over receptacle slots."""


# --------------------------------------------------------------------------- 2-D maps: slots


def oracle_slots(q: jnp.ndarray) -> jnp.ndarray:
    """The oracle predictor: q itself. (..., K) → (..., K + 1) with an empty off bin."""
    q = check_probabilities("q", q, (..., None), atol=PROB_ATOL, min_value=-PROB_ATOL)
    return with_off_bin(jnp.asarray(q, jnp.float32))


@jax.jit
def with_off_bin(q):
    """The kernel of :func:`oracle_slots` (no checks): q (..., K) float32 with an empty off
    bin."""
    return jnp.concatenate([q, jnp.zeros_like(q[..., :1])], axis=-1)


@partial(jax.jit, static_argnames="n")
def draw_slot_histogram(key, q, n):
    """The kernel of :func:`sampled_oracle_slots` (no checks; ``q`` float32)."""
    draws = jax.random.categorical(key, jnp.log(q)[..., None, :], shape=(*q.shape[:-1], n))
    return histogram(draws, q.shape[-1])  # (..., K + 1); draws never hit the off bin


def sampled_oracle_slots(key: jax.Array, q: jnp.ndarray, n: int) -> jnp.ndarray:
    """A perfect sampler seen through n samples: slot counts / n of n draws from q itself.

    (..., K) → (..., K + 1) (off bin empty). Its slot scores are the best any sampler can expect
    from n samples: the gap to the exact oracle is pure finite-sample noise.
    """
    q = check_probabilities("q", q, (..., None), atol=PROB_ATOL, min_value=-PROB_ATOL)
    n = check_int("n", n)
    return draw_slot_histogram(key, jnp.asarray(q, jnp.float32), n)


@partial(jax.jit, static_argnames="num_slots")
def one_hot_slots(slot_now, num_slots: int):
    """The kernel of :func:`last_seen_slots` (no checks; ``num_slots`` an int)."""
    return jax.nn.one_hot(slot_now, num_slots + 1)


def last_seen_slots(slot_now: jnp.ndarray, num_slots: int) -> jnp.ndarray:
    """Last-seen predictor: the object stays where it is. slot_now (...) ints → (..., K + 1).

    num_slots: K, the padded slot count. slot_now indexes the same slot axis as q.
    """
    num_slots = check_int("num_slots", num_slots)
    slot_now = check_int_array("slot_now", slot_now, 0, num_slots - 1)
    return one_hot_slots(jnp.asarray(slot_now), num_slots)


@partial(jax.jit, static_argnames="num_slots")
def uniform_over_slots(count, num_slots: int):
    """The kernel of :func:`uniform_slots` (no checks; ``num_slots`` an int)."""
    real = jnp.arange(num_slots) < count[..., None]
    probs = jnp.where(real, 1.0 / count[..., None], 0.0)
    return jnp.concatenate([probs, jnp.zeros_like(probs[..., :1])], axis=-1)


def uniform_slots(count: jnp.ndarray, num_slots: int) -> jnp.ndarray:
    """Uniform predictor over the real slots. count (...) ints in 1..K → (..., K + 1).

    Real slots are the first ``count`` of the K padded ones (as in ``Scenes.visit_order``).
    """
    num_slots = check_int("num_slots", num_slots)
    count = check_int_array("count", count, 1, num_slots)
    return uniform_over_slots(jnp.asarray(count), num_slots)


# --------------------------------------------------------------------------- homes: receptacles


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


def histogram_draws(key, probs, num_samples: int) -> jax.Array:
    """(..., R): counts / N of ``num_samples`` categorical draws from ``probs`` (..., R): the
    2-D oracle samples' kernel (:func:`draw_slot_histogram`) without its empty off bin."""
    return draw_slot_histogram(key, probs, num_samples)[..., :-1]


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
