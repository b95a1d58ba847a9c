"""Schedule regimes: each object's hourly transition law over its A allowed receptacles
(docs/flowsim.md, "Homes").

P_t = (1 − m_t) I_A + m_t B_{c(t)}, m_t the object's ``move`` at hour of day t mod 24 and B a
row-stochastic move kernel over A (zero outside A), per regime (``REGIMES``): preferences,
balanced, frequent and routine.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.flowsim.homes.config import (
    HOURS_PER_WEEK,
    NUM_CONTEXTS,
    REGIMES,
    HomesConfig,
    context_of,
)
from flowmaps_jax.flowsim.homes.floorplan import split_uniforms
from flowmaps_jax.flowsim.kernels import distance_weights

PREFERENCES, BALANCED, FREQUENT, ROUTINE = (REGIMES.index(r) for r in
                                            ("preferences", "balanced", "frequent", "routine"))


def law_uniforms(config: HomesConfig) -> dict[str, tuple[int, ...]]:
    """The uniforms ``draw_laws`` reads, by name and shape."""
    return {"regime": (config.max_objects,), "favourite": (config.max_objects, NUM_CONTEXTS)}


def draw_laws(u, object_valid, cycle, num_allowed, config: HomesConfig):
    """Each object's regime (M,) int32 and favourites (M, NUM_CONTEXTS) int32 (receptacle
    indices, drawn uniformly over its allowed receptacles; −1 for masked objects), from
    uniforms u (``law_uniforms``, flat)."""
    u = split_uniforms(u, law_uniforms(config))
    used = jnp.asarray(config.regimes_used, jnp.int32)
    pick = jnp.floor(u["regime"] * len(used)).astype(jnp.int32)
    regime = used[jnp.minimum(pick, len(used) - 1)]
    u = u["favourite"]
    position = jnp.minimum(jnp.floor(u * num_allowed[:, None]).astype(jnp.int32),
                           jnp.maximum(num_allowed[:, None] - 1, 0))
    favourite = jnp.take_along_axis(cycle, position, axis=1)
    return regime, jnp.where(object_valid[:, None], favourite, -1)


def move_probabilities(regime, config: HomesConfig) -> jnp.ndarray:
    """(..., 24) float32 m_h: the probability of a move at each hour of the day."""
    rho = jnp.asarray([config.preference_move, config.balanced_move, config.frequent_move, 1.0],
                      jnp.float32)[regime]
    activity = jnp.asarray(config.activity, jnp.float32)
    scaled = rho[..., None] * activity
    return jnp.where((regime == ROUTINE)[..., None], 1.0, scaled)


def week_contexts(config: HomesConfig) -> jnp.ndarray:
    """(168,) int32: the preference context of each hour of the week (a law's ``"context"``)."""
    return jnp.asarray(context_of(np.arange(HOURS_PER_WEEK), config.day_phases), jnp.int32)


def _cycle_shifts(cycle, num_allowed, r: int, shifts: int) -> jnp.ndarray:
    """(shifts, R, R) float32: S^a for a = 0 … shifts − 1 on the cycle (zero outside it)."""
    n = jnp.maximum(num_allowed, 1)
    position = jnp.arange(r)
    here = jax.nn.one_hot(cycle, r, dtype=jnp.float32)  # (R pos, R); cycle −1 -> zero row
    moves = []
    for a in range(shifts):
        there = jax.nn.one_hot(cycle[jnp.mod(position + a, n)], r, dtype=jnp.float32)
        there = jnp.where((position < num_allowed)[:, None], there, 0.0)
        moves.append(here.T @ there)
    return jnp.stack(moves)


def move_kernel(regime, cycle, num_allowed, allowed, distance, config: HomesConfig):
    """One object's state-dependent move kernel B (R, R) float32 (balanced, frequent, routine;
    the identity on A for preferences, whose B_c is ``preference_targets``)."""
    r = allowed.shape[0]
    eye = jnp.where(allowed[:, None], jnp.eye(r, dtype=jnp.float32), 0.0)
    shifts = _cycle_shifts(cycle, num_allowed, r, 3)
    single = num_allowed <= 1
    others = (allowed[:, None] & allowed[None, :] & ~jnp.eye(r, dtype=bool)).astype(jnp.float32)
    uniform = others / jnp.maximum(num_allowed - 1, 1).astype(jnp.float32)
    c = config.balanced_cycle
    balanced = c * shifts[1] + (1 - c) * uniform
    weight, total = distance_weights(others > 0, distance, config.frequent_length)
    frequent = weight / jnp.where(total > 0, total, 1.0)
    p0, p1, p2 = config.routine_probs
    routine = p0 * shifts[0] + p1 * shifts[1] + p2 * shifts[2]
    kernel = jnp.select([regime == BALANCED, regime == FREQUENT, regime == ROUTINE],
                        [balanced, frequent, routine], eye)
    return jnp.where(single, eye, kernel)


def preference_targets(favourite, allowed, num_allowed, mass) -> jnp.ndarray:
    """π (..., C, R) float32 for favourites (..., C) (or, for a posterior over favourites, pass
    their weights (..., C, R) instead: π is linear in them)."""
    r = allowed.shape[-1]
    weight = (jax.nn.one_hot(favourite, r, dtype=jnp.float32) if favourite.ndim == allowed.ndim
              else favourite)
    n = num_allowed[..., None, None].astype(jnp.float32)
    a = jnp.where(n > 1, mass, 1.0)
    b = jnp.where(n > 1, (1.0 - mass) / jnp.maximum(n - 1, 1.0), 0.0)
    pi = a * weight + b * (1.0 - weight)
    return jnp.where(allowed[..., None, :], pi, 0.0)


def _targets(law: dict, t) -> jnp.ndarray:
    """π_{c(t)} (R,): the law's preference targets at hour t."""
    return law["targets"][law["context"][t % HOURS_PER_WEEK]]


def step_distribution(law: dict, p, t) -> jnp.ndarray:
    """p (R,) at hour t -> its distribution at t + 1 under one object's law (p P_t)."""
    m = law["move"][t % 24]
    moved = jnp.where(law["regime"] == PREFERENCES,
                      jnp.sum(p) * _targets(law, t), p @ law["kernel"])
    return (1.0 - m) * p + m * moved


def transition_matrix(law: dict, t) -> jnp.ndarray:
    """P_t (R, R) float32 of one object's law at hour t: [i, j] = P(j at t + 1 | i at t);
    rows and columns outside the allowed receptacles are zero."""
    allowed = law["allowed"]
    r = allowed.shape[0]
    eye = jnp.where(allowed[:, None], jnp.eye(r, dtype=jnp.float32), 0.0)
    target = jnp.where(allowed[:, None], _targets(law, t)[None, :], 0.0)
    moved = jnp.where(law["regime"] == PREFERENCES, target, law["kernel"])
    m = law["move"][t % 24]
    return (1.0 - m) * eye + m * moved
