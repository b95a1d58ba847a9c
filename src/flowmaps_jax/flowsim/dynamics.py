"""Object dynamics along the visiting order, and their exact posterior (docs/flowsim.md,
"Dynamics"): ``"markov"`` (stay / advance one / advance two) and ``"schedule_jitter"``.
Every object starts at slot 0.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.flowsim.config import (
    DEFAULT_CONFIG,
    DYNAMICS,
    FlowSimConfig,
    SimShape,
)
from flowmaps_jax.flowsim.layout import uniform16
from flowmaps_jax.validation import check_choice, check_instance, check_int_array, is_concrete


def _draw_offsets(u: jnp.ndarray, probs: jnp.ndarray) -> jnp.ndarray:
    """Map uniforms u to {0, 1, 2} with probabilities ``probs`` (3,)."""
    return ((u >= probs[0]).astype(jnp.int32) + (u >= probs[0] + probs[1]).astype(jnp.int32))


def rollout_num_words(shape: SimShape) -> int:
    """Random 32-bit words one rollout consumes (two 16-bit uniforms per word)."""
    return math.ceil((shape.num_timesteps - 1) * shape.num_objects / 2)


def rollout(words: jnp.ndarray, num_slots: jnp.ndarray, params: dict,
            shape: SimShape) -> jnp.ndarray:
    """Slots of M objects over T timesteps, environment axis last.

    words: (rollout_num_words(shape), E) uint32, two uniforms on a 2**-16 grid each.
    num_slots: (M, E) int32 number of slots K of each object's visiting order.
    Returns (T, M, E) int32 position along the visiting order, 0 at t = 0.
    """
    t, m = shape.num_timesteps, shape.num_objects
    halves = jnp.concatenate([words >> 16, words], axis=0)[: (t - 1) * m]
    u = uniform16(halves).reshape((t - 1, m, *words.shape[1:]))
    start = jnp.zeros((1, m, *words.shape[1:]), jnp.int32)
    if shape.dynamics == "markov":
        steps = _draw_offsets(u, params["transition_probs"])

        def step(slot, advance):
            slot = jnp.mod(slot + advance, num_slots)
            return slot, slot

        _, later = jax.lax.scan(step, start[0], steps)
    else:  # "schedule_jitter", the other of DYNAMICS (the config checked which)
        offsets = _draw_offsets(u, params["jitter_probs"]) - 1
        time = jnp.arange(1, t, dtype=jnp.int32).reshape((t - 1,) + (1,) * (u.ndim - 1))
        later = jnp.mod(time + offsets, num_slots[None])
    return jnp.concatenate([start, later], axis=0)


# ---------------------------------------------------------------------- exact posterior


def _advance_table(probs: tuple[float, float, float], max_horizon: int) -> np.ndarray:
    """(H + 1, 2H + 1) float64: row h is the distribution of the total advance after h steps."""
    table = np.zeros((max_horizon + 1, 2 * max_horizon + 1))
    table[0, 0] = 1.0
    for h in range(1, max_horizon + 1):
        table[h] = np.convolve(table[h - 1], np.asarray(probs, np.float64))[: 2 * max_horizon + 1]
    return table


@functools.partial(jax.jit, static_argnames=("config",))
def _markov_posterior(num_slots, slot_now, horizon, config: FlowSimConfig):
    max_h = config.num_timesteps - 1
    table = jnp.asarray(_advance_table(config.transition_probs, max_h), jnp.float32)
    num_slots, slot_now, horizon = jnp.broadcast_arrays(
        jnp.asarray(num_slots, jnp.int32), jnp.asarray(slot_now, jnp.int32),
        jnp.asarray(horizon, jnp.int32))
    weights = table[jnp.clip(horizon, 0, max_h)]  # (..., 2H+1)
    advance = jnp.arange(2 * max_h + 1)
    position = jnp.mod(slot_now[..., None] + advance, num_slots[..., None])  # (..., 2H+1)
    onehot = jax.nn.one_hot(position, config.num_furniture, dtype=jnp.float32)
    return jnp.einsum("...n,...nf->...f", weights, onehot)


@functools.partial(jax.jit, static_argnames=("config",))
def _jitter_posterior(num_slots, slot_now, tau_q, config: FlowSimConfig):
    num_slots, slot_now, tau_q = jnp.broadcast_arrays(
        jnp.asarray(num_slots, jnp.int32), jnp.asarray(slot_now, jnp.int32),
        jnp.asarray(tau_q, jnp.int32))
    probs = jnp.asarray(config.jitter_probs, jnp.float32)
    offsets = jnp.arange(-1, 2)
    position = jnp.mod(tau_q[..., None] + offsets, num_slots[..., None])  # (..., 3)
    onehot = jax.nn.one_hot(position, config.num_furniture, dtype=jnp.float32)
    jittered = jnp.einsum("n,...nf->...f", probs, onehot)
    at_start = jax.nn.one_hot(jnp.zeros_like(tau_q), config.num_furniture, dtype=jnp.float32)
    return jnp.where((tau_q == 0)[..., None], at_start, jittered)


def exact_posterior(num_slots, slot_now, horizon, config: FlowSimConfig = DEFAULT_CONFIG,
                    dynamics: str | None = None, tau=None) -> jnp.ndarray:
    """Exact distribution (..., F) float32 of an object's slot ``horizon`` steps ahead.

    num_slots: (...) int number of slots K of the object's visiting order (1..F).
    slot_now: (...) int slot observed at state time tau (0..K-1).
    horizon: (...) int Δτ in 0..T-1 (horizon 0 gives the observed slot).
    dynamics: "markov" or "schedule_jitter"; default ``config.dynamics``.
    tau: (...) int state time, required for "schedule_jitter".
    Leading dims broadcast; entries beyond K are zero. Concrete inputs are validated (ValueError
    naming the argument); a traced row out of range is all NaN.
    """
    check_instance("config", config, FlowSimConfig)
    max_h = config.num_timesteps - 1
    num_slots = check_int_array("num_slots", num_slots, 1, config.num_furniture)
    slot_now = check_int_array("slot_now", slot_now, 0, num_slots - 1, high_name="num_slots - 1")
    horizon = check_int_array("horizon", horizon, 0, max_h)
    if dynamics is not None:
        check_choice("dynamics", dynamics, DYNAMICS)
    if tau is not None:
        tau = check_int_array("tau", tau, 0, max_h)
    dynamics = config.dynamics if dynamics is None else dynamics
    concrete = is_concrete(num_slots, slot_now, horizon)  # then checked above
    if dynamics == "markov":
        probs = _markov_posterior(num_slots, slot_now, horizon, config)
        return probs if concrete else _nan_outside(
            probs, _in_range(num_slots, slot_now, horizon, max_h, config))
    if tau is None:
        raise ValueError("tau is required for dynamics='schedule_jitter' (its posterior depends "
                         "on the absolute query time tau + horizon)")
    if is_concrete(tau, horizon):
        check_int_array("tau + horizon", np.asarray(tau) + np.asarray(horizon), 0, max_h)
    now = jax.nn.one_hot(jnp.asarray(slot_now), config.num_furniture, dtype=jnp.float32)
    ahead = _jitter_posterior(num_slots, slot_now, jnp.asarray(tau) + jnp.asarray(horizon),
                              config)
    probs = jnp.where((jnp.asarray(horizon) == 0)[..., None], now, ahead)
    if concrete and is_concrete(tau):
        return probs
    tau, query = jnp.asarray(tau), jnp.asarray(tau) + jnp.asarray(horizon)
    valid = (_in_range(num_slots, slot_now, horizon, max_h, config) & (tau >= 0)
             & (tau <= max_h) & (query <= max_h))
    return _nan_outside(probs, valid)


def _in_range(num_slots, slot_now, horizon, max_h: int, config: FlowSimConfig) -> jnp.ndarray:
    """(...) bool: where num_slots is in 1..F, slot_now in 0..K − 1 and horizon in 0..max_h (the
    checks of concrete inputs, on traced ones)."""
    k, now, h = (jnp.asarray(a) for a in (num_slots, slot_now, horizon))
    valid = (k >= 1) & (k <= config.num_furniture) & (h >= 0) & (h <= max_h)
    return valid if slot_now is None else valid & (now >= 0) & (now < k)


def _nan_outside(values: jnp.ndarray, valid: jnp.ndarray, trailing: int = 1) -> jnp.ndarray:
    """``values`` (..., *trailing dims) with NaN where ``valid`` (...) is False."""
    valid = jnp.reshape(valid, jnp.shape(valid) + (1,) * trailing)
    return jnp.where(valid, values, jnp.nan)


@functools.partial(jax.jit, static_argnames=("config",))
def _transition_matrix(num_slots, config: FlowSimConfig):
    f = config.num_furniture
    k = jnp.asarray(num_slots, jnp.int32)[..., None]  # (..., 1)
    row = jnp.arange(f)
    matrix = 0.0
    for advance, prob in enumerate(config.transition_probs):
        onehot = jax.nn.one_hot(jnp.mod(row + advance, k), f, dtype=jnp.float32)  # (..., F, F)
        matrix = matrix + prob * onehot
    return jnp.where((row < k)[..., None], matrix, 0.0)


def transition_matrix(num_slots, config: FlowSimConfig = DEFAULT_CONFIG) -> jnp.ndarray:
    """Markov transition matrix (..., F, F) float32: entry [i, j] = P(slot j next | slot i now).

    The top-left K × K block (K = num_slots, (...) int) is the cyclic kernel of
    ``config.transition_probs``, the rest zero; a traced K out of range gives NaN.
    """
    check_instance("config", config, FlowSimConfig)
    num_slots = check_int_array("num_slots", num_slots, 1, config.num_furniture)
    if is_concrete(num_slots):  # its values checked above
        return _transition_matrix(num_slots, config)
    k = jnp.asarray(num_slots)
    return _nan_outside(_transition_matrix(num_slots, config),
                        (k >= 1) & (k <= config.num_furniture), trailing=2)
