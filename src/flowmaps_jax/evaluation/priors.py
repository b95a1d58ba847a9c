"""The reference priors of every world (docs/flowsim.md "FlowMaps on homes", docs/protocol.md).

2-D maps: slot distributions (..., K + 1), the K slots of the object's kind then "off", each a
checked entry and its jitted kernel that the protocol and the search call on built arrays.
Receptacle worlds: ``prior(homes, queries) -> (E, Q, R)`` float32 over the home's receptacle
slots, mass only on the object's allowed receptacles, jitted and vmapped over homes and queries.
The count rows read ``homes.receptacle`` −1 as "not seen" (:func:`seen_only`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from functools import partial

import jax
import jax.numpy as jnp
from flax import struct

from flowmaps_jax.flowsim.homes import HomesConfig, homes_history_posterior
from flowmaps_jax.flowsim.homes.queries import HomesQueries, allowed_slots, receptacle_at
from flowmaps_jax.flowsim.homes.world import Homes
from flowmaps_jax.tables import histogram
from flowmaps_jax.validation import (
    PROB_ATOL,
    check_array,
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
    """The kernel of :func:`oracle_slots`: q (..., K) float32 with an empty off bin."""
    return jnp.concatenate([q, jnp.zeros_like(q[..., :1])], axis=-1)


@partial(jax.jit, static_argnames="n")
def draw_slot_histogram(key, q, n):
    """The kernel of :func:`sampled_oracle_slots` (no checks; ``q`` float32)."""
    draws = jax.random.categorical(key, jnp.log(q)[..., None, :], shape=(*q.shape[:-1], n))
    return histogram(draws, q.shape[-1])  # (..., K + 1); draws never hit the off bin


def sampled_oracle_slots(key: jax.Array, q: jnp.ndarray, n: int) -> jnp.ndarray:
    """Slot counts / n of n draws from q (..., K) → (..., K + 1): a perfect sampler."""
    q = check_probabilities("q", q, (..., None), atol=PROB_ATOL, min_value=-PROB_ATOL)
    n = check_int("n", n)
    return draw_slot_histogram(key, jnp.asarray(q, jnp.float32), n)


@partial(jax.jit, static_argnames="num_slots")
def one_hot_slots(slot_now, num_slots: int):
    """The kernel of :func:`last_seen_slots` (no checks; ``num_slots`` an int)."""
    return jax.nn.one_hot(slot_now, num_slots + 1)


def last_seen_slots(slot_now: jnp.ndarray, num_slots: int) -> jnp.ndarray:
    """Last-seen predictor: slot_now (...) ints in 0..K − 1 → (..., K + 1), K = num_slots."""
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
    """Uniform over the first ``count`` (...) ints in 1..K real slots → (..., K + 1)."""
    num_slots = check_int("num_slots", num_slots)
    count = check_int_array("count", count, 1, num_slots)
    return uniform_over_slots(jnp.asarray(count), num_slots)


# --------------------------------------------------------------------------- homes: receptacles


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
    """(..., R): counts / N of ``num_samples`` categorical draws from ``probs`` (..., R)."""
    return draw_slot_histogram(key, probs, num_samples)[..., :-1]


def oracle_samples_prior(config: HomesConfig, key, num_samples: int = 100,
                         history: int = DEFAULT_HISTORY) -> Prior:
    """``num_samples`` draws from ``exact_prior(config, history)``, histogrammed."""
    key = check_key(key)
    num_samples = check_int("num_samples", num_samples)
    exact = exact_prior(config, history)

    def prior(homes: Homes, queries: HomesQueries) -> jax.Array:
        return histogram_draws(key, exact(homes, queries), num_samples)

    return prior


# --------------------------------------------------------------------------- count tables

COUNT_ROW, STAY_ROW = "count table (hour of day)", "last seen, fitted stay"
BANDWIDTHS = (0.5, 1.0, 2.0, 4.0, 8.0, 1e3)
"""Hours: the kernel bandwidths :func:`fit_count_table` tries (1e3: no hour-of-day effect)."""
ALPHAS = (0.1, 0.5, 2.0, 8.0, 32.0)
"""Pseudo-counts of the class back-off tried."""
DAY_FACTORS = (1.0, 0.2)
"""Weight of an hour of the other day type (weekday / weekend) tried (1: day type ignored)."""
STAYS = (0.2, 0.35, 0.5, 0.7, 0.8, 0.85, 0.9, 0.93, 0.95, 0.97, 0.98, 0.99, 0.995, 0.999)
"""Hourly stay probabilities s₁ tried."""
CLASS_PSEUDO = 0.5
"""Add-β of the class table (per receptacle class and hour of day)."""
LOG_FLOOR = 1e-9


@struct.dataclass
class CountFit:
    """The count rows' parameters: ``classes`` (Co, 24, Cr) training sightings of each object
    class on each receptacle class by hour of day; ``bandwidth`` b (hours), ``alpha``,
    ``day_factor``, ``stay`` s₁: float32 scalars."""

    classes: jax.Array
    bandwidth: jax.Array
    alpha: jax.Array
    day_factor: jax.Array
    stay: jax.Array

    def summary(self) -> dict:
        """The chosen values (JSON-able)."""
        return {k: float(getattr(self, k)) for k in ("bandwidth", "alpha", "day_factor", "stay")}


def seen_only(homes: Homes, observed) -> Homes:
    """``homes`` with ``receptacle`` −1 where ``observed`` (E, T, M) is False."""
    return homes.replace(receptacle=jnp.where(observed, homes.receptacle, -1))


def _kernel(hours, bandwidth):
    """exp(−d² / 2b²), d the circular distance of ``hours`` on the 24-hour clock."""
    d = jnp.abs(hours) % 24
    return jnp.exp(-0.5 * (jnp.minimum(d, 24 - d) / bandwidth) ** 2)


@functools.partial(jax.jit, static_argnames="shape")
def _class_counts(homes: Homes, shape):
    rec = homes.receptacle  # (E, T, M)
    rc = jnp.take_along_axis(homes.receptacle_class, jnp.maximum(rec, 0).reshape(
        rec.shape[0], -1), 1).reshape(rec.shape)
    oc = jnp.broadcast_to(homes.object_class[:, None, :], rec.shape)
    ok = (rec >= 0) & (oc >= 0) & (rc >= 0)
    hod = (jnp.arange(rec.shape[1]) % 24)[None, :, None]
    index = (jnp.maximum(oc, 0) * 24 + hod) * shape[1] + jnp.maximum(rc, 0)
    flat = jnp.zeros(shape[0] * 24 * shape[1]).at[index.ravel()].add(ok.ravel().astype(float))
    return flat.reshape(shape[0], 24, shape[1])


def _backoff(homes: Homes, queries: HomesQueries, fit: CountFit, allowed):
    """(E, Q, R) over the allowed receptacles: the class back-off at τ_q's hour of day."""
    hours = jnp.arange(24)
    smooth = jnp.einsum("hk,okc->ohc", _kernel(hours[:, None] - hours, fit.bandwidth),
                        fit.classes) + CLASS_PSEUDO
    oc = jnp.maximum(jnp.take_along_axis(homes.object_class, queries.object_index, 1), 0)
    row = smooth[oc, queries.tau_q % 24]  # (E, Q, Cr)
    rc = jnp.broadcast_to(jnp.maximum(homes.receptacle_class, 0)[:, None], allowed.shape)
    same = jnp.sum(allowed[..., None, :] & (rc[..., :, None] == rc[..., None, :]), -1)
    w = jnp.where(allowed, jnp.take_along_axis(row, rc, -1) / jnp.maximum(same, 1), 0.0)
    return w / w.sum(-1, keepdims=True)


@functools.partial(jax.jit, static_argnames="history")
def _count_table(homes: Homes, queries: HomesQueries, fit: CountFit, history: int):
    allowed = allowed_slots(homes, queries)
    hours = queries.tau[..., None] - jnp.arange(history)  # (E, Q, H): τ, τ − 1, …
    e = jnp.arange(hours.shape[0])[:, None, None]
    where = homes.receptacle[e, jnp.maximum(hours, 0), queries.object_index[..., None]]
    weekend = (hours // 24) % 7 >= 5
    w = _kernel(hours - queries.tau_q[..., None], fit.bandwidth) * jnp.where(
        weekend == ((queries.tau_q // 24) % 7 >= 5)[..., None], 1.0, fit.day_factor)
    w = jnp.where((hours >= 0) & (where >= 0), w, 0.0)
    counts = jnp.einsum("eqh,eqhr->eqr", w, jax.nn.one_hot(where, allowed.shape[-1]))
    p = jnp.where(allowed, counts + fit.alpha * _backoff(homes, queries, fit, allowed), 0.0)
    return p / p.sum(-1, keepdims=True)


@functools.partial(jax.jit, static_argnames="history")
def _stay(homes: Homes, queries: HomesQueries, fit: CountFit, history: int):
    table = _count_table(homes, queries, fit, history)
    rec = jnp.take_along_axis(homes.receptacle, queries.object_index[:, None, :], 2)  # (E,T,Q)
    t = jnp.arange(rec.shape[1])[None, :, None]
    last = jnp.max(jnp.where((rec >= 0) & (t <= queries.tau[:, None]), t, -1), 1)  # (E, Q)
    place = jnp.take_along_axis(rec, jnp.maximum(last, 0)[:, None], 1)[:, 0]
    s = jnp.where(last >= 0, fit.stay ** (queries.tau_q - last), 0.0)[..., None]
    return s * jax.nn.one_hot(place, table.shape[-1]) + (1.0 - s) * table


def count_table_prior(fit: CountFit, history: int = DEFAULT_HISTORY) -> Prior:
    """Per object × hour-of-day kernel counts over the ``history`` hours up to τ, plus α × the
    class back-off."""
    check_instance("fit", fit, CountFit)
    return functools.partial(_count_table, fit=fit, history=check_int("history", history))


def stay_prior(fit: CountFit, history: int = DEFAULT_HISTORY) -> Prior:
    """Last seen with the fitted stay probability, the rest by the count table."""
    check_instance("fit", fit, CountFit)
    return functools.partial(_stay, fit=fit, history=check_int("history", history))


def fit_count_table(homes: Homes, queries: HomesQueries, target, valid, num_classes: tuple,
                    history: int = DEFAULT_HISTORY) -> CountFit:
    """The :class:`CountFit` maximising the mean log score of the realised ``target`` (E, Q)
    where ``valid`` (E, Q) over a training part's ``homes`` (−1 where not seen) and ``queries``
    (E, Q); ``num_classes`` (Co, Cr)."""
    shape = tuple(check_int("num_classes", n) for n in num_classes)
    if len(shape) != 2:
        raise ValueError(f"num_classes must be (object classes, receptacle classes); got {shape}")
    target = jnp.asarray(check_array("target", target, queries.tau.shape))[..., None]
    valid = jnp.asarray(check_array("valid", valid, queries.tau.shape), bool)
    history = check_int("history", history)
    classes = _class_counts(homes, shape)

    def score(kernel, values):
        fit = CountFit(classes, *(jnp.float32(v) for v in values))
        p = jnp.take_along_axis(kernel(homes, queries, fit, history), target, -1)[..., 0]
        return float(jnp.sum(jnp.where(valid, jnp.log(jnp.maximum(p, LOG_FLOOR)), 0.0)))

    best = max(((b, a, d, 0.0) for b in BANDWIDTHS for a in ALPHAS for d in DAY_FACTORS),
               key=lambda v: score(_count_table, v))
    stay = max(STAYS, key=lambda s: score(_stay, (*best[:3], s)))
    return CountFit(classes, *(jnp.float32(v) for v in (*best[:3], stay)))
