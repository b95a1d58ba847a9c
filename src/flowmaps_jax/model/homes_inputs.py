"""What the homes network reads: a home's layout as tokens, a query's times and the queried
object's observation history. Only what any log has; nothing here imports a simulator.

* **Tokens** (one scene per home and map hour, ``config.max_tokens`` slots S): the rooms, the
  receptacle slots, the object slots at τ, then padding. Each token has a 6-D box
  (cx, cy, cz, w, d, h) normalised by the home's footprint (x and w by its width, y and d by its
  depth) and by :data:`HEIGHT_SCALE` (z and h), a descriptor (an id into the class vocabulary:
  room types, receptacle classes, object classes, ``config.descriptor_offsets``), a kind (room,
  receptacle, object) and a mask. A room's box runs from the floor to :data:`ROOM_HEIGHT`; an
  object's box at τ is its class's size centred on the top of the receptacle it was last seen on.
* **Query features** (…, :data:`QUERY_FEATURES`): :func:`periodic` of τ_q and of τ, and the
  horizon Δ = τ_q − τ as log(1 + Δ) / log(1 + T) with its sines and cosines at
  :data:`HORIZON_FREQUENCIES`.
* **Events** (…, H) int32: the receptacle the object was seen on at each hour τ − H + 1 … τ, −1
  where it was not observed (or before hour 0). The network embeds each event's hour of day, day
  of week and age and attends over them (``model.homes_family``): the rhythms are learned.
* **Row features** (…, R, :data:`ROW_FEATURES`): statistics of the observed history, per
  (query, receptacle r), zero off the object's allowed receptacles (except ``allowed``); with
  ``negative`` (a model's ``negative_evidence``), :data:`NEGATIVE_FEATURES` after them, from
  ``not_at`` (E, T, M, R) bool ("looked for on r at hour t, not there"; None: no such looks).

Hour t counts from the log's hour 0; hour of day t mod 24, day of week ⌊t / 24⌋ mod 7. Partial
observation: ``observed`` (E, T, M) bool, None for every hour; ``homes.receptacle`` holds where
each object was last seen. Everything is jittable and unchecked (the Predictor checks).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

HEIGHT_SCALE = 2.5
"""Metres: token z and h are divided by this (the footprint scales x, y, w, d)."""
ROOM_HEIGHT = 2.5
"""Metres: a room's 6-D box runs from the floor to this height."""
DISTANCE_SCALE = 10.0
"""Metres: walking distances are divided by this."""
DEFAULT_HISTORY = 168
"""Hours of history the network reads by default (a week)."""
ROOM, RECEPTACLE, OBJECT = 0, 1, 2
"""Token kinds."""
HOUR_HARMONICS, WEEK_HARMONICS = 6, 3
"""Harmonics of the hour of day and of the day of week in :func:`periodic`."""
PERIODIC_FEATURES = 2 * (HOUR_HARMONICS + WEEK_HARMONICS)
HORIZON_FREQUENCIES = (1.0, 2.0, 4.0, 8.0)
"""Angular frequencies (× π) of the horizon's log-scaled features."""
QUERY_FEATURES = 2 * PERIODIC_FEATURES + 1 + 2 * len(HORIZON_FREQUENCIES)
ROW_FEATURES = ("last_seen", "distance", "allowed", "occupancy", "one_step", "pushed",
                "pushed_log", "inverse_allowed", "coverage", "moves", "unseen_at_tau",
                "hours_since_seen", "never_seen")
"""Per (query, receptacle r): r is where the object was last seen (up to τ); the walking
distance from there / :data:`DISTANCE_SCALE`; r is allowed; the fraction of the window's
observed hours on r; the empirical hourly chain P̂ (counts of consecutive observed hours,
plus :data:`STAY_PRIOR` on staying) from the last-seen receptacle to r in one step, and
pushed over the hours from the last sighting to τ_q (with its log, scaled); then per query: 1 / n
(n allowed receptacles), the fraction of the window observed, the fraction of its consecutive
observed hour pairs that moved, unseen at τ, log(1 + hours since last seen) / log(1 + T) (the
hours since −1 when never) and never seen up to τ."""
NEGATIVE_FEATURES = ("ruled_out_since_seen", "ruled_out_recency")
"""Per (query, receptacle r), over the history window up to τ: r was ruled out after the
object's last sighting (any time, when never seen); 1 − log(1 + τ − t_r) / log(1 + H) for the
last hour t_r it was ruled out on r, 0 when it was not."""
STAY_PRIOR = 0.5
"""Pseudo-count on staying in every row of the empirical hourly chain."""
LOG_FLOOR = 1e-3


@struct.dataclass
class HomeTokens:
    """Scene tokens (…, S): boxes (…, S, 6) normalised, descriptor, kind (…, S) int32, mask
    (…, S) bool."""

    boxes: jax.Array
    descriptor: jax.Array
    kind: jax.Array
    mask: jax.Array


@struct.dataclass
class HomesBatch:
    """What the homes network reads for B scenes with Q queries each.

    tokens (B, S); object_token (B, Q) int32, the queried object's token; tau, tau_q (B, Q)
    int32; query (B, Q, QUERY_FEATURES); events (B, Q, H) int32; rows (B, Q, R, ROW_FEATURES);
    allowed (B, Q, R) bool; current (B, Q) int32 the receptacle it was last seen on; target
    (B, Q) int32 its receptacle at τ_q; target_box (B, Q, 6) its normalised box at τ_q.
    """

    tokens: HomeTokens
    object_token: jax.Array
    tau: jax.Array
    tau_q: jax.Array
    query: jax.Array
    events: jax.Array
    rows: jax.Array
    allowed: jax.Array
    current: jax.Array
    target: jax.Array
    target_box: jax.Array


def token_layout(config) -> tuple[int, int, int]:
    """(first receptacle token, first object token, S): rooms sit at 0 … NR − 1."""
    first_receptacle = config.num_rooms
    return first_receptacle, first_receptacle + config.max_receptacles, config.max_tokens


def _scale(home_size):
    """(E, 6) divisors of (cx, cy, cz, w, d, h)."""
    h = jnp.full_like(home_size[:, :1], HEIGHT_SCALE)
    return jnp.concatenate([home_size, h, home_size, h], axis=-1)


def normalise_boxes(boxes, home_size):
    """Boxes (E, …, 6) in metres → normalised (footprint and :data:`HEIGHT_SCALE`)."""
    return boxes / _scale(home_size).reshape(home_size.shape[0], *([1] * (boxes.ndim - 2)), 6)


def denormalise_boxes(boxes, home_size):
    """Inverse of :func:`normalise_boxes`."""
    return boxes * _scale(home_size).reshape(home_size.shape[0], *([1] * (boxes.ndim - 2)), 6)


def object_boxes(homes, hour, config):
    """(E, M, 6) object boxes in metres at ``hour`` (E,): the class's size centred on the top
    of its receptacle; 0 for masked objects."""
    where = jnp.take_along_axis(homes.receptacle, hour[:, None, None], axis=1)[:, 0]  # (E, M)
    under = jnp.take_along_axis(homes.receptacle_box, jnp.maximum(where, 0)[..., None], axis=1)
    size = jnp.asarray([o.size for o in config.object_classes], jnp.float32)[
        jnp.maximum(homes.object_class, 0)]  # (E, M, 3)
    centre = jnp.stack([under[..., 0], under[..., 1], under[..., 5] + size[..., 2] / 2], -1)
    return jnp.where(homes.object_valid[..., None], jnp.concatenate([centre, size], -1), 0.0)


def scene_tokens(homes, tau, config) -> HomeTokens:
    """Tokens (E, K, S) of every home at the hours ``tau`` (E, K)."""
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


def periodic(hours) -> jax.Array:
    """(…, PERIODIC_FEATURES) float32: sines and cosines of the hour of day (harmonics
    1 … :data:`HOUR_HARMONICS`) and of the day of week (1 … :data:`WEEK_HARMONICS`)."""
    hours = jnp.asarray(hours)
    day = 2 * jnp.pi * (hours % 24).astype(jnp.float32)[..., None] / 24.0
    week = 2 * jnp.pi * ((hours // 24) % 7).astype(jnp.float32)[..., None] / 7.0
    day = day * jnp.arange(1, HOUR_HARMONICS + 1)
    week = week * jnp.arange(1, WEEK_HARMONICS + 1)
    return jnp.concatenate([jnp.sin(day), jnp.cos(day), jnp.sin(week), jnp.cos(week)], -1)


def query_features(tau, tau_q, num_hours: int) -> jax.Array:
    """(…, QUERY_FEATURES) float32 of queries with map hours ``tau`` and query hours ``tau_q``."""
    tau, tau_q = jnp.asarray(tau), jnp.asarray(tau_q)
    scaled = jnp.log1p((tau_q - tau).astype(jnp.float32)) / jnp.log1p(float(num_hours))
    waves = scaled[..., None] * jnp.pi * jnp.asarray(HORIZON_FREQUENCIES, jnp.float32)
    return jnp.concatenate([periodic(tau_q), periodic(tau), scaled[..., None], jnp.sin(waves),
                            jnp.cos(waves)], axis=-1).astype(jnp.float32)


def history_events(homes, queries, history: int, observed=None) -> jax.Array:
    """(E, Q, H) int32: the queried object's receptacle at hours τ − H + 1 … τ, −1 where it was
    not observed or the hour is before 0."""
    hours = queries.tau[..., None] - history + 1 + jnp.arange(history)  # (E, Q, H)
    obs = (jnp.ones(homes.receptacle.shape, bool) if observed is None else observed)

    def one(traj, seen, hh, obj):
        at = jnp.maximum(hh, 0), obj[:, None]
        return jnp.where((hh >= 0) & seen[at], traj[at], -1)

    return jax.vmap(one)(homes.receptacle, obs, hours, queries.object_index).astype(jnp.int32)


def _last_seen(observed, queries):
    """(E, Q) int32: the last hour <= τ at which each queried object was seen (−1: never)."""
    def one(obs, obj, tau):  # obs (T, M); obj, tau (Q,)
        t = jnp.arange(obs.shape[0])
        return jnp.max(jnp.where(obs[:, obj].T & (t <= tau[:, None]), t, -1), axis=-1)

    return jax.vmap(one)(observed, queries.object_index, queries.tau).astype(jnp.int32)


def _pushed(chain, start, steps, bits: int):
    """start (…, R) pushed ``steps`` (…) hours through ``chain`` (…, R, R): binary powers."""
    def body(carry, bit):
        v, m = carry
        take = ((steps >> bit) & 1)[..., None] == 1
        return (jnp.where(take, jnp.einsum("...i,...ij->...j", v, m), v), m @ m), None

    (v, _), _ = jax.lax.scan(body, (start, chain), jnp.arange(bits))
    return v


def row_features(homes, queries, config, events, observed=None) -> jax.Array:
    """(E, Q, R, len(ROW_FEATURES)) float32 (see :data:`ROW_FEATURES`) from ``events``
    (:func:`history_events`)."""
    r, t = config.max_receptacles, config.num_hours
    allowed = jax.vmap(lambda a, o: a[o])(homes.object_allowed, queries.object_index)
    current = jax.vmap(lambda traj, tau, o: traj[tau, o])(homes.receptacle, queries.tau,
                                                          queries.object_index)
    last = queries.tau if observed is None else _last_seen(observed, queries)
    seen = events >= 0
    on = jax.nn.one_hot(events, r, dtype=jnp.float32)  # (E, Q, H, R); zero where unseen
    pair = seen[..., 1:] & seen[..., :-1]
    counts = jnp.einsum("...hi,...hj->...ij", on[..., :-1, :] * pair[..., None], on[..., 1:, :])
    eye = jnp.eye(r, dtype=jnp.float32) * allowed[..., None, :]
    counts = (counts + STAY_PRIOR * eye) * allowed[..., :, None] * allowed[..., None, :]
    chain = counts / jnp.maximum(counts.sum(-1, keepdims=True), 1e-9)
    here = jax.nn.one_hot(current, r, dtype=jnp.float32) * (last >= 0)[..., None]
    one_step = jnp.einsum("...i,...ij->...j", here, chain)
    steps = queries.tau_q - jnp.where(last >= 0, last, queries.tau)
    pushed = _pushed(chain, here, steps, max(1, int(t).bit_length()))
    dist = jax.vmap(lambda d, c: d[c])(homes.receptacle_distance, current)  # (E, Q, R)
    n = jnp.maximum(allowed.sum(-1), 1).astype(jnp.float32)
    observed_hours = seen.sum(-1).astype(jnp.float32)
    ago = jnp.log1p((queries.tau - last).astype(jnp.float32)) / jnp.log1p(float(t))
    per_slot = [here, dist / DISTANCE_SCALE, allowed.astype(jnp.float32),
                on.sum(-2) / jnp.maximum(observed_hours, 1.0)[..., None], one_step, pushed,
                jnp.log(pushed + LOG_FLOOR) / -jnp.log(LOG_FLOOR)]
    per_query = [1.0 / n, observed_hours / events.shape[-1],
                 (pair & (events[..., 1:] != events[..., :-1])).sum(-1)
                 / jnp.maximum(pair.sum(-1), 1), (last != queries.tau).astype(jnp.float32), ago,
                 (last < 0).astype(jnp.float32)]
    out = jnp.stack([*per_slot, *(jnp.broadcast_to(f[..., None].astype(jnp.float32),
                                                   allowed.shape) for f in per_query)], -1)
    keep = allowed[..., None] | (jnp.arange(out.shape[-1]) == ROW_FEATURES.index("allowed"))
    return jnp.where(keep, out, 0.0).astype(jnp.float32)


def negative_features(not_at, queries, history: int, observed=None, allowed=None):
    """(E, Q, R, len(NEGATIVE_FEATURES)) float32 (see :data:`NEGATIVE_FEATURES`) from
    ``not_at`` (E, T, M, R) bool; zero off ``allowed`` (E, Q, R)."""
    hours = queries.tau[..., None] - history + 1 + jnp.arange(history)  # (E, Q, H)
    out = jax.vmap(lambda na, hh, obj: na[jnp.maximum(hh, 0), obj[:, None]] & (hh >= 0)[
        ..., None])(not_at, hours, queries.object_index)  # (E, Q, H, R)
    latest = jnp.max(jnp.where(out, hours[..., None], -1), axis=-2)  # (E, Q, R)
    last = queries.tau if observed is None else _last_seen(observed, queries)
    recency = 1.0 - jnp.log1p((queries.tau[..., None] - latest).astype(jnp.float32)) / \
        jnp.log1p(float(history))
    feats = jnp.stack([latest > last[..., None], jnp.where(latest >= 0, recency, 0.0)], -1)
    return feats.astype(jnp.float32) * (1.0 if allowed is None else allowed[..., None])


def _parts(homes, queries, config, history: int, observed=None, not_at=None,
           negative: bool = False) -> dict:
    _, first_object, _ = token_layout(config)
    allowed = jax.vmap(lambda a, o: a[o])(homes.object_allowed, queries.object_index)
    boxes = jax.vmap(lambda hour: object_boxes(homes, hour, config), in_axes=1,
                     out_axes=1)(queries.tau_q)  # (E, Q, M, 6)
    box = jnp.take_along_axis(boxes, queries.object_index[..., None, None], axis=2)[:, :, 0]
    at = jax.vmap(lambda traj, t, o: traj[t, o])
    events = history_events(homes, queries, history, observed)
    rows = row_features(homes, queries, config, events, observed)
    if negative:
        extra = (jnp.zeros((*rows.shape[:-1], len(NEGATIVE_FEATURES))) if not_at is None else
                 negative_features(not_at, queries, history, observed, allowed))
        rows = jnp.concatenate([rows, extra.astype(jnp.float32)], -1)
    return {"object_token": (first_object + queries.object_index).astype(jnp.int32),
            "tau": queries.tau.astype(jnp.int32), "tau_q": queries.tau_q.astype(jnp.int32),
            "query": query_features(queries.tau, queries.tau_q, config.num_hours),
            "events": events, "rows": rows,
            "allowed": allowed,
            "current": at(homes.receptacle, queries.tau, queries.object_index).astype(jnp.int32),
            "target": at(homes.receptacle, queries.tau_q, queries.object_index).astype(jnp.int32),
            "target_box": normalise_boxes(box, homes.home_size)}


def shared_tau_batch(homes, queries, config, history: int, observed=None, not_at=None,
                     negative: bool = False) -> HomesBatch:
    """One scene per home (B = E) at the map hour ``queries.tau[:, 0]``, which all the home's
    queries share (training)."""
    tokens = jax.tree.map(lambda a: a[:, 0], scene_tokens(homes, queries.tau[:, :1], config))
    return HomesBatch(tokens=tokens, **_parts(homes, queries, config, history, observed, not_at,
                                              negative))


def per_query_batch(homes, queries, config, history: int, observed=None, not_at=None,
                    negative: bool = False) -> HomesBatch:
    """One scene per query (B = E·Q, one query each), each home at its own query's τ
    (inference)."""
    e, q = queries.tau.shape
    tokens = jax.tree.map(lambda a: a.reshape(e * q, *a.shape[2:]),
                          scene_tokens(homes, queries.tau, config))
    parts = {k: v.reshape(e * q, 1, *v.shape[2:])
             for k, v in _parts(homes, queries, config, history, observed, not_at,
                                negative).items()}
    return HomesBatch(tokens=tokens, **parts)
