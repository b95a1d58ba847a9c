"""Habits: each object's own transition law over its slots, and the exact posterior given a
history (docs/flowsim.md, "Habits").

Families (``HABITS``): routine, preferences (one or two favourite slots), dynamic (distance
kernel). Hypotheses are fixed by F alone: index 0 the routine, 1 … F the single favourites,
then the pairs (i < j) in lexicographic order, the last the dynamic habit; a favourite at slot
≥ K does not exist for an object with K places. ``history_posterior``: hypothesis weights ∝
prior(h) · [e₀ P_h^{τ−n+1}](s_{τ−n+1}) · Π P_h(s_i, s_{i+1}), the place at τ + Δτ is
Σ_h w_h · onehot(s_τ) P_h^{Δτ}.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.flowsim.config import HABITS, FlowSimConfig, sim_params
from flowmaps_jax.flowsim.kernels import distance_weights
from flowmaps_jax.flowsim.worlds import HABITS_HISTORY
from flowmaps_jax.validation import (
    check_instance,
    check_int,
    check_int_array,
    check_probabilities,
)

ROUTINE, PREFERENCES, DYNAMIC = range(3)


def num_hypotheses(num_furniture: int) -> int:
    """Number of habit hypotheses for F places: routine, F singles, F(F−1)/2 pairs, dynamic."""
    f = num_furniture
    return 2 + f + f * (f - 1) // 2


@functools.lru_cache(maxsize=16)
def hypothesis_table(num_furniture: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(family (NH,) int32 index into ``HABITS``, favourites (NH, F) bool, needs (NH,) int32:
    the fewest places K for which the hypothesis exists) for F places."""
    f = num_furniture
    sets = [()] + [(i,) for i in range(f)] + [(i, j) for i in range(f) for j in range(i + 1, f)]
    family = np.array([ROUTINE] + [PREFERENCES] * (len(sets) - 1) + [DYNAMIC], np.int32)
    favourites = np.zeros((len(sets) + 1, f), bool)
    for h, places in enumerate(sets):
        favourites[h, list(places)] = True
    needs = np.array([1] + [max(s) + 1 for s in sets[1:]] + [1], np.int32)
    return family, favourites, needs


def hypothesis_names(num_furniture: int) -> list[str]:
    """Readable name of every hypothesis, e.g. 'routine', 'preferences {0, 2}', 'dynamic'."""
    family, favourites, _ = hypothesis_table(num_furniture)
    return [HABITS[fam] if fam != PREFERENCES else
            "preferences {" + ", ".join(str(i) for i in np.flatnonzero(fav)) + "}"
            for fam, fav in zip(family, favourites, strict=True)]


def habit_prior(num_slots, habit_probs, num_furniture: int) -> jnp.ndarray:
    """Prior (..., NH) float32 over the hypotheses of objects with ``num_slots`` (...) places.

    habit_probs: (3,) probabilities of the families in ``HABITS`` order. Concrete arguments are
    checked (ValueError naming the argument); traced ones are used as given.
    """
    num_furniture = check_int("num_furniture", num_furniture)
    num_slots = check_int_array("num_slots", num_slots, 1, num_furniture)
    check_probabilities("habit_probs", habit_probs, (3,))
    family, _, needs = (jnp.asarray(a) for a in hypothesis_table(num_furniture))
    k = jnp.asarray(num_slots, jnp.int32)[..., None]
    exists = needs <= k  # (..., NH)
    per_family = jax.nn.one_hot(family, 3, dtype=jnp.float32)  # (NH, 3)
    count = jnp.einsum("...h,hc->...c", exists.astype(jnp.float32), per_family)  # (..., 3)
    share = jnp.asarray(habit_probs, jnp.float32) / jnp.maximum(count, 1.0)
    return jnp.where(exists, jnp.take_along_axis(
        share, jnp.broadcast_to(family, exists.shape), axis=-1), 0.0)


def _routine_matrix(k, f: int, probs) -> jnp.ndarray:
    row = jnp.arange(f)
    matrix = sum(p * jax.nn.one_hot(jnp.mod(row + a, k), f, dtype=jnp.float32)
                 for a, p in enumerate(jnp.asarray(probs, jnp.float32)))
    return matrix


def _preference_matrix(k, favourites, move, mass) -> jnp.ndarray:
    f = favourites.shape[-1]
    place = jnp.arange(f) < k
    fav = favourites & place
    others = place & ~fav
    n_fav = jnp.maximum(jnp.sum(fav), 1)
    n_others = jnp.sum(others)
    fav_mass = jnp.where(n_others > 0, mass, 1.0)
    pi = jnp.where(fav, fav_mass / n_fav,
                   jnp.where(others, (1.0 - fav_mass) / jnp.maximum(n_others, 1), 0.0))
    return (1.0 - move) * jnp.eye(f, dtype=jnp.float32) + move * pi[None, :]


def _dynamic_matrix(k, centres, stay, length) -> jnp.ndarray:
    f = centres.shape[0]
    place = jnp.arange(f) < k
    distance = jnp.linalg.norm(centres[:, None, :] - centres[None, :, :], axis=-1)
    others = place[None, :] & ~jnp.eye(f, dtype=bool)
    weight, total = distance_weights(others, distance, length)  # no row underflows
    move = jnp.where(total > 0, (1.0 - stay) * weight / jnp.where(total > 0, total, 1.0), 0.0)
    stay_here = jnp.where(total[:, 0] > 0, stay, 1.0)
    return move + stay_here[:, None] * jnp.eye(f, dtype=jnp.float32)


def hypothesis_matrix(hypothesis, num_slots, slot_centres, params) -> jnp.ndarray:
    """Transition matrix (F, F) float32, [i, j] = P(slot j next | slot i now), zero at rows and
    columns ≥ K, of hypothesis () int for one object: num_slots () int K, slot_centres (F, 2)
    table centres along the visiting order in map sides, params ``sim_params``."""
    f = slot_centres.shape[0]
    family, favourites, _ = (jnp.asarray(a) for a in hypothesis_table(f))
    fam = family[hypothesis]
    k = jnp.asarray(num_slots, jnp.int32)
    matrix = jnp.where(
        fam == ROUTINE, _routine_matrix(k, f, params["transition_probs"]),
        jnp.where(fam == PREFERENCES,
                  _preference_matrix(k, favourites[hypothesis], params["preference_move"],
                                     params["preference_mass"]),
                  _dynamic_matrix(k, slot_centres, params["dynamic_stay"],
                                  params["dynamic_length"])))
    place = jnp.arange(f) < k
    return jnp.where(place[:, None] & place[None, :], matrix, 0.0)


def transition_matrices(num_slots, slot_centres, params) -> jnp.ndarray:
    """Every hypothesis's transition matrix (..., NH, F, F) float32; num_slots (...) int K,
    slot_centres (..., F, 2)."""
    f = slot_centres.shape[-2]
    lead = jnp.shape(num_slots)
    flat_k = jnp.reshape(num_slots, (-1,))
    flat_c = jnp.reshape(slot_centres, (-1, f, 2))
    per_object = jax.vmap(  # over objects, then hypotheses
        lambda k, c: jax.vmap(lambda h: hypothesis_matrix(h, k, c, params))(
            jnp.arange(num_hypotheses(f))))
    return per_object(flat_k, flat_c).reshape(*lead, num_hypotheses(f), f, f)


# ------------------------------------------------------------------------------ rollout


def _uniform24(words: jnp.ndarray) -> jnp.ndarray:
    """uint32 words -> float32 uniforms on a 2**-24 grid in [0, 1)."""
    return (words >> 8).astype(jnp.float32) * (1.0 / 16777216.0)


def rollout_num_words(num_timesteps: int) -> int:
    """Random 32-bit words one object's habit rollout consumes."""
    return 2 + num_timesteps - 1


def draw_hypothesis(u_family, u_member, num_slots, habit_probs, num_furniture: int):
    """One object's hypothesis index from two uniforms: the family by ``habit_probs``, then one
    of that family's hypotheses that exist for K = ``num_slots`` places, uniformly."""
    family, _, needs = (jnp.asarray(a) for a in hypothesis_table(num_furniture))
    cdf = jnp.cumsum(jnp.asarray(habit_probs, jnp.float32))
    fam = jnp.minimum(jnp.sum(u_family >= cdf[:-1]), 2)
    fam = jnp.where(jnp.asarray(habit_probs)[fam] > 0, fam, jnp.argmax(habit_probs > 0))
    member = (family == fam) & (needs <= num_slots)
    count = jnp.sum(member)
    pick = jnp.minimum(jnp.floor(u_member * count).astype(jnp.int32), count - 1)
    return jnp.argmax(member & (jnp.cumsum(member) == pick + 1)).astype(jnp.int32)


def habit_rollout(words, num_slots, slot_centres, params, num_timesteps: int,
                  families: tuple[int, ...] = (ROUTINE, PREFERENCES, DYNAMIC),
                  max_places: int | None = None):
    """One object's (slots (T,) int32 starting at 0, hypothesis () int32); vmap it over objects.

    words: (rollout_num_words(T),) uint32, one uniform per step. num_slots: () int K.
    slot_centres: (F, 2) in map sides. ``families``: the ``HABITS`` indices the world can draw
    (static). ``max_places``: a static bound on K (default F) for the dynamic habit's matrix.
    """
    f = slot_centres.shape[0]
    u = _uniform24(words)
    h = draw_hypothesis(u[0], u[1], num_slots, params["habit_probs"], f)
    family, favourites, _ = (jnp.asarray(a) for a in hypothesis_table(f))
    k = jnp.asarray(num_slots, jnp.int32)
    last = jnp.maximum(k - 1, 0)
    steps = u[2:2 + num_timesteps - 1]  # (T - 1,)
    start = jnp.zeros((1,), jnp.int32)
    paths = {}
    if ROUTINE in families:
        cdf = jnp.cumsum(jnp.asarray(params["transition_probs"], jnp.float32))
        advance = jnp.sum(steps[:, None] >= cdf[None, :-1], axis=1).astype(jnp.int32)
        paths[ROUTINE] = jnp.mod(jnp.cumsum(advance), jnp.maximum(k, 1))
    if PREFERENCES in families:
        move = jnp.asarray(params["preference_move"], jnp.float32)
        pi = _preference_matrix(k, favourites[h], 1.0, params["preference_mass"])[0]
        moved = steps >= 1.0 - move
        v = (steps - (1.0 - move)) / jnp.where(move > 0, move, 1.0)
        target = jnp.minimum(jnp.sum(jnp.cumsum(pi)[None, :] <= v[:, None], axis=1), last)
        when = jax.lax.cummax(jnp.where(moved, jnp.arange(steps.shape[0]), -1))
        paths[PREFERENCES] = jnp.where(when >= 0, target[jnp.maximum(when, 0)], 0)
    if DYNAMIC in families:
        n = f if max_places is None else min(max_places, f)  # slots stay below K <= n
        place = jnp.arange(n) < k
        matrix = jnp.where(place[:, None] & place[None, :], _dynamic_matrix(
            k, slot_centres[:n], params["dynamic_stay"], params["dynamic_length"]), 0.0)
        cdf = jnp.cumsum(matrix, axis=-1)

        def step(slot, u_t):
            nxt = jnp.minimum(jnp.sum(cdf[slot] <= u_t), last).astype(jnp.int32)
            return nxt, nxt

        paths[DYNAMIC] = jax.lax.scan(step, jnp.int32(0), steps)[1]
    fam = family[h]
    later = paths[families[-1]]
    for index in families[:-1]:
        later = jnp.where(fam == index, paths[index], later)
    return jnp.concatenate([start, later.astype(jnp.int32)]), h


# --------------------------------------------------------------------- history posterior


def _matrix_power_apply(vectors, matrices, power, max_power: int):
    """vectors (NH, F) @ matrices (NH, F, F) ** power, power () int in 0..max_power."""
    def step(v, i):
        return jnp.where(i < power, jnp.einsum("hf,hfg->hg", v, matrices), v), None

    out, _ = jax.lax.scan(step, vectors, jnp.arange(max_power))
    return out


def history_posterior_one(transitions, prior, history, valid, tau, horizon, num_timesteps: int):
    """(exact posterior (F,) of one object's slot at τ + Δτ, hypothesis weights (NH,)).

    transitions: (NH, F, F); prior: (NH,). history: (H,) int32 slots at τ − H + 1 … τ; valid:
    (H,) bool, a suffix (padding first). tau, horizon: () int.
    """
    nh, f, _ = transitions.shape
    n = jnp.sum(valid)
    first = jnp.argmax(valid)
    start = jnp.broadcast_to(jax.nn.one_hot(0, f, dtype=jnp.float32), (nh, f))
    marginal = _matrix_power_apply(start, transitions, tau - n + 1, num_timesteps - 1)
    log_lik = jnp.log(marginal[:, history[first]])
    pair = valid[:-1] & valid[1:]  # (H - 1,)
    step_p = transitions[:, history[:-1], history[1:]]  # (NH, H - 1)
    log_lik = log_lik + jnp.sum(jnp.where(pair[None], jnp.log(jnp.where(pair[None], step_p, 1.0)),
                                          0.0), axis=-1)
    log_w = jnp.where(prior > 0, jnp.log(jnp.where(prior > 0, prior, 1.0)) + log_lik, -jnp.inf)
    weights = jax.nn.softmax(log_w)
    now = jnp.broadcast_to(jax.nn.one_hot(history[-1], f, dtype=jnp.float32), (nh, f))
    ahead = _matrix_power_apply(now, transitions, horizon, num_timesteps - 1)
    return weights @ ahead, weights


@functools.partial(jax.jit, static_argnames=("num_timesteps",))
def history_posterior_batch(transitions, prior, history, valid, tau, horizon, num_timesteps: int):
    """``history_posterior_one`` over a leading query axis Q: returns ((Q, F), (Q, NH))."""
    return jax.vmap(functools.partial(history_posterior_one, num_timesteps=num_timesteps))(
        transitions, prior, history, valid, tau, horizon)


def empirical_frequency(history, valid, num_furniture: int) -> jnp.ndarray:
    """(..., F) fraction of the observed history (..., H) int, valid (..., H) at each slot."""
    counts = jnp.sum(jax.nn.one_hot(history, num_furniture, dtype=jnp.float32)
                     * valid[..., None], axis=-2)
    return counts / jnp.maximum(jnp.sum(counts, axis=-1, keepdims=True), 1.0)


# ----------------------------------------------------------------------- on FlowSim scenes


def slot_centres(scenes, config, env=None) -> jnp.ndarray:
    """(E, M, F, 2) table centres along each object's visiting order, in map sides (padding
    places repeat the first table; they are never visited); with ``env`` (Q,), only those
    environments' (Q, M, F, 2)."""
    boxes = jnp.asarray(scenes.furniture_boxes, jnp.float32)
    order = jnp.asarray(scenes.visit_order)
    if env is not None:
        boxes, order = boxes[env], order[env]
    centre = 0.5 * (boxes[..., :2] + boxes[..., 2:]) / config.map_size  # (E, F, 2)
    return jax.vmap(lambda c, t: c[t])(centre, jnp.maximum(order, 0))


def scene_hypotheses(scenes, config, env, obj) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(transitions (Q, NH, F, F), prior (Q, NH)) of objects ``obj`` (Q,) in environments
    ``env`` (Q,): every habit hypothesis's matrix for that object's places, and the prior of
    ``config.habits``."""
    env, obj = jnp.asarray(env, jnp.int32), jnp.asarray(obj, jnp.int32)
    params = sim_params(config)
    k = jnp.asarray(scenes.num_slots)[env, obj]
    centres = slot_centres(scenes, config, env)[jnp.arange(env.shape[0]), obj]
    return (transition_matrices(k, centres, params),
            habit_prior(k, params["habit_probs"], config.num_furniture))


def observed_history(scenes, env, obj, tau, history_len, max_history: int | None = None):
    """(history (Q, H_max) int32, valid (Q, H_max) bool): the slots of objects ``obj`` in
    ``env`` at τ − H + 1 … τ (last entry at τ; padding first, slot 0). env, obj, tau,
    history_len: (Q,) ints (history_len may be one int)."""
    tau = jnp.asarray(tau, jnp.int32)
    h = jnp.broadcast_to(jnp.asarray(history_len, jnp.int32), tau.shape)
    width = int(np.max(np.asarray(history_len))) if max_history is None else max_history
    return _observed_history(jnp.asarray(scenes.slot), jnp.asarray(env), jnp.asarray(obj), tau,
                             h, width)


@functools.partial(jax.jit, static_argnames=("width",))
def _observed_history(slot, env, obj, tau, h, width: int):
    lag = jnp.arange(width - 1, -1, -1)  # H_max - 1 … 0
    time = tau[:, None] - lag[None, :]
    valid = (lag[None, :] < h[:, None]) & (time >= 0)
    slots = slot[env[:, None], jnp.maximum(time, 0), obj[:, None]]
    return jnp.where(valid, slots, 0), valid


def _check_query(name: str, value, q: int | None, low: int, high, high_name: str | None = None):
    """A (Q,) integer query argument of :func:`history_posterior` in ``low..high``."""
    value = check_int_array(name, value)
    if np.ndim(value) != 1 or (q is not None and np.shape(value)[0] != q):
        count = "" if q is None else f" with Q = {q} (env's queries)"
        raise ValueError(f"{name} must have shape (Q,){count}, one entry per query; got "
                         f"{tuple(np.shape(value))}")
    return check_int_array(name, value, low, high, high_name=high_name)


def history_posterior(scenes, config, env, obj, tau, horizon, history_len=1):
    """Exact posterior (Q, F) over the slot of object ``obj`` in ``env`` at τ + Δτ given its
    slots in ``scenes.slot`` at τ − H + 1 … τ, the habit marginalised over ``config``'s mixture.

    env, obj, tau, horizon: (Q,) ints; history_len: an int or (Q,) ints in 1 … τ + 1.
    ValueError naming the argument on bad input.
    """
    check_instance("config", config, FlowSimConfig)
    t = config.num_timesteps
    env = _check_query("env", env, None, 0, scenes.num_envs - 1)
    q = env.shape[0]
    obj = _check_query("obj", obj, q, 0, config.num_objects - 1)
    tau = _check_query("tau", tau, q, 0, t - 1)
    horizon = _check_query("horizon", horizon, q, 0, t - 1 - np.asarray(tau),  # τ + Δτ < T
                           "T - 1 - tau")
    history_len = check_int_array("history_len", history_len, 1, np.asarray(tau) + 1,
                                  high_name="tau + 1 (no longer than the query's past)")
    width = int(np.max(history_len))
    history_len = np.broadcast_to(history_len, tau.shape).astype(np.int32)
    return _history_posterior(scenes, config, env, obj, tau, horizon, history_len, width)


@functools.partial(jax.jit, static_argnames=("config", "width"))
def _history_posterior(scenes, config, env, obj, tau, horizon, history_len, width: int):
    transitions, prior = scene_hypotheses(scenes, config, env, obj)
    history, valid = _observed_history(scenes.slot, env, obj, tau, history_len, width)
    posterior, _ = history_posterior_batch(transitions, prior, history, valid, tau, horizon,
                                           config.num_timesteps)
    return posterior


def habit_family(scenes, env, obj) -> np.ndarray:
    """(...) int32 ``HABITS`` index of the habit of each queried (env, obj) (broadcastable)."""
    family = hypothesis_table(int(np.asarray(scenes.visit_order).shape[-1]))[0]
    return family[np.asarray(scenes.habit)[np.asarray(env), np.asarray(obj)]]


def available_history(tau, history_len: int) -> np.ndarray:
    """min(H, τ + 1) for each τ: the observations a history of ``history_len`` maps holds."""
    return np.minimum(int(history_len), np.asarray(tau) + 1).astype(np.int32)


EXACT_H1_ROW = "exact, H = 1"
"""Reference row: the exact posterior given only the last observation."""


def empirical_row(history: int) -> str:
    """Name of the reference row: the fraction of the last H observations at each place."""
    return f"empirical frequency, H = {int(history)}"


def uses_history(config, history: int = 1) -> bool:
    """Whether queries are scored against the history posterior (a habit other than the
    routine, or H > 1) rather than the paper's one-observation ``exact_posterior``."""
    return bool(config.has_habits or int(history) > 1)


def default_history(config, reads: int = 1) -> int:
    """The reference posterior's default history: ``reads`` (the most maps a scored model
    reads), at least ``worlds.HABITS_HISTORY`` in a world with habits, at most T."""
    return min(max(int(reads), HABITS_HISTORY if config.has_habits else 1),
               config.num_timesteps)


_REFERENCE_CHUNK = 4096  # queries per history_posterior call (each holds NH × F × F matrices)


def history_references(scenes, config, env, tau, horizon, history: int):
    """Ground truth for R query rows, every object: env, tau (R,), horizon (R, M). Returns
    (q (R, M, F) float32 exact posterior given min(H, τ + 1) observations, habit (R, M) int32,
    extra {``EXACT_H1_ROW``, ``empirical_row(H)``: (R, M, F)} or None for H = 1)."""
    rows, m, f = int(np.shape(env)[0]), config.num_objects, config.num_furniture
    q_env = np.repeat(np.asarray(env), m)
    q_obj = np.tile(np.arange(m, dtype=np.int32), rows)
    q_tau = np.repeat(np.asarray(tau), m)
    q_horizon = np.asarray(horizon).reshape(-1)
    seen = available_history(q_tau, history)
    n = q_env.size

    def posterior(history_len) -> jnp.ndarray:
        lengths = np.broadcast_to(history_len, q_tau.shape)
        parts = []
        for first in range(0, n, _REFERENCE_CHUNK):
            index = (np.minimum(np.arange(first, first + _REFERENCE_CHUNK), n - 1)
                     if n > _REFERENCE_CHUNK else np.arange(n))
            part = history_posterior(scenes, config, q_env[index], q_obj[index], q_tau[index],
                                     q_horizon[index], lengths[index])
            parts.append(np.asarray(part)[: min(_REFERENCE_CHUNK, n - first)])
        return jnp.asarray(np.concatenate(parts).reshape(rows, m, f), jnp.float32)

    probs = posterior(seen)
    habit = jnp.asarray(habit_family(scenes, q_env, q_obj).reshape(rows, m), jnp.int32)
    if history == 1:
        return probs, habit, None
    observed, valid = observed_history(scenes, q_env, q_obj, q_tau, seen, max_history=history)
    frequency = empirical_frequency(observed, valid, f).reshape(rows, m, f)
    return probs, habit, {EXACT_H1_ROW: posterior(np.ones_like(q_tau)),
                          empirical_row(history): jnp.asarray(frequency, jnp.float32)}
