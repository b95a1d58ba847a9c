"""``generate_homes(key, config, num_homes)``: homes and hourly trajectories, jitted and vmapped.
Home e depends only on ``jax.random.split(key, num_homes)[e]``; an object starts uniformly on an
allowed receptacle and moves each hour by its law (:mod:`.schedules`), one uniform per (object,
hour); only the frequent regime runs a ``lax.scan``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.flowsim.homes import floorplan, furnish, schedules
from flowmaps_jax.flowsim.homes.config import DEFAULT_HOMES_CONFIG, HomesConfig, context_of
from flowmaps_jax.flowsim.homes.schedules import BALANCED, FREQUENT, PREFERENCES, ROUTINE
from flowmaps_jax.flowsim.homes.world import FIELDS, Homes, field_shape, sizes, validate_homes
from flowmaps_jax.resources import array_bytes, check_request_size, computed_rows, first_rows
from flowmaps_jax.validation import check_instance, check_int, check_key


def _uniform24(words: jnp.ndarray) -> jnp.ndarray:
    return (words >> 8).astype(jnp.float32) * (1.0 / 16777216.0)


def _uniform16(words: jnp.ndarray, count: int) -> jnp.ndarray:
    """The first ``count`` uniforms on a 2⁻¹⁶ grid, two per 32-bit word (high half first)."""
    halves = jnp.concatenate([words >> 16, words & 0xFFFF], axis=0)[:count]
    return halves.astype(jnp.float32) * (1.0 / 65536.0)


def trajectory_words(config: HomesConfig) -> int:
    """32-bit words one home's trajectories read (two 16-bit uniforms per object and hour)."""
    return -(-config.num_hours * config.max_objects // 2)


def _pick(cdf: jnp.ndarray, u: jnp.ndarray, last) -> jnp.ndarray:
    """Index of u in a CDF (..., R): the first j with cdf_j > u, at most ``last``."""
    return jnp.minimum(jnp.sum(cdf <= u[..., None], axis=-1), last).astype(jnp.int32)


def layout_uniforms(config: HomesConfig) -> dict[str, int]:
    """How many uniforms each part of a home's layout reads (one ``bits`` call for all)."""
    parts = {"plan": floorplan.plan_uniforms(config),
             "receptacles": furnish.receptacle_uniforms(config),
             "objects": furnish.object_uniforms(config), "laws": schedules.law_uniforms(config)}
    return {name: sum(int(np.prod(shape)) for shape in shapes.values())
            for name, shapes in parts.items()}


def _layout(home_key, config: HomesConfig) -> dict:
    """Everything of one home but its trajectories (one ``jax.random.bits`` call: each call
    costs about a second of compile time)."""
    counts = layout_uniforms(config)
    u = floorplan.split_uniforms(_uniform24(jax.random.bits(
        jax.random.fold_in(home_key, 0), (sum(counts.values()),), jnp.uint32)),
        {name: (count,) for name, count in counts.items()})
    plan = floorplan.floor_plan(u["plan"], config)
    rec = furnish.place_receptacles(u["receptacles"], plan["room_type"], plan["room_box"],
                                    config)
    obj = furnish.place_objects(u["objects"], rec["receptacle_class"], rec["receptacle_valid"],
                                config)
    distance = floorplan.geodesic_distances(
        rec["receptacle_box"][:, :2], rec["receptacle_room"], rec["receptacle_valid"],
        plan["door_position"], plan["door_rooms"], plan["door_valid"], config.num_rooms)
    valid = rec["receptacle_valid"]
    distance = jnp.where(valid[:, None] & valid[None, :], distance, 0.0)
    cycle, num = furnish.cycles(obj["object_allowed"], rec["receptacle_box"], plan["home_size"])
    regime, favourite = schedules.draw_laws(u["laws"], obj["object_valid"], cycle, num, config)
    return {**plan, **rec, **obj, "receptacle_distance": distance, "cycle": cycle,
            "num_allowed": num, "regime": regime, "favourite": favourite}


def _cycle_position(cycle, state):
    """Position along the cycle of receptacle ``state`` (..., M) (0 if absent)."""
    return jnp.argmax(cycle == state[..., None], axis=-1).astype(jnp.int32)


def _hours(t0, steps: int, config: HomesConfig):
    """(hour of day, context) of the hours t0 … t0 + steps − 1 each step leaves: numpy
    constants when t0 is a Python int (as in ``generate_homes``), else traced."""
    xp = np if isinstance(t0, int) else jnp
    hours = t0 + xp.arange(steps)
    return hours % 24, context_of(hours, config.day_phases)


def sample_paths(home: dict, start, t0, u, config: HomesConfig) -> jnp.ndarray:
    """Receptacles (S, M) int32 at hours t0 + 1 … t0 + S of every object of one home.

    home: one home's fields; start: (M,) receptacles at hour t0 (−1 masked); u: (S, M)
    uniforms in [0, 1). Exactly the chain P_t of :mod:`.schedules`.
    """
    steps = u.shape[0]
    hour, context = _hours(t0, steps, config)
    regime, cycle = home["regime"], home["cycle"]
    n = jnp.maximum(home["num_allowed"], 1)
    rho = jnp.asarray([config.preference_move, config.balanced_move, config.frequent_move, 1.0],
                      jnp.float32)[regime]
    m = jnp.asarray(np.asarray(config.activity, np.float32))[hour][:, None] * rho  # (S, M)
    moved = u < m
    position = _cycle_position(cycle, start)  # (M,) where each object starts on its cycle
    positions = {}
    used = config.regimes_used
    if PREFERENCES in used:  # where the last move went (the favourite if u < m·mass)
        mass = jnp.where(n > 1, config.preference_mass, 1.0)
        fav = jnp.take(_cycle_position(cycle[:, None, :], home["favourite"]), context,
                       axis=1).T  # (S, M) cycle position of the context's favourite
        spare = m * (1.0 - mass)
        rest = jnp.minimum(jnp.floor((u - m * mass) / jnp.where(spare > 0, spare, 1.0)
                                     * (n - 1)).astype(jnp.int32), n - 2)
        target = jnp.where(u < m * mass, fav, jnp.mod(fav + 1 + rest, n))
        code = jnp.where(moved, jnp.arange(steps, dtype=jnp.int32)[:, None] * 64 + target, -1)
        code = jax.lax.cummax(code, axis=0)  # the latest move and its target
        positions[PREFERENCES] = jnp.where(code >= 0, code & 63, position)
    if BALANCED in used or ROUTINE in used:  # cumulative steps along the cycle
        step = jnp.zeros_like(moved, dtype=jnp.int32)
        if BALANCED in used:  # +1 if u < m·c, else one of the n − 1 others
            c = config.balanced_cycle
            spare = m * (1.0 - c)
            other = 1 + jnp.minimum(jnp.floor((u - m * c) / jnp.where(spare > 0, spare, 1.0)
                                              * (n - 1)).astype(jnp.int32), n - 2)
            step = jnp.where(moved, jnp.where(u < m * c, 1, other), 0)
        if ROUTINE in used:  # stay / advance one / advance two
            p0, p1, _ = config.routine_probs
            advance = (u >= p0).astype(jnp.int32) + (u >= p0 + p1).astype(jnp.int32)
            step = jnp.where(regime == ROUTINE, advance, step)
        positions[BALANCED] = positions[ROUTINE] = jnp.mod(
            position + jnp.cumsum(step, axis=0), n)
    out = None
    if positions:
        along = positions[next(iter(positions))]
        for index, value in positions.items():
            along = jnp.where(regime == index, value, along)
        out = jnp.take_along_axis(cycle, along.T, axis=1).T
    if FREQUENT in used:  # the move depends on where the object is: a scan
        allowed = home["object_allowed"]
        last = allowed.shape[-1] - 1 - jnp.argmax(allowed[:, ::-1], axis=-1)  # (M,)
        kernel = jax.vmap(lambda reg, cyc, num, al: schedules.move_kernel(
            reg, cyc, num, al, home["receptacle_distance"], config))(
                jnp.full_like(regime, FREQUENT), cycle, home["num_allowed"], allowed)
        cdf = jnp.cumsum(kernel, axis=-1)  # (M, R, R)
        v = jnp.where(u > 0, u, 2.0**-17) / jnp.where(m > 0, m, 1.0)  # the move's own uniform

        def hop(state, x):
            go, w = x
            row = jnp.take_along_axis(cdf, jnp.maximum(state, 0)[:, None, None], axis=1)[:, 0]
            nxt = jnp.where(go, _pick(row, w, last), state)
            return nxt, nxt

        hopped = jax.lax.scan(hop, start, (moved, v))[1]
        out = hopped if out is None else jnp.where(regime == FREQUENT, hopped, out)
    out = jnp.where(home["num_allowed"] <= 1, start, out)
    return jnp.where(home["object_valid"], out, -1).astype(jnp.int32)


def _one_home(home_key, config: HomesConfig) -> dict:
    home = _layout(home_key, config)
    t, m = config.num_hours, config.max_objects
    words = jax.random.bits(jax.random.fold_in(home_key, 1), (trajectory_words(config),),
                            jnp.uint32)
    u = _uniform16(words, t * m).reshape(t, m)
    n = home["num_allowed"]
    first = jnp.minimum(jnp.floor(u[0] * n).astype(jnp.int32), jnp.maximum(n - 1, 0))
    start = jnp.where(home["object_valid"],
                      jnp.take_along_axis(home["cycle"], first[:, None], axis=1)[:, 0], -1)
    later = sample_paths(home, start, 0, u[1:], config)
    home["receptacle"] = jnp.concatenate([start[None], later], axis=0)
    return home


@functools.partial(jax.jit, static_argnames=("config",))
def homes_from_keys(home_keys, config: HomesConfig) -> Homes:
    """Homes for one PRNG key per home (E,); home e depends on ``home_keys[e]`` only."""
    fields = jax.vmap(lambda k: _one_home(k, config))(home_keys)
    return Homes(**{name: fields[name].astype(FIELDS[name][1]) for name in FIELDS})


def homes_bytes_per_home(config: HomesConfig) -> int:
    """Bytes of one home's ``Homes`` arrays."""
    dims = sizes(config, 1)
    return sum(array_bytes(field_shape(f, dims), np.dtype(FIELDS[f][1])) for f in FIELDS)


def generate_homes(key, config: HomesConfig = DEFAULT_HOMES_CONFIG, num_homes: int = 1) -> Homes:
    """Generate ``num_homes`` homes with ``config.num_hours`` hourly trajectories; ValueError
    naming the argument on bad input or when they would not fit in memory."""
    key = check_key(key)
    check_instance("config", config, HomesConfig)
    num_homes = check_int("num_homes", num_homes)
    # the trajectories' working set: a few (T, M) float/int arrays per home besides the output
    per_home = homes_bytes_per_home(config) + 8 * config.num_hours * config.max_objects * 4
    check_request_size(f"generate_homes({num_homes} homes)", num_homes * per_home)
    rows = computed_rows(num_homes, per_home)
    return first_rows(homes_from_keys(jax.random.split(key, rows), config), num_homes)


@functools.partial(jax.jit, static_argnames=("steps", "num_chains", "config"))
def _simulate(key, home: Homes, object_index, tau, steps: int, num_chains: int,
              config: HomesConfig):
    fields = home.as_dict()  # that object alone (an M axis of 1): chains of it only
    for name, (symbols, _, _, _) in FIELDS.items():
        if "M" in symbols:
            axis = symbols.index("M") - 1
            fields[name] = jax.lax.dynamic_slice_in_dim(fields[name], object_index, 1, axis)
    start = fields["receptacle"][tau]

    def chain(k):
        u = _uniform16(jax.random.bits(k, (-(-steps // 2),), jnp.uint32), steps)
        return sample_paths(fields, start, tau, u[:, None], config)[-1, 0]

    return jax.vmap(chain)(jax.random.split(key, num_chains))


def simulate(key, home: Homes, object_index: int, tau: int, tau_q: int, num_chains: int,
             config: HomesConfig = DEFAULT_HOMES_CONFIG) -> jax.Array:
    """Monte-Carlo check of the posterior: (num_chains,) int32 receptacles of object
    ``object_index`` at hour ``tau_q`` of independent chains started where it is at ``tau``
    in ``home`` (one home, ``Homes.home(i)``), by the sampler ``generate_homes`` uses."""
    key = check_key(key)
    num_chains = check_int("num_chains", num_chains)
    check_instance("config", config, HomesConfig)
    t = config.num_hours
    tau = check_int("tau", tau, 0, t - 1)
    tau_q = check_int("tau_q", tau_q, tau + 1, t - 1)
    object_index = check_int("object_index", object_index, 0, config.max_objects - 1)
    validate_homes(home, config, batched=False, values=False)
    return _simulate(key, home, object_index, tau, tau_q - tau, num_chains, config)
