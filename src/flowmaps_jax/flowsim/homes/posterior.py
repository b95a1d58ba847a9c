"""Exact posteriors of an object's receptacle at a later hour (docs/flowsim.md, "Homes"):
``homes_posterior`` (a forward pass of P_t from where it is at τ), ``homes_history_posterior``
(the preferences regime's favourites hidden, given the last ``history`` hours) and
``filtered_posterior`` (seen only at the ``observed`` hours). ``home`` is one home
(``Homes.home(i)``); every function is jittable and vmappable. Concrete inputs are checked
(``ValueError`` naming the argument); a traced query out of range gives NaNs.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from flowmaps_jax.flowsim.homes import schedules
from flowmaps_jax.flowsim.homes.config import DEFAULT_HOMES_CONFIG, HomesConfig, context_of
from flowmaps_jax.flowsim.homes.schedules import PREFERENCES
from flowmaps_jax.flowsim.homes.world import Homes, validate_homes
from flowmaps_jax.validation import check_instance, check_int_array, check_mask, is_concrete


def object_law(home: Homes, object_index, config: HomesConfig) -> dict:
    """One object's law: move (24,), kernel (R, R), targets (C, R), regime (), allowed (R,),
    context (168,) (``schedules.week_contexts``)."""
    allowed = home.object_allowed[object_index]
    regime = home.regime[object_index]
    num = home.num_allowed[object_index]
    kernel = schedules.move_kernel(regime, home.cycle[object_index], num, allowed,
                                   home.receptacle_distance, config)
    return {"move": schedules.move_probabilities(regime, config), "kernel": kernel,
            "targets": schedules.preference_targets(home.favourite[object_index], allowed, num,
                                                    config.preference_mass),
            "regime": regime, "allowed": allowed, "context": schedules.week_contexts(config)}


def _forward(law: dict, p, tau, tau_q):
    return jax.lax.fori_loop(tau, tau_q, lambda t, q: schedules.step_distribution(law, q, t), p)


def _object_ok(home: Homes, object_index):
    """Whether ``object_index`` is an in-range, unmasked object slot of ``home``."""
    m = home.object_valid.shape[0]
    inside = (object_index >= 0) & (object_index < m)
    return inside & home.object_valid[jnp.clip(object_index, 0, m - 1)]


def _valid(home: Homes, object_index, tau, tau_q):
    t = home.receptacle.shape[0]
    return _object_ok(home, object_index) & (tau >= 0) & (tau_q > tau) & (tau_q < t)


@functools.partial(jax.jit, static_argnames=("config",))
def _posterior(home: Homes, object_index, tau, tau_q, config: HomesConfig):
    law = object_law(home, object_index, config)
    r = law["allowed"].shape[0]
    start = jax.nn.one_hot(home.receptacle[tau, object_index], r, dtype=jnp.float32)
    p = _forward(law, start, tau, tau_q)
    return jnp.where(_valid(home, object_index, tau, tau_q), p, jnp.nan)


def favourite_weights(home: Homes, object_index, tau, history, config: HomesConfig):
    """(C, R) float32: the exact posterior marginal of each context's favourite of a preferences
    object given its receptacles at hours τ − history + 1 … τ (uniform where uninformed)."""
    law = object_law(home, object_index, config)
    allowed, num = law["allowed"], home.num_allowed[object_index]
    s = home.receptacle[:, object_index]
    hours = jnp.arange(s.shape[0])
    t = hours[:-1]
    here, there = s[:-1], s[1:]
    m = law["move"][t % 24][:, None]  # (T − 1, 1)
    r, c = allowed.shape[0], law["targets"].shape[0]
    f = jnp.arange(r)
    mass = jnp.where(num > 1, config.preference_mass, 1.0)
    rest = jnp.where(num > 1, (1.0 - config.preference_mass) / jnp.maximum(num - 1, 1), 0.0)
    pi = jnp.where(there[:, None] == f[None, :], mass, rest)  # π(s_{t+1}; f) (T − 1, R)
    lik = (1.0 - m) * (here == there)[:, None] + m * pi
    first = tau - history + 1  # a
    window = (t >= first) & (t < tau)
    loglik = jnp.where(window[:, None], jnp.log(lik), 0.0)
    per_context = jax.nn.one_hot(context_of(t, config.day_phases), c, dtype=jnp.float32)
    total = per_context.T @ loglik  # (C, R)
    ell = jax.nn.softmax(jnp.where(allowed[None, :], total, -jnp.inf), axis=-1)  # ℓ_c
    # p(s_a | f) = α / n + Σ_c W_c π_c(s_a): the uniform start pushed through hours 0 … a − 1
    move = law["move"][hours % 24]
    before = hours < first
    keep = jnp.where(before, 1.0 - move, 1.0)
    from_here = jnp.cumprod(keep[::-1])[::-1]  # Π_{u ≥ t, u < a} (1 − m_u)
    later = jnp.concatenate([from_here[1:], jnp.ones((1,), from_here.dtype)])
    alpha = from_here[0]
    w_hour = jnp.where(before, move * later, 0.0)  # m_t Π_{t < u < a} (1 − m_u)
    in_context = jax.nn.one_hot(context_of(hours, config.day_phases), c, dtype=jnp.float32)
    w_ctx = in_context.T @ w_hour  # W_c (C,)
    s_a = s[jnp.clip(first, 0, s.shape[0] - 1)]
    ell_a = ell[:, s_a]  # ℓ_c(s_a) (C,)
    z = alpha / jnp.maximum(num, 1) + jnp.sum(w_ctx * (rest + (mass - rest) * ell_a))
    shift = (mass - rest) * ((f == s_a)[None, :] - ell_a[:, None])  # π_k(s_a) − E_c[π_c(s_a)]
    return ell * (1.0 + w_ctx[:, None] * shift / z)


@functools.partial(jax.jit, static_argnames=("config",))
def _history_posterior(home: Homes, object_index, tau, tau_q, history, config: HomesConfig):
    law = object_law(home, object_index, config)
    weights = favourite_weights(home, object_index, tau, history, config)
    law["targets"] = jnp.where(law["regime"] == PREFERENCES, schedules.preference_targets(
        weights, law["allowed"], home.num_allowed[object_index], config.preference_mass),
        law["targets"])
    r = law["allowed"].shape[0]
    start = jax.nn.one_hot(home.receptacle[tau, object_index], r, dtype=jnp.float32)
    p = _forward(law, start, tau, tau_q)
    valid = _valid(home, object_index, tau, tau_q) & (history >= 1) & (history <= tau + 1)
    return jnp.where(valid, p, jnp.nan)


def _after(bound):
    """``bound + 1`` for a concrete hour, else no bound (a traced τ checks under jit nothing)."""
    return int(bound) + 1 if is_concrete(bound) else None


def _check_query(home: Homes, object_index, tau, tau_q, config: HomesConfig):
    """A query's arguments checked (values when concrete; ``home`` one home of ``config``)."""
    check_instance("config", config, HomesConfig)
    t = config.num_hours
    object_index = check_int_array("object_index", object_index, 0, config.max_objects - 1,
                                   shape=())
    tau = check_int_array("tau", tau, 0, t - 1, shape=())
    tau_q = check_int_array("tau_q", tau_q, _after(tau), t - 1, shape=())
    validate_homes(home, config, batched=False, values=False)
    if (is_concrete(home.object_valid, object_index, tau, tau_q)
            and not bool(home.object_valid[int(object_index)])):
        raise ValueError(f"object_index {int(object_index)} is a masked object slot (unused, or "
                         f"its class has no allowed receptacle in this home)")
    return object_index, tau, tau_q


def homes_posterior(home: Homes, object_index, tau, tau_q,
                    config: HomesConfig = DEFAULT_HOMES_CONFIG) -> jax.Array:
    """(R,) float32: P(object ``object_index`` on receptacle r at hour ``tau_q`` | where it is
    at ``tau``), exact; object_index, tau, tau_q int scalars, 0 <= tau < tau_q <= T − 1.
    """
    object_index, tau, tau_q = _check_query(home, object_index, tau, tau_q, config)
    return _posterior(home, object_index, tau, tau_q, config)


def homes_history_posterior(home: Homes, object_index, tau, tau_q, history,
                            config: HomesConfig = DEFAULT_HOMES_CONFIG) -> jax.Array:
    """(R,) float32: the posterior at ``tau_q`` given the object's receptacles at the
    ``history`` hours τ − history + 1 … τ (1 <= history <= tau + 1)."""
    object_index, tau, tau_q = _check_query(home, object_index, tau, tau_q, config)
    history = check_int_array("history", history, 1, _after(tau), shape=())
    return _history_posterior(home, object_index, tau, tau_q, history, config)


@functools.partial(jax.jit, static_argnames=("config",))
def _filtered_posterior(home: Homes, object_index, observed, tau, tau_q, config: HomesConfig):
    """The unchecked core of :func:`filtered_posterior` (jittable, vmappable)."""
    law = object_law(home, object_index, config)
    allowed = law["allowed"]
    r = allowed.shape[0]
    m = observed.shape[1]
    column = jnp.clip(object_index, 0, m - 1)
    where = home.receptacle[:, column]  # (T,)
    seen = observed[:, column] & (jnp.arange(observed.shape[0]) <= tau)  # (T,)
    num = jnp.maximum(home.num_allowed[column], 1).astype(jnp.float32)

    def condition(p, t):
        """p times the indicator of where the object was seen at t, renormalised (if the law
        gives that sighting no mass, the sighting itself); p unchanged where t is unseen."""
        hit = jax.nn.one_hot(where[t], r, dtype=p.dtype)
        q = p * hit
        total = jnp.sum(q)
        return jnp.where(seen[t], jnp.where(total > 0, q / jnp.where(total > 0, total, 1.0),
                                            hit), p)

    def hour(p, t):  # t -> t + 1 while t < τ_q, then the sighting at t + 1 (if ≤ τ)
        p = jnp.where(t < tau_q, schedules.step_distribution(law, p, t), p)
        return condition(p, t + 1), None

    start = condition(jnp.where(allowed, 1.0 / num, 0.0), 0)  # hour 0: uniform over A
    p, _ = jax.lax.scan(hour, start, jnp.arange(observed.shape[0] - 1))
    return jnp.where(_valid(home, object_index, tau, tau_q), p, jnp.nan)


def filtered_posterior(home: Homes, object_index, observed, tau, tau_q,
                       config: HomesConfig = DEFAULT_HOMES_CONFIG) -> jax.Array:
    """(R,) float32: P(object ``object_index`` on receptacle r at hour ``tau_q`` | its
    receptacles at the hours t <= ``tau`` where ``observed`` (T, M) bool is True), the law known,
    from the uniform start at hour 0.
    """
    object_index, tau, tau_q = _check_query(home, object_index, tau, tau_q, config)
    observed = check_mask("observed", observed, (config.num_hours, config.max_objects))
    return _filtered_posterior(home, object_index, jnp.asarray(observed, bool), tau, tau_q,
                               config)


def transition_matrix(home: Homes, object_index, hour,
                      config: HomesConfig = DEFAULT_HOMES_CONFIG) -> jax.Array:
    """P_hour (R, R) float32 of one object: [i, j] = P(j at hour + 1 | i at hour); zero outside
    its allowed receptacles."""
    check_instance("config", config, HomesConfig)
    object_index = check_int_array("object_index", object_index, 0, config.max_objects - 1,
                                   shape=())
    hour = check_int_array("hour", hour, 0, config.num_hours - 2, shape=())
    validate_homes(home, config, batched=False, values=False)
    return _transition_matrix(home, object_index, hour, config)


@functools.partial(jax.jit, static_argnames=("config",))
def _transition_matrix(home: Homes, object_index, hour, config: HomesConfig):
    p = schedules.transition_matrix(object_law(home, object_index, config), hour)
    m = home.object_valid.shape[0]
    valid = (object_index >= 0) & (object_index < m) & (hour >= 0) & (hour < config.num_hours - 1)
    return jnp.where(valid, p, jnp.nan)
