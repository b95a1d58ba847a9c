"""A home at hour τ as model inputs: scene tokens, query features and history features.

Tokens (one scene per home and map hour, ``config.max_tokens`` slots S): the rooms, then the
receptacle slots, then the object slots at τ, then padding. Each token has a 6-D box
(cx, cy, cz, w, d, h) normalised by the home's footprint (x and w by its width, y and d by its
depth) and by :data:`HEIGHT_SCALE` (z and h), a descriptor (an id into the one class vocabulary:
room types, then receptacle classes, then object classes, ``HomesConfig.descriptor_offsets``;
the model embeds it with a learned table), a kind (room, receptacle, object) and a mask (False
on unused slots). A room's box is lifted to 6-D: from the floor to :data:`ROOM_HEIGHT`. An
object's box at τ is ``object_boxes``': its class's size, centred on its receptacle's top.

Query features (…, :data:`QUERY_FEATURES`): hour of day and day of week of τ_q and of τ as
sines and cosines, a weekend flag of τ_q, and the horizon Δ = τ_q − τ in hours as log(1 + Δ)
scaled to [0, 1] with its sines and cosines at :data:`HORIZON_FREQUENCIES`.

History features (…, R, :data:`HISTORY_FEATURES`), per (query, receptacle slot), over the
``history`` hours τ − H + 1 … τ (hours before 0 left out): see :data:`HISTORY_FEATURES`. The
cycle features read ``Homes.cycle``, the object's allowed receptacles clockwise around the home's
centre: a function of the map's geometry (``furnish.cycles``), not of the hidden law.

Everything here is jittable and vmapped over homes and queries; :func:`home_tokens` and
:func:`history_features` check their arguments (``ValueError`` naming them), the ``_``
functions and the batch builders do not.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from flowmaps_jax.flowsim.homes.config import HomesConfig, context_of
from flowmaps_jax.flowsim.homes.queries import HomesQueries, check_queries
from flowmaps_jax.flowsim.homes.world import Homes, object_boxes, validate_homes
from flowmaps_jax.validation import (
    check_instance,
    check_int,
    check_int_array,
    check_mask,
    prefix_errors,
)

HEIGHT_SCALE = 2.5
"""Metres: token z and h are divided by this (the footprint scales x, y, w, d)."""
ROOM_HEIGHT = 2.5
"""Metres: a room's 6-D box runs from the floor to this height."""
DISTANCE_SCALE = 10.0
"""Metres: geodesic distances are divided by this."""
DEFAULT_HISTORY = 168
"""Hours of history the features read by default (a week)."""
ROOM, RECEPTACLE, OBJECT = 0, 1, 2
"""Token kinds."""
HORIZON_FREQUENCIES = (1.0, 2.0, 4.0, 8.0)
"""Angular frequencies (× π) of the horizon's log-scaled features."""
QUERY_FEATURES = 9 + 2 * len(HORIZON_FREQUENCIES) + 1
HISTORY_FEATURES = ("occupancy", "context_occupancy", "at_tau", "distance", "near",
                    "allowed", "cycle_0", "cycle_1", "cycle_2", "cycle_back", "cycle_fraction",
                    "arrivals", "context_arrivals", "inverse_allowed", "move_rate",
                    "step_1_rate", "step_2_rate", "coverage",
                    "context_arrival_count", "context_hour_count", "earlier_arrival_count",
                    "earlier_hour_count", "next_arrival_count", "next_hour_count",
                    "same_hour_occupancy", "unseen_at_tau", "hours_since_seen", "never_seen")
"""Per (query, receptacle r): fraction of the window's hours the object stood on r; the same
over the window's hours with the preference context of τ_q (``context_of``); whether it stands
on r at τ; the geodesic distance from its receptacle at τ to r / :data:`DISTANCE_SCALE`, and
exp(−distance / ``config.frequent_length``); whether r is allowed; whether r is 0, 1, 2 or
n − 1 places on along the object's cycle from its receptacle at τ, and that offset / n; the
fraction of the window's moves that ended on r, and of those in τ_q's context; then, the same
for every r of a query: 1 / n (n allowed receptacles), the fraction of the window's hour steps
that moved, that advanced one and two places along the cycle, and the fraction of the window
inside the rollout; then counts, log(1 + count) / :data:`COUNT_SCALE`, of the window's moves
that ended on r and of its hours on r, within the context of τ_q, of τ_q − 6 h and of τ + 1 h;
and the fraction of the window's days on which the object stood on r at τ_q's hour of day.
Zero off the allowed receptacles (except ``allowed``). Counts, unlike fractions, say how much
evidence there is: a posterior over a context's favourite place sharpens with every arrival.
Models before these counts read the first :data:`BASE_HISTORY_FEATURES` only.

Partial observation (recorded worlds: ``observed`` (E, T, M), False where the object was not
seen): the window's features count only the hours the object was seen, ``Homes.receptacle``
holds where it was last seen (its receptacle at τ too), and the last three say whether it was
unseen at τ, the hours since it was last seen, log(1 + hours) / log(1 + ``num_hours``) (the
hours since −1 when never), and whether it was never seen up to τ. All three are 0 when every
hour is observed (FlowSim homes). Models before them read the first
:data:`COUNT_HISTORY_FEATURES` (``HomesModelConfig.history_observed``)."""
BASE_HISTORY_FEATURES = 18
"""The history features of models without ``history_counts`` (the first 18)."""
COUNT_HISTORY_FEATURES = 25
"""The history features of models with ``history_counts`` but without ``history_observed``."""
COUNT_SCALE = 4.0
"""log(1 + count) is divided by this (about 1 at 50 hours)."""


@struct.dataclass
class HomeTokens:
    """Scene tokens (…, S): boxes (…, S, 6) normalised, descriptor, kind (…, S) int32, mask
    (…, S) bool."""

    boxes: jax.Array
    descriptor: jax.Array
    kind: jax.Array
    mask: jax.Array


def token_layout(config: HomesConfig) -> tuple[int, int, int]:
    """(first receptacle token, first object token, S): rooms sit at 0 … NR − 1."""
    first_receptacle = config.num_rooms
    return first_receptacle, first_receptacle + config.max_receptacles, config.max_tokens


def _scale(home_size):
    """(E, 6) divisors of (cx, cy, cz, w, d, h)."""
    h = jnp.full_like(home_size[:, :1], HEIGHT_SCALE)
    return jnp.concatenate([home_size, h, home_size, h], axis=-1)


def normalise_boxes(boxes, home_size):
    """Boxes (E, …, 6) in metres → normalised (footprint and :data:`HEIGHT_SCALE`)."""
    scale = _scale(home_size).reshape(home_size.shape[0], *([1] * (boxes.ndim - 2)), 6)
    return boxes / scale


def denormalise_boxes(boxes, home_size):
    """Inverse of :func:`normalise_boxes`."""
    scale = _scale(home_size).reshape(home_size.shape[0], *([1] * (boxes.ndim - 2)), 6)
    return boxes * scale


def _tokens(homes: Homes, tau, config: HomesConfig) -> HomeTokens:
    """Tokens (E, K, S) of every home at the hours ``tau`` (E, K). Unchecked; jittable."""
    e, k = tau.shape
    room = homes.room_box
    rooms = jnp.stack([(room[..., 0] + room[..., 2]) / 2, (room[..., 1] + room[..., 3]) / 2,
                       jnp.full_like(room[..., 0], ROOM_HEIGHT / 2), room[..., 2] - room[..., 0],
                       room[..., 3] - room[..., 1], jnp.full_like(room[..., 0], ROOM_HEIGHT)],
                      axis=-1)  # (E, NR, 6)
    objects = jax.vmap(lambda hour: object_boxes(homes, hour, config), in_axes=1,
                       out_axes=1)(tau)  # (E, K, M, 6)
    fixed = jnp.concatenate([rooms, homes.receptacle_box], axis=1)  # (E, NR + R, 6)
    boxes = jnp.concatenate([jnp.broadcast_to(fixed[:, None], (e, k, *fixed.shape[1:])),
                             objects], axis=2)
    _, rec_off, obj_off = config.descriptor_offsets
    descriptor = jnp.concatenate([
        homes.room_type, jnp.where(homes.receptacle_valid, homes.receptacle_class + rec_off, 0),
        jnp.where(homes.object_valid, homes.object_class + obj_off, 0)], axis=1)
    kind = jnp.concatenate([jnp.full(homes.room_type.shape, ROOM),
                            jnp.full(homes.receptacle_class.shape, RECEPTACLE),
                            jnp.full(homes.object_class.shape, OBJECT)], axis=1)
    mask = jnp.concatenate([jnp.ones(homes.room_type.shape, bool), homes.receptacle_valid,
                            homes.object_valid], axis=1)
    pad = config.max_tokens - boxes.shape[2]
    boxes = jnp.pad(normalise_boxes(boxes, homes.home_size), ((0, 0), (0, 0), (0, pad), (0, 0)))
    flat = [jnp.broadcast_to(jnp.pad(a, ((0, 0), (0, pad)))[:, None], (e, k, config.max_tokens))
            for a in (descriptor, kind, mask)]
    return HomeTokens(boxes=boxes.astype(jnp.float32), descriptor=flat[0].astype(jnp.int32),
                      kind=flat[1].astype(jnp.int32), mask=flat[2].astype(bool))


def home_tokens(homes: Homes, tau, config: HomesConfig) -> HomeTokens:
    """Tokens of every home at hour ``tau``: (E,) ints → (E, S); (E, K) → (E, K, S)."""
    check_instance("config", config, HomesConfig)
    tau = check_int_array("tau", tau, 0, config.num_hours - 1)
    with prefix_errors("config."):
        config.validate()  # its token budget too, should it have skipped its own checks
    validate_homes(homes, config, values=False)
    e = homes.num_homes
    if tau.ndim not in (1, 2) or tau.shape[0] != e:
        raise ValueError(f"tau must have shape (E={e},) or (E, K); got {tau.shape}")
    out = _tokens(homes, jnp.asarray(tau, jnp.int32).reshape(e, -1), config)
    return jax.tree.map(lambda a: a[:, 0], out) if tau.ndim == 1 else out


def _cyclic(hours, period):
    angle = 2 * jnp.pi * hours / period
    return [jnp.sin(angle), jnp.cos(angle)]


def _query_features(tau, tau_q, config: HomesConfig):
    """(…, QUERY_FEATURES) float32 of queries with map hours ``tau`` and query hours ``tau_q``."""
    tau, tau_q = jnp.asarray(tau), jnp.asarray(tau_q)
    scaled = jnp.log1p((tau_q - tau).astype(jnp.float32)) / jnp.log1p(float(config.num_hours))
    waves = scaled[..., None] * jnp.pi * jnp.asarray(HORIZON_FREQUENCIES, jnp.float32)
    parts = [*_cyclic(tau_q % 24, 24.0), *_cyclic((tau_q // 24) % 7, 7.0),
             *_cyclic(tau % 24, 24.0), *_cyclic((tau // 24) % 7, 7.0),
             ((tau_q // 24) % 7 >= 5).astype(jnp.float32), scaled]
    out = jnp.concatenate([jnp.stack(parts, -1), jnp.sin(waves), jnp.cos(waves)], axis=-1)
    return out.astype(jnp.float32)


def _per_query(homes: Homes, queries: HomesQueries, history: int):
    """The object's receptacles over the window (E, Q, H), which hours are in the rollout, and
    its receptacle at τ (E, Q)."""
    hours = queries.tau[..., None] - history + 1 + jnp.arange(history)  # (E, Q, H)
    inside = hours >= 0

    def one(traj, hh, obj, tau):
        return traj[jnp.maximum(hh, 0), obj[:, None]], traj[tau, obj]

    window, current = jax.vmap(one)(homes.receptacle, hours, queries.object_index, queries.tau)
    return window, hours, inside, current


def _last_seen(observed, queries: HomesQueries):
    """(E, Q) int32: the last hour <= τ at which each queried object was seen (−1: never)."""
    def one(obs, obj, tau):  # obs (T, M); obj, tau (Q,)
        t = jnp.arange(obs.shape[0])
        seen = obs[:, obj].T & (t <= tau[:, None])  # (Q, T)
        return jnp.max(jnp.where(seen, t, -1), axis=-1)

    return jax.vmap(one)(observed, queries.object_index, queries.tau).astype(jnp.int32)


def _history_features(homes: Homes, queries: HomesQueries, config: HomesConfig,
                      history: int, observed=None):
    """(E, Q, R, len(HISTORY_FEATURES)) float32; see :data:`HISTORY_FEATURES`. ``observed``
    (E, T, M) bool, None: every hour. Unchecked."""
    r = config.max_receptacles
    window, hours, inside, current = _per_query(homes, queries, history)
    if observed is not None:  # only the hours the object was seen count
        seen = jax.vmap(lambda obs, hh, obj: obs[jnp.maximum(hh, 0), obj[:, None]])(
            observed, hours, queries.object_index)  # (E, Q, H)
        inside = inside & seen
    slots = jnp.arange(r)
    on = (window[..., None] == slots) & inside[..., None]  # (E, Q, H, R)
    fraction = lambda num, den: num / jnp.maximum(den, 1.0)[..., None]  # noqa: E731
    same = inside & (context_of(jnp.maximum(hours, 0)) == context_of(queries.tau_q)[..., None])
    occupancy = fraction(on.sum(2), inside.sum(-1))
    context_occupancy = fraction((on & same[..., None]).sum(2), same.sum(-1))
    pair = inside[..., 1:] & inside[..., :-1]  # hour steps inside the window
    moved = pair & (window[..., 1:] != window[..., :-1])
    arrive = moved[..., None] & on[..., 1:, :]
    moved_same = moved & same[..., :-1]  # the move's hour (t of t → t + 1) in τ_q's context
    arrivals = fraction(arrive.sum(2), moved.sum(-1))
    context_arrivals = fraction((arrive & same[..., :-1, None]).sum(2), moved_same.sum(-1))

    def per_home(cycle, allowed, num, dist, obj, cur):
        return cycle[obj], allowed[obj], num[obj], dist[cur]

    cycle, allowed, num, dist = jax.vmap(per_home)(
        homes.cycle, homes.object_allowed, homes.num_allowed, homes.receptacle_distance,
        queries.object_index, current)  # (E, Q, R), (E, Q, R), (E, Q), (E, Q, R)
    n = jnp.maximum(num, 1)[..., None]
    position = jnp.argmax(cycle[..., None, :] == slots[:, None], axis=-1)  # (E, Q, R)
    here = jnp.take_along_axis(position, current[..., None], axis=-1)
    offset = jnp.mod(position - here, n)  # places along the cycle from the object's receptacle
    along = jnp.take_along_axis(position, jnp.maximum(window, 0), axis=-1)  # (E, Q, H)
    step = jnp.mod(along[..., 1:] - along[..., :-1], n)
    steps = jnp.maximum(pair.sum(-1), 1)
    per_query = jnp.stack([1.0 / n[..., 0], moved.sum(-1) / steps,
                           (pair & (step == 1)).sum(-1) / steps,
                           (pair & (step == 2)).sum(-1) / steps,
                           inside.sum(-1) / history], axis=-1)  # (E, Q, 5)
    per_slot = jnp.stack([
        occupancy, context_occupancy, (slots == current[..., None]).astype(jnp.float32),
        dist / DISTANCE_SCALE, jnp.exp(-dist / config.frequent_length),
        allowed.astype(jnp.float32), offset == 0, offset == 1, offset == 2, offset == n - 1,
        offset / n, arrivals, context_arrivals], axis=-1).astype(jnp.float32)
    def counts(hour):  # moves ending on r and hours on r, in the context of ``hour`` (E, Q)
        ctx = inside & (context_of(jnp.maximum(hours, 0)) == context_of(hour)[..., None])
        return [jnp.log1p((arrive & ctx[..., :-1, None]).sum(2)) / COUNT_SCALE,
                jnp.log1p((on & ctx[..., None]).sum(2)) / COUNT_SCALE]

    same_hour = inside & (jnp.mod(hours, 24) == jnp.mod(queries.tau_q, 24)[..., None])
    extra = jnp.stack([*counts(queries.tau_q), *counts(queries.tau_q - 6),
                       *counts(queries.tau + 1),
                       fraction((on & same_hour[..., None]).sum(2), same_hour.sum(-1))],
                      axis=-1).astype(jnp.float32)
    if observed is None:
        unseen = jnp.zeros((*per_slot.shape[:-1], 3), jnp.float32)
    else:
        last = _last_seen(observed, queries)  # (E, Q)
        ago = jnp.log1p((queries.tau - last).astype(jnp.float32)) / jnp.log1p(
            float(config.num_hours))
        unseen = jnp.stack([last != queries.tau, ago, last < 0], axis=-1).astype(jnp.float32)
        unseen = jnp.broadcast_to(unseen[..., None, :], (*per_slot.shape[:-1], 3))
    extra = jnp.concatenate([extra, unseen], axis=-1)
    out = jnp.concatenate([per_slot, jnp.broadcast_to(per_query[..., None, :],
                                                      (*per_slot.shape[:-1], 5)), extra],
                          axis=-1)
    keep = allowed[..., None] | (jnp.arange(out.shape[-1]) == HISTORY_FEATURES.index("allowed"))
    return jnp.where(keep, out, 0.0)


def history_features(homes: Homes, queries: HomesQueries, config: HomesConfig,
                     history: int = DEFAULT_HISTORY, observed=None) -> jax.Array:
    """(E, Q, R, len(HISTORY_FEATURES)) float32 history features of every query (see
    :data:`HISTORY_FEATURES`), over the ``history`` hours up to each query's τ; ``observed``
    (E, T, M) bool: the hours each object was seen (None: every hour)."""
    check_instance("config", config, HomesConfig)
    history = check_int("history", history, 1, config.num_hours)
    with prefix_errors("config."):
        config.validate()  # its token budget too, should it have skipped its own checks
    validate_homes(homes, config, values=False)
    check_queries(queries, homes, config)
    if observed is not None:
        observed = check_mask("observed", observed, tuple(homes.receptacle.shape))
    return _history_features(homes, queries, config, history, observed)


@struct.dataclass
class HomesBatch:
    """What the homes model reads for B scenes with Q queries each.

    tokens (B, S); object_token (B, Q) int32, the queried object's token index; query
    (B, Q, QUERY_FEATURES); history (B, Q, R, len(HISTORY_FEATURES)); allowed (B, Q, R) bool;
    current (B, Q) int32 its receptacle at τ; target (B, Q) int32 its receptacle at τ_q;
    target_box (B, Q, 6) its normalised box at τ_q.
    """

    tokens: HomeTokens
    object_token: jax.Array
    query: jax.Array
    history: jax.Array
    allowed: jax.Array
    current: jax.Array
    target: jax.Array
    target_box: jax.Array


def _targets(homes: Homes, queries: HomesQueries, config: HomesConfig):
    """Receptacle (E, Q) and normalised box (E, Q, 6) of each queried object at τ_q."""
    boxes = jax.vmap(lambda hour: object_boxes(homes, hour, config), in_axes=1,
                     out_axes=1)(queries.tau_q)  # (E, Q, M, 6)
    box = jnp.take_along_axis(boxes, queries.object_index[..., None, None], axis=2)[:, :, 0]

    def where(traj, tq, obj):
        return traj[tq, obj]

    target = jax.vmap(where)(homes.receptacle, queries.tau_q, queries.object_index)
    return target, normalise_boxes(box, homes.home_size)


def _parts(homes: Homes, queries: HomesQueries, config: HomesConfig, history: int,
           observed=None) -> dict:
    _, first_object, _ = token_layout(config)
    allowed = jax.vmap(lambda a, o: a[o])(homes.object_allowed, queries.object_index)
    target, box = _targets(homes, queries, config)
    current = jax.vmap(lambda traj, t, o: traj[t, o])(homes.receptacle, queries.tau,
                                                      queries.object_index)
    return {"object_token": (first_object + queries.object_index).astype(jnp.int32),
            "query": _query_features(queries.tau, queries.tau_q, config),
            "history": _history_features(homes, queries, config, history, observed),
            "allowed": allowed, "current": current.astype(jnp.int32),
            "target": target.astype(jnp.int32), "target_box": box}


def shared_tau_batch(homes: Homes, queries: HomesQueries, config: HomesConfig,
                     history: int, observed=None) -> HomesBatch:
    """One scene per home (B = E) at the map hour ``queries.tau[:, 0]``, which all the home's
    queries must share (training); ``observed`` (E, T, M): the hours each object was seen
    (None: every hour). Unchecked; jittable."""
    tokens = jax.tree.map(lambda a: a[:, 0], _tokens(homes, queries.tau[:, :1], config))
    return HomesBatch(tokens=tokens, **_parts(homes, queries, config, history, observed))


def per_query_batch(homes: Homes, queries: HomesQueries, config: HomesConfig,
                    history: int, observed=None) -> HomesBatch:
    """One scene per query (B = E·Q, one query each), each home at its own query's τ
    (inference: any queries). Unchecked; jittable."""
    e, q = queries.tau.shape
    tokens = jax.tree.map(lambda a: a.reshape(e * q, *a.shape[2:]),
                          _tokens(homes, queries.tau, config))
    parts = {k: v.reshape(e * q, 1, *v.shape[2:])
             for k, v in _parts(homes, queries, config, history, observed).items()}
    return HomesBatch(tokens=tokens, **parts)
