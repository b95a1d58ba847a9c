"""Queries on homes (object, map hour τ, query hour τ_q), and the prior's contract:
``prior(homes, queries) -> (E, Q, R)`` float32, the probability that the object stands on
receptacle slot r at τ_q given the home at τ (and its history), rows summing to 1 on the
object's allowed receptacles.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from flowmaps_jax.flowsim.homes.config import HomesConfig
from flowmaps_jax.flowsim.homes.world import Homes
from flowmaps_jax.validation import (
    check_array,
    check_instance,
    check_int,
    check_int_array,
    is_concrete,
)

DEFAULT_HORIZONS = (1, 3, 6, 12, 24, 72, 168)
"""Query horizons τ_q − τ in hours: an hour, a morning, half a day, a day, three days, a week."""


@struct.dataclass
class HomesQueries:
    """Q queries per home, each (E, Q) int32: object slot, map hour τ, query hour τ_q > τ."""

    object_index: jax.Array
    tau: jax.Array
    tau_q: jax.Array

    @property
    def horizon(self) -> jax.Array:
        """(E, Q) τ_q − τ in hours."""
        return self.tau_q - self.tau


def check_horizons(name: str, horizons, most: int) -> tuple[int, ...]:
    """``horizons`` as a tuple: a non-empty tuple (or list) of ints in 1..``most``; the
    messages name ``name``."""
    if not isinstance(horizons, (tuple, list)) or not horizons:
        raise ValueError(f"{name} must be a tuple of horizons; got {horizons!r}")
    return tuple(check_int(name, h, 1, most) for h in horizons)


def draw_queries(key, homes: Homes, config: HomesConfig, num_queries: int, *,
                 history: int = 168, horizons: tuple[int, ...] = DEFAULT_HORIZONS
                 ) -> HomesQueries:
    """Q queries per home: a valid object uniformly, a horizon uniformly from ``horizons``, and
    τ uniformly from the hours that leave ``history`` hours before it and the horizon after it
    (τ ∈ [history − 1, T − 1 − Δ]). Pure given ``key``; jittable."""
    check_instance("config", config, HomesConfig)
    num_queries = check_int("num_queries", num_queries)
    t = config.num_hours
    history = check_int("history", history, 1, t - 1)
    horizons = check_horizons("horizons", horizons, t - history)
    return _draw_queries(key, homes, t, num_queries, history, horizons)


@jax.jit(static_argnums=(2, 3, 4, 5))  # one program, not one per operation
def _draw_queries(key, homes, t, num_queries, history, horizons) -> HomesQueries:
    e, m = homes.object_valid.shape
    k_obj, k_h, k_tau = jax.random.split(key, 3)
    logits = jnp.where(homes.object_valid, 0.0, -jnp.inf)[:, None, :]
    obj = jax.random.categorical(k_obj, jnp.broadcast_to(logits, (e, num_queries, m)))
    dt = jnp.asarray(horizons, jnp.int32)[jax.random.randint(k_h, (e, num_queries), 0,
                                                            len(horizons))]
    low = history - 1
    u = jax.random.uniform(k_tau, (e, num_queries))
    tau = low + jnp.floor(u * (t - dt - low)).astype(jnp.int32)
    return HomesQueries(object_index=obj.astype(jnp.int32), tau=tau, tau_q=tau + dt)


def check_queries(queries: HomesQueries, homes: Homes, config: HomesConfig) -> HomesQueries:
    """``ValueError`` naming the field unless ``queries`` fits ``homes``: (E, Q) ints, objects
    valid, 0 <= τ < τ_q <= T − 1 (values checked when concrete); arrays, not lists."""
    check_instance("queries", queries, HomesQueries)
    for field in ("object_index", "tau", "tau_q"):
        check_array(f"queries.{field}", getattr(queries, field))
    e, t = homes.object_valid.shape[0], config.num_hours
    obj = check_int_array("queries.object_index", queries.object_index, 0,
                          config.max_objects - 1, shape=(e, None))
    q = obj.shape[1]
    tau = check_int_array("queries.tau", queries.tau, 0, t - 2, shape=(e, q))
    tau_q = check_int_array("queries.tau_q", queries.tau_q, 1, t - 1, shape=(e, q))
    if is_concrete(obj, tau, tau_q, homes.object_valid):
        obj, tau, tau_q = np.asarray(obj), np.asarray(tau), np.asarray(tau_q)
        if not np.all(np.take_along_axis(np.asarray(homes.object_valid), obj, axis=1)):
            raise ValueError("queries.object_index names a masked object slot")
        if np.any(tau_q <= tau):
            raise ValueError("queries.tau_q must be > queries.tau")
    return queries


def allowed_slots(homes: Homes, queries: HomesQueries) -> jax.Array:
    """(E, Q, R) bool: the queried object's allowed receptacles."""
    return jnp.take_along_axis(homes.object_allowed, queries.object_index[..., None], axis=1)


def receptacle_at(homes: Homes, hour, object_index) -> jax.Array:
    """(E, Q) int32: where object ``object_index`` (E, Q) stands at ``hour`` (E, Q)."""
    e = jnp.arange(homes.receptacle.shape[0])[:, None]
    return homes.receptacle[e, hour, object_index]
