"""The recorded world: a recorded dataset (``flowmaps_jax.recorded``, a folder PATH) as the homes
network's input.

Every environment of the dataset is padded to the dataset's common maxima and written as one
home of a :class:`~flowmaps_jax.flowsim.homes.world.Homes` pytree (:func:`recorded_homes`), with
an ``observed`` (E, T, M) mask beside it (False where the object was not seen, and on the
padding). The homes network reads it through a :class:`~flowmaps_jax.flowsim.homes.HomesConfig`
derived from the data (:func:`homes_config_of`): its vocabulary is the dataset's class names (the
classes' ``text``; the ``name`` s are ``room0``, ``receptacle3``, ... and a ``none`` room type
for rooms that are not known), its sizes (rooms NR, receptacle slots R, object slots M, hours T)
the largest environment's, its token budget NR + R + M. It is stored with the run
(``config.json``'s ``homes``), so that evaluation rebuilds the same inputs from it: data whose
classes it does not name, or whose environments are larger, is refused (``ValueError``).

How an environment becomes a home (a Homes-compatible pytree; nothing of the homes' hidden
law is known, so ``regime`` is 0 and ``favourite`` each object's first allowed receptacle):
coordinates moved so that the smallest x, y (and z, if below 0) is 0; the hour axis is the
recorded hours themselves (hour t of the recording at index t, hours never recorded
unobserved); ``receptacle`` (E, T, M) where each object was last seen (before its first
sighting: its first allowed receptacle, marked unseen); the rooms as recorded, then ``none``
rooms spanning the home (a receptacle of unknown room stands in the first); ``cycle`` from the
geometry (``furnish.cycles``); ``receptacle_distance`` ``Environment.walking_distance()``.

The split (:func:`split_environments`) is by environment, seeded: ``test_fraction`` and
``val_fraction`` of them held out, the rest trained on; with ``time_fraction`` > 0 the last
``time_fraction`` of every training environment's hours are held out too (training targets
before the cut, test targets after it; with no validation environment, validation targets in
the first half of the held-out hours, test targets in the second). Training draws each home
at one map hour τ with queries only on (object, τ_q) pairs that were observed (targets are the
receptacle seen at τ_q); a query's object may be unseen at τ (its inputs then say where and how
long ago it was last seen).

``cfg`` is a ``flowmaps_jax.training.config.RecordedTrainConfig`` throughout.
"""

from __future__ import annotations

import math
import pathlib
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from flowmaps_jax.flowsim.homes.config import MAX_OBJECTS, MAX_PER_ROOM, NUM_CONTEXTS, HomesConfig
from flowmaps_jax.flowsim.homes.floorplan import door_pairs
from flowmaps_jax.flowsim.homes.furnish import cycles
from flowmaps_jax.flowsim.homes.queries import DEFAULT_HORIZONS, HomesQueries
from flowmaps_jax.flowsim.homes.vocabulary import ObjectClass, ReceptacleClass, RoomType
from flowmaps_jax.flowsim.homes.world import Homes, validate_homes
from flowmaps_jax.model.homes_family import FAMILY_NAME
from flowmaps_jax.model.homes_inputs import shared_tau_batch
from flowmaps_jax.recorded.format import content_digest, load_recorded
from flowmaps_jax.validation import check_int, prefix_errors
from flowmaps_jax.worlds import homes as homes_world
from flowmaps_jax.worlds.world import World

VAL_SEED = 0x40E5_0003
"""The seed of the fixed validation batches (distinct from the homes world's)."""
NO_ROOM = "none"
"""The room type of rooms that are not recorded (``text``: "unknown room")."""
DEFAULT_RECEPTACLE_SIZE = (0.5, 0.5, 0.5)
DEFAULT_OBJECT_SIZE = (0.1, 0.1, 0.1)
"""Metres: an object class's size when the data has no object boxes."""
MIN_SIZE = 1e-3
"""Metres: the smallest box side (a flat recorded box is this thick)."""
SPLITS = ("train", "val", "test")
MIN_HELD_OUT = 3
"""Validation or test by environment on fewer environments draws a warning (describe_split)."""


@struct.dataclass
class RecordedHomes:
    """E recorded environments as homes: ``homes`` (a :class:`Homes` of the run's config),
    ``observed`` (E, T, M) bool, and the hours whose observations are targets of this part of
    the split: ``start`` <= τ_q < ``stop`` (E,) int32; ``not_at`` (E, T, M, R) bool, looked
    for on r at hour t and not there (None: the data has no such looks)."""

    homes: Homes
    observed: jax.Array
    start: jax.Array
    stop: jax.Array
    not_at: jax.Array | None = None

    @property
    def num_homes(self) -> int:
        return self.homes.num_homes


# --------------------------------------------------------------------------------------------
# The vocabulary and sizes


def _class_sizes(recorded, kind: str) -> dict[str, tuple[float, float, float]]:
    """Median (w, d, h) of every receptacle (``kind`` "receptacles") or object class (from the
    object boxes, where recorded), metres."""
    sizes: dict[str, list] = {}
    for env in recorded.environments:
        if kind == "receptacles" and env.receptacle_corners is None:
            continue
        if kind == "receptacles":
            boxes = np.asarray(env.receptacle_boxes())[:, 3:]
            classes = env.receptacle_classes
        elif env.object_corners is not None:
            corners = np.asarray(env.object_corners)  # (T, M, 8, 3)
            seen = np.asarray(env.observed)
            span = corners.max(-2) - corners.min(-2)  # (T, M, 3)
            boxes = np.stack([np.median(span[seen[:, m], m], 0) if seen[:, m].any()
                              else np.full(3, np.nan) for m in range(env.num_objects)])
            classes = env.object_classes
        else:
            continue
        for cls, box in zip(classes, boxes, strict=True):
            if np.all(np.isfinite(box)):
                sizes.setdefault(cls, []).append(box)
    return {c: tuple(float(max(v, MIN_SIZE)) for v in np.median(np.stack(b), 0))
            for c, b in sizes.items()}


def homes_config_of(recorded) -> HomesConfig:
    """The :class:`HomesConfig` the homes network reads ``recorded`` with (see the module
    docstring); ``ValueError`` when an environment is larger than the network takes (more than
    ``MAX_OBJECTS`` objects)."""
    envs = recorded.environments
    voc = recorded.vocabulary()
    big = max(envs, key=lambda e: e.num_objects)
    if big.num_objects > MAX_OBJECTS:
        raise ValueError(f"environment {big.name!r} has {big.num_objects} objects; the "
                         f"homes network takes at most {MAX_OBJECTS} per environment")
    r_max = max(e.num_receptacles for e in envs)
    m_max = max(e.num_objects for e in envs)
    rooms = max(len(e.room_classes) for e in envs) + 1  # and a spare "none" room
    rooms = max(rooms, -(-r_max // MAX_PER_ROOM))
    per_room = -(-r_max // rooms)
    hours = max(int(np.asarray(e.hours)[-1]) + 1 for e in envs)
    room_types = (*(RoomType(f"room{i}", c) for i, c in enumerate(voc["rooms"])),
                  RoomType(NO_ROOM, "unknown room"))
    type_names = tuple(t.name for t in room_types)
    rec_sizes = _class_sizes(recorded, "receptacles")
    receptacles = tuple(ReceptacleClass(f"receptacle{i}", c,
                                        rec_sizes.get(c, DEFAULT_RECEPTACLE_SIZE), type_names)
                        for i, c in enumerate(voc["receptacles"]))
    rec_names = tuple(r.name for r in receptacles)
    obj_sizes = _class_sizes(recorded, "objects")
    objects = [ObjectClass(f"object{i}", c, obj_sizes.get(c, DEFAULT_OBJECT_SIZE), rec_names)
               for i, c in enumerate(voc["objects"])]
    objects += [ObjectClass(f"object_pad{j}", "unused", DEFAULT_OBJECT_SIZE, rec_names)
                for j in range(m_max - len(objects))]  # objects_per_home[1] <= classes
    width = 2.0 * rooms  # the generator's fields: any valid plan (nothing is generated)
    config = HomesConfig(
        rooms=(NO_ROOM,) * rooms, grid_rows=1, home_width=(width, width),
        home_depth=(2.0, 2.0), split_jitter=0.0, receptacles_per_room=(1, per_room),
        objects_per_home=(1, m_max), num_hours=max(hours, 2), regime="mixed",
        room_types=room_types, receptacle_classes=receptacles, object_classes=tuple(objects),
        max_tokens=rooms * (1 + per_room) + m_max,
        max_vocabulary=len(room_types) + len(receptacles) + len(objects))
    return config


def _ids(config: HomesConfig, field: str) -> dict[str, int]:
    """Class name -> id in ``config``'s ``field``: the entry's ``text`` (a config derived from
    data holds the class names there) or its ``name`` (a FlowSim homes model's config, whose
    names ``from_homes`` records as the classes)."""
    entries = [(i, c) for i, c in enumerate(getattr(config, field))
               if not c.name.startswith("object_pad") and c.name != NO_ROOM]
    return {**{c.name: i for i, c in entries}, **{c.text: i for i, c in entries}}


# --------------------------------------------------------------------------------------------
# Environments as homes


_cycles = jax.jit(cycles)  # one program, not one per operation


def _environment_home(env, config: HomesConfig, ids: dict) -> dict:
    """One environment as the fields of one home (numpy) and its observed mask (T, M)."""
    nr, r, m, t = (config.num_rooms, config.max_receptacles, config.max_objects,
                   config.num_hours)
    re, me, k = env.num_receptacles, env.num_objects, len(env.room_classes)
    where = f"environment {env.name!r}"
    unknown = bool(np.any(np.asarray(env.receptacle_room) < 0))
    if re > r or me > m or k + unknown > nr or int(env.hours[-1]) >= t:
        raise ValueError(f"{where} is larger than the model's homes ({re} receptacles, {me} "
                         f"objects, {k} rooms{' + 1 for unknown rooms' if unknown else ''}, "
                         f"{int(env.hours[-1]) + 1} hours; the model takes {r}, {m}, {nr} "
                         f"and {t})")
    for field, classes in (("room_types", env.room_classes),
                           ("receptacle_classes", env.receptacle_classes),
                           ("object_classes", env.object_classes)):
        missing = sorted(set(classes) - set(ids[field]))
        if missing:
            what = {"room_types": "room", "receptacle_classes": "receptacle",
                    "object_classes": "object"}[field]
            raise ValueError(f"{where}: the model's vocabulary has no {what} class "
                             f"{missing[0]!r} ({len(missing)} class(es) missing)")
    geometry = env.receptacle_corners is not None  # else every box at 0, the home 1 m wide
    corners = np.asarray(env.receptacle_corners if geometry else np.zeros((re, 8, 3)),
                         np.float64)  # (R, 8, 3)
    points = [corners[..., :2].reshape(-1, 2)]
    room_box = (np.zeros((0, 4)) if env.room_boxes is None or k == 0
                else np.asarray(env.room_boxes, np.float64))
    if len(room_box):
        points += [room_box[:, :2], room_box[:, 2:]]
    low = np.concatenate(points).min(0)
    z_low = min(float(corners[..., 2].min()), 0.0)
    shift = np.array([*low, z_low])
    corners = corners - shift
    room_box = room_box - np.tile(low, 2)
    size = np.maximum(np.concatenate([corners[..., :2].reshape(-1, 2),
                                      room_box[:, 2:]]).max(0), 0.01 if geometry else 1.0)
    boxes = np.asarray(env.receptacle_boxes(), np.float64)
    boxes[:, :3] -= shift
    boxes[:, 3:] = np.maximum(boxes[:, 3:], MIN_SIZE)
    boxes[:, 2] = np.maximum(boxes[:, 2], boxes[:, 5] / 2)
    rooms = np.tile(np.array([0.0, 0.0, *size]), (nr, 1))
    rooms[:len(room_box)] = room_box  # rooms without boxes span the home
    names = [c.name for c in config.room_types]
    room_type = np.full(nr, names.index(NO_ROOM) if NO_ROOM in names else 0, np.int32)
    room_type[:k] = [ids["room_types"][c] for c in env.room_classes]
    rec_class = np.full(r, -1, np.int32)
    rec_class[:re] = [ids["receptacle_classes"][c] for c in env.receptacle_classes]
    rec_room = np.zeros(r, np.int32)
    room_of = np.asarray(env.receptacle_room)
    rec_room[:re] = np.where(room_of >= 0, room_of, k)
    rec_box = np.zeros((r, 6))
    rec_box[:re] = boxes
    valid_r = np.arange(r) < re
    dist = np.zeros((r, r))
    dist[:re, :re] = np.asarray(env.walking_distance(), np.float64)
    obj_class = np.full(m, -1, np.int32)
    obj_class[:me] = [ids["object_classes"][c] for c in env.object_classes]
    allowed = np.zeros((m, r), bool)
    allowed[:me, :re] = np.asarray(env.allowed, bool)
    valid_o = allowed.any(-1)
    obj_class = np.where(valid_o, obj_class, -1)
    cyc, num = (np.asarray(a) for a in _cycles(allowed, np.asarray(rec_box, np.float32),
                                               np.asarray(size, np.float32)))
    location = np.full((t, m), -1, np.int64)
    location[np.asarray(env.hours), :me] = np.asarray(env.location)
    location[:, ~valid_o] = -1
    observed = location >= 0
    last = np.maximum.accumulate(np.where(observed, np.arange(t)[:, None], -1), axis=0)
    first_allowed = np.maximum(cyc[:, 0], 0)
    filled = np.where(last >= 0, np.take_along_axis(location, np.maximum(last, 0), 0),
                      first_allowed[None, :])
    filled = np.where(valid_o[None, :], filled, -1)
    favourite = np.where(valid_o[:, None], first_allowed[:, None], -1)
    not_at = None
    if env.not_at is not None:
        not_at = np.zeros((t, m, r), bool)
        not_at[np.asarray(env.hours), :me, :re] = env.not_at
    d = config.max_doors
    return {
        "home_size": size.astype(np.float32), "room_type": room_type,
        "room_box": rooms.astype(np.float32), "door_position": np.zeros((d, 2), np.float32),
        "door_rooms": door_pairs(config), "door_valid": np.zeros(d, bool),
        "receptacle_class": rec_class, "receptacle_room": rec_room,
        "receptacle_box": rec_box.astype(np.float32), "receptacle_valid": valid_r,
        "receptacle_distance": dist.astype(np.float32), "object_class": obj_class,
        "object_valid": valid_o, "object_allowed": allowed,
        "regime": np.zeros(m, np.int32), "cycle": cyc.astype(np.int32),
        "num_allowed": num.astype(np.int32),
        "favourite": np.broadcast_to(favourite, (m, NUM_CONTEXTS)).astype(np.int32),
        "receptacle": filled.astype(np.int32), "_observed": observed, "_not_at": not_at,
        "_hours": int(env.hours[-1]) + 1}


def recorded_homes(recorded, config: HomesConfig, index=None, start=None,
                   stop=None) -> RecordedHomes:
    """Environments ``index`` (default all) of ``recorded`` as :class:`RecordedHomes` of
    ``config`` (checked with ``validate_homes``); targets in hours ``start`` … ``stop`` − 1
    (E,) (default: all the environment's hours). ``ValueError`` naming the environment when it
    does not fit ``config`` (a class its vocabulary lacks, more slots than it has)."""
    envs = recorded.environments
    index = range(len(envs)) if index is None else index
    ids = {f: _ids(config, f) for f in ("room_types", "receptacle_classes", "object_classes")}
    parts = [_environment_home(envs[i], config, ids) for i in index]
    if not parts:
        raise ValueError("no environment to read")
    looks = [p.pop("_not_at") for p in parts]
    stacked = {k: np.stack([p[k] for p in parts]) for k in parts[0]}
    homes = Homes(**{k: jax.device_put(v) for k, v in stacked.items() if not k.startswith("_")})
    validate_homes(homes, config, name="the homes of the data")
    e = len(parts)
    start = np.zeros(e, np.int32) if start is None else np.asarray(start, np.int32)
    stop = stacked["_hours"] if stop is None else np.asarray(stop)
    return RecordedHomes(homes=homes, observed=jax.device_put(stacked["_observed"]),
                         start=jax.device_put(start), stop=jax.device_put(stop.astype(np.int32)),
                         not_at=None if all(x is None for x in looks) else jax.device_put(np.stack(
                             [np.zeros((*stacked["_observed"].shape[1:], config.max_receptacles),
                                       bool) if x is None else x for x in looks])))


def answer(predictor, data, environment: str, object_id: str, tau: int, tau_q: int
           ) -> dict[str, float]:
    """Where is ``object_id`` of ``environment`` at hour ``tau_q``, given the log up to ``tau``
    (hours as the data counts them)? ``{receptacle id: probability}`` over its allowed
    receptacles, most probable first: ``predictor.probabilities`` on that one query, with the
    data's observation mask. ``data``: a dataset folder or a loaded ``Recorded``."""
    recorded = load_recorded(data) if isinstance(data, (str, pathlib.Path)) else data
    names = [env.name for env in recorded.environments]
    if environment not in names:
        raise ValueError(f"environment must be one of the data's {len(names)} environments; "
                         f"got {environment!r}")
    env = recorded.environments[names.index(environment)]
    if object_id not in env.object_ids:
        raise ValueError(f"object_id must be an object of {environment!r}; got {object_id!r}")
    tau = check_int("tau", tau, 0, int(env.hours[-1]))
    tau_q = check_int("tau_q", tau_q, tau + 1, predictor.homes.num_hours - 1)
    homes = recorded_homes(recorded, predictor.homes, index=[names.index(environment)])
    queries = HomesQueries(*(jnp.full((1, 1), v, jnp.int32)
                             for v in (env.object_ids.index(object_id), tau, tau_q)))
    p = np.asarray(predictor.probabilities(homes.homes, queries, predictor.homes,
                                           observed=homes.observed, not_at=homes.not_at))[0, 0]
    return {env.receptacle_ids[r]: float(p[r]) for r in np.argsort(-p[:env.num_receptacles])
            if p[r] > 0}


# --------------------------------------------------------------------------------------------
# The split


def split_environments(names, val_fraction: float, test_fraction: float,
                       seed: int) -> dict[str, tuple[int, ...]]:
    """Environment indices by part (``"train"``, ``"val"``, ``"test"``): a seeded permutation,
    ``round(fraction · E)`` environments to test and to val (at least one each when the
    fraction is > 0 and E >= 3), the rest (at least one) to train."""
    e = len(names)
    order = np.random.default_rng(seed).permutation(e)
    counts = []
    for fraction in (test_fraction, val_fraction):
        n = round(fraction * e)
        counts.append(max(n, 1 if fraction > 0 and e >= 3 else 0))
    n_test, n_val = counts
    if n_test + n_val >= e:
        raise ValueError(f"val_fraction={val_fraction} and test_fraction={test_fraction} leave "
                         f"no training environment of the {e}")
    return {"test": tuple(sorted(order[:n_test].tolist())),
            "val": tuple(sorted(order[n_test:n_test + n_val].tolist())),
            "train": tuple(sorted(order[n_test + n_val:].tolist()))}


def time_cut(recorded, index, time_fraction: float) -> np.ndarray:
    """(len(index),) int32: the first held-out hour of each environment (its last
    ``time_fraction`` of hours held out; its length when 0)."""
    out = []
    for i in index:
        hours = np.asarray(recorded.environments[i].hours)
        keep = len(hours) - round(time_fraction * len(hours))
        out.append(int(hours[keep]) if keep < len(hours) else int(hours[-1]) + 1)
    return np.asarray(out, np.int32)


def describe_split(recorded, split: dict, time_fraction: float) -> str:
    """One line per part: its environments' names; then the time split, and a warning when
    validation or test rests on fewer than ``MIN_HELD_OUT`` environments."""
    names = recorded.names()
    lines = [f"  {part} ({len(split[part])}): "
             + ", ".join(names[i] for i in split[part][:8])
             + (" ..." if len(split[part]) > 8 else "") for part in SPLITS]
    if time_fraction > 0:
        lines.append(f"  and the last {time_fraction:.0%} of every training environment's "
                     "hours held out for " + ("test" if split["val"] else
                                              "validation (first half) and test (second)"))
    few = [f"{part} {len(split[part])}" for part in ("val", "test")
           if len(split[part]) < MIN_HELD_OUT and not (time_fraction > 0 and (
               part == "test" or not split["val"]))]
    if few:
        lines.append(f"  warning: {' and '.join(few)} environments (fewer than {MIN_HELD_OUT}); "
                     "with few environments hold out the last days of every one instead: "
                     "--set val_fraction=0 --set test_fraction=0 --set time_fraction=0.25")
    return "\n".join(lines)


def split(recorded, cfg_split: tuple) -> dict:
    """The split ``cfg_split`` = (val_fraction, test_fraction, time_fraction, seed) of
    ``recorded``, the one split of train, evaluate and search: ``"environments"``
    (:func:`split_environments`), and for each part of :data:`SPLITS` ``(index, start, stop)``:
    its environments in the homes' order and their target hours (None: all). Test: the held-out
    environments whole, then the held-out hours of the training ones; with no validation
    environment, the first half of those hours validates, the second tests."""
    val_fraction, test_fraction, time_fraction, seed = cfg_split
    envs = split_environments(recorded.names(), val_fraction, test_fraction, seed)
    train = envs["train"]
    cut = time_cut(recorded, train, time_fraction)
    parts = {"environments": envs, "train": (train, None, cut),
             "val": (envs["val"], None, None), "test": (envs["test"], None, None)}
    if time_fraction > 0:
        mid = cut if envs["val"] else time_cut(recorded, train, time_fraction / 2)
        parts["test"] = ((*envs["test"], *train),
                         np.concatenate([np.zeros(len(envs["test"]), np.int32), mid]), None)
        if not envs["val"]:  # validation by time
            parts["val"] = (train, cut, mid)
    return parts


def part_of(recorded, config: HomesConfig, parts: dict, part: str) -> RecordedHomes:
    """The part ``part`` of :func:`split`'s ``parts``: its environments as homes of
    ``config``, their target hours set."""
    index, start, stop = parts[part]
    if not index:
        raise ValueError(f"the split has no {part} environment (val_fraction / test_fraction)")
    return recorded_homes(recorded, config, index, start=start, stop=stop)


# --------------------------------------------------------------------------------------------
# Batches


def target_hours(data: RecordedHomes) -> jax.Array:
    """(E, T, M) bool: the observed (hour, object) pairs that may be targets."""
    t = jnp.arange(data.observed.shape[1])
    inside = (t >= data.start[:, None]) & (t < data.stop[:, None])
    return data.observed & inside[..., None] & data.homes.object_valid[:, None, :]


def _horizon_weights(max_horizon: int, default_frac: float) -> jax.Array:
    """(max_horizon,) the probability of each horizon 1 … max_horizon: ``default_frac`` on
    ``DEFAULT_HORIZONS`` (those that fit), the rest log-uniform as the homes world draws it."""
    dt = np.arange(1, max_horizon + 1)
    spread = (np.log(np.minimum(dt + 1, max_horizon + 1)) - np.log(dt)) / math.log(
        max_horizon + 1)
    spread[-1] += 1.0 - spread.sum()
    fixed = np.isin(dt, [d for d in DEFAULT_HORIZONS if d <= max_horizon] or [1])
    w = default_frac * fixed / fixed.sum() + (1 - default_frac) * spread
    return jnp.asarray(w, jnp.float32)


def drawable_tau(data: RecordedHomes, max_horizon: int, default_frac: float) -> jax.Array:
    """(E, T) bool: the map hours τ with an observed target at a horizon :func:`draw_queries`
    may draw (1 … ``max_horizon``, weighted by :func:`_horizon_weights`)."""
    ok = target_hours(data)  # (E, T, M)
    e, t, _ = ok.shape
    h = max_horizon
    weights = _horizon_weights(h, default_frac)  # (H,)
    any_ok = jnp.concatenate([ok.any(-1), jnp.zeros((e, h + 1), bool)], axis=1)
    ahead = any_ok[:, jnp.arange(t)[:, None] + jnp.arange(1, h + 1)]  # (E, T, H): τ + Δ
    return jnp.any(ahead & (weights > 0), axis=-1)  # a target at a horizon drawn


def check_drawable(data: RecordedHomes, names, cfg, part: str) -> None:
    """``ValueError`` naming the first environment of ``data`` (``names`` in its order) with
    no map hour :func:`draw_queries` can draw (its queries would target hours never observed:
    e.g. no sighting within ``max_horizon`` hours after another one)."""
    ok = np.asarray(drawable_tau(data, cfg.max_horizon, cfg.default_horizon_frac).any(-1))
    if not ok.all():
        bad = int(np.flatnonzero(~ok)[0])
        raise ValueError(f"{part} environment {names[bad]!r} has no observed target within "
                         f"max_horizon={cfg.max_horizon} hours after a map hour"
                         + (" before the time cut" if part == "training" else "")
                         + f" ({int((~ok).sum())} such environment(s)); drop it from the data")


def draw_queries(key, data: RecordedHomes, num_queries: int, max_horizon: int,
                 default_frac: float) -> HomesQueries:
    """Q queries per home, sharing one map hour τ per home: τ uniformly among the hours with
    an observed target at a horizon it may draw (1 … ``max_horizon``), then
    (object, horizon) pairs among the observed targets, horizons weighted as the homes world
    draws them (:func:`_horizon_weights`). Jittable."""
    k_tau, k_pair = jax.random.split(key)
    ok = target_hours(data)  # (E, T, M)
    e, _, m = ok.shape
    h = max_horizon
    weights = _horizon_weights(h, default_frac)  # (H,)
    tau_ok = drawable_tau(data, max_horizon, default_frac)  # (E, T)
    tau = jax.random.categorical(k_tau, jnp.where(tau_ok, 0.0, -jnp.inf))  # (E,)
    padded = jnp.concatenate([ok, jnp.zeros((e, h + 1, m), bool)], axis=1)
    window = jax.vmap(lambda o, s: jax.lax.dynamic_slice_in_dim(o, s + 1, h, 0))(
        padded, tau)  # (E, H, M)
    logits = jnp.where(window, jnp.log(weights)[:, None], -jnp.inf)
    pair = jax.random.categorical(k_pair, logits.reshape(e, 1, h * m),
                                  shape=(e, num_queries))  # (E, Q)
    dt, obj = pair // m + 1, pair % m
    tau = jnp.broadcast_to(tau[:, None], (e, num_queries)).astype(jnp.int32)
    return HomesQueries(object_index=obj.astype(jnp.int32), tau=tau,
                        tau_q=(tau + dt).astype(jnp.int32))


def draw_batch(key, data: RecordedHomes, cfg, index=None):
    """A training batch (B = ``batch_size`` environments x Q = ``queries_per_scene`` queries)
    from ``data``: environments ``index`` (B,) (default: uniformly drawn). Jittable."""
    k_home, k_query = jax.random.split(key)
    if index is None:
        index = jax.random.randint(k_home, (cfg.batch_size,), 0, data.num_homes)
    data = jax.tree.map(lambda a: a[index], data)
    queries = draw_queries(k_query, data, cfg.queries_per_scene, cfg.max_horizon,
                           cfg.default_horizon_frac)
    return shared_tau_batch(data.homes, queries, cfg.homes, cfg.model.history, data.observed,
                            data.not_at, cfg.model.negative_evidence)


def split_of(cfg) -> tuple:
    """The split fields of a recorded run config ``cfg`` (a dict or a config), :func:`split`'s
    ``cfg_split``."""
    get = cfg.get if isinstance(cfg, dict) else lambda k, d: getattr(cfg, k)
    return (get("val_fraction", 0.0), get("test_fraction", 0.0), get("time_fraction", 0.0),
            get("split_seed", 0))


_LOADED: dict = {}


def load_data(path) -> tuple:
    """(the dataset in the folder ``path``, its :func:`content_digest`): read and digested
    once per process while its files stay the same (their names, sizes and times); ValueError
    on a missing or bad dataset (callers name the option)."""
    if not path:
        raise ValueError("a recorded run needs a dataset (--data PATH)")
    try:
        stamp = (path, sorted((str(f), s.st_ino, s.st_size, s.st_mtime_ns) for f in
                              [pathlib.Path(path), *pathlib.Path(path).rglob("*")]
                              for s in [f.stat()]))
    except OSError:
        stamp = None  # load_recorded says what is wrong
    try:
        if stamp is None or _LOADED.get("stamp") != stamp:
            recorded = load_recorded(path)
            _LOADED.clear()  # at most one dataset in memory
            _LOADED.update(stamp=stamp, data=(recorded, content_digest(recorded)))
    except OSError as err:
        raise ValueError(f"cannot read {path}: {err.strerror or err}") from None
    return _LOADED["data"]


def splits(cfg, log: Callable[[str], None] = print, mesh=None):
    """(the training environments, the validation environments) of ``cfg.data``, split as
    ``cfg`` says (printed)."""
    start = time.perf_counter()
    with prefix_errors("data: "):
        recorded, digest = load_data(cfg.data)
        if cfg.data_digest and digest != cfg.data_digest:
            raise ValueError(f"{cfg.data} changed since the run began (its contents no longer "
                             f"match the digest in config.json, data_digest); train a new run "
                             f"on the new data")
        parts = split(recorded, split_of(cfg))
        log(f"Recorded data {cfg.data}: {len(recorded.environments)} environments, split by "
            f"environment (split_seed={cfg.split_seed}):\n"
            + describe_split(recorded, parts["environments"], cfg.time_fraction))
        train = part_of(recorded, cfg.homes, parts, "train")
        if not bool(target_hours(train).any()):
            raise ValueError(f"the training environments of {cfg.data} hold no observation "
                             "to train on")
        names = recorded.names()
        check_drawable(train, [names[i] for i in parts["train"][0]], cfg, "training")
        val_part = "val" if parts["val"][0] else "train"
        val = part_of(recorded, cfg.homes, parts, val_part)
        check_drawable(val, [names[i] for i in parts[val_part][0]],
                       cfg, "validation" if val_part == "val" else "training")
    log(f"  data ready in {time.perf_counter() - start:.1f} s")
    return train, val


def validation_batches(cfg, data: RecordedHomes):
    """``val_batches`` fixed batches (stacked on a leading axis): batch j holds validation
    environments j·B … (j + 1)·B − 1 (cyclically), drawn with a key from :data:`VAL_SEED`."""
    key = jax.random.fold_in(jax.random.key(VAL_SEED), 1)
    draw = jax.jit(lambda k, d, index: draw_batch(k, d, cfg, index))
    b = cfg.batch_size
    batches = [draw(jax.random.fold_in(key, j), data,
                    jnp.arange(j * b, (j + 1) * b) % data.num_homes)
               for j in range(cfg.val_batches)]
    return jax.tree.map(lambda *a: jnp.stack(a), *batches)


def resource_estimate(cfg, devices: int = 1) -> list[tuple[str, int, int]]:
    """The homes world's estimate of the model, the step and the validation batches (the
    data is what the files hold)."""
    return homes_world.resource_estimate(cfg, devices)[:3]


def _no_endless(cfg, data_key, step, mesh=None):
    raise ValueError("a recorded world's training data is fixed (its files)")


WORLD = World(
    name="recorded", splits=splits, endless=_no_endless,
    chunk_steps=lambda cfg: cfg.steps, is_endless=lambda cfg: False,
    batch_fn=lambda cfg: lambda key, data: draw_batch(key, data, cfg),
    val_batches=validation_batches, objective=homes_world.objective,
    check_batch=homes_world.check_batch, resources=resource_estimate,
    host_part=homes_world.host_part, families=(FAMILY_NAME,), reads_files=True,
    inference=homes_world.INFERENCE, config="flowmaps_jax.training.config:RecordedTrainConfig",
    presets="flowmaps_jax.training.config:RECORDED_PRESETS",
    evaluate="flowmaps_jax.evaluation.realised:evaluate",
    search="flowmaps_jax.evaluation.realised:search",
    options={"evaluate": ("data", "queries", "budget"),
             "search": ("data", "queries", "budget")})
"""The recorded world."""
