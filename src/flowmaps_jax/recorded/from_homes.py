"""FlowSim homes as a recorded world: ``from_homes(homes, config, mask_fraction=..., seed=...)``
(docs/data.md, "from-homes").

One environment per home (``home{e}`` unless named): its valid receptacles and objects in slot
order (ids ``<class>|<slot>``), rooms, doors, ``receptacle_distance`` as ``distance``, hours
0..T-1; the hidden schedule parameters are dropped. Rooms are unvisited in alternating runs of
hours (``MASK_RUN_HOURS`` on average), each hour's chance ``mask_fraction``; an object in an
unvisited room is not observed (−1). Home e's mask depends only on (seed, e)
(``numpy.random.default_rng([seed, e])``), so chunks (``first_home``) match one call.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from flowmaps_jax.flowsim.homes.config import HomesConfig
from flowmaps_jax.flowsim.homes.world import Homes, validate_homes
from flowmaps_jax.recorded.format import (
    Environment,
    Recorded,
    check_environment_name,
    validate_recorded,
)
from flowmaps_jax.validation import check_int, check_real, check_seed

MASK_RUN_HOURS = 6.0
"""The mean length (hours) of the shorter of a room's unvisited and visited runs."""

_CORNER_SIGNS = np.asarray([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                            [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], np.float32)
"""The 8 corners of a box: the bottom face counter-clockwise from (x0, y0), then the top."""


def box_corners(boxes: np.ndarray) -> np.ndarray:
    """float32 (..., 8, 3) corners of axis-aligned boxes (..., 6) (cx, cy, cz, w, d, h)."""
    boxes = np.asarray(boxes, np.float32)
    return (boxes[..., None, :3] + _CORNER_SIGNS * (boxes[..., None, 3:] / 2)).astype(np.float32)


def unvisited_rooms(rng: np.random.Generator, num_rooms: int, num_hours: int,
                    fraction: float, mean_run: float = MASK_RUN_HOURS) -> np.ndarray:
    """bool (T, NR): whether each room goes unvisited at each hour; independent alternating
    runs per room, unvisited with probability ``fraction`` at every hour."""
    if fraction <= 0.0:
        return np.zeros((num_hours, num_rooms), bool)
    short = min(fraction, 1.0 - fraction)
    mean = {True: mean_run * fraction / short, False: mean_run * (1.0 - fraction) / short}
    first = rng.random(num_rooms) < fraction  # the stationary state at hour 0
    runs = num_hours + 1  # every run lasts at least an hour: enough to cover T
    state = first[:, None] ^ (np.arange(runs)[None, :] % 2 == 1)  # (NR, runs)
    lengths = rng.geometric(1.0 / np.where(state, mean[True], mean[False]))
    ends = np.cumsum(lengths, axis=1)  # run i covers hours ends[i-1] .. ends[i] - 1
    hours = np.arange(num_hours)
    run = np.stack([np.searchsorted(ends[k], hours, side="right") for k in range(num_rooms)])
    return np.take_along_axis(state, run, axis=1).T


def _check_names(names, num_homes: int, first: int) -> tuple[str, ...]:
    if names is None:
        return tuple(f"home{first + e}" for e in range(num_homes))
    if isinstance(names, str) or not isinstance(names, Sequence) or len(names) != num_homes:
        raise ValueError(f"names must be a sequence of {num_homes} environment names (one per "
                         f"home); got {names!r}"[:300])
    return tuple(check_environment_name(n, f"names[{i}]") for i, n in enumerate(names))


def home_environment(arrays: dict, e: int, config: HomesConfig, name: str,
                     mask_fraction: float, seed: int, home: int | None = None) -> Environment:
    """Home ``e`` of the homes' numpy ``arrays`` (``Homes.as_dict``) as an Environment; ``home``
    (default ``e``): its number in the whole set, which seeds its mask."""
    home = e if home is None else home
    a = {k: v[e] for k, v in arrays.items()}
    slots = np.flatnonzero(a["receptacle_valid"])
    objects = np.flatnonzero(a["object_valid"])
    renumber = np.full(a["receptacle_valid"].shape[0], -1, np.int32)
    renumber[slots] = np.arange(slots.size, dtype=np.int32)
    location = renumber[a["receptacle"][:, objects]]  # (T, M'): valid objects are always placed
    room = a["receptacle_room"][slots].astype(np.int32)
    rng = np.random.default_rng([seed, home])
    hidden = unvisited_rooms(rng, config.num_rooms, config.num_hours, mask_fraction)
    location = np.where(np.take_along_axis(hidden, room[location], axis=1), -1,
                        location).astype(np.int32)
    doors = a["door_valid"]
    rec_cls = [config.receptacle_classes[c] for c in a["receptacle_class"][slots]]
    obj_cls = [config.object_classes[c] for c in a["object_class"][objects]]
    return Environment(
        name=name,
        receptacle_ids=tuple(f"{c.name}|{s}" for c, s in zip(rec_cls, slots, strict=True)),
        receptacle_classes=tuple(c.name for c in rec_cls),
        receptacle_texts=tuple(c.text for c in rec_cls),
        receptacle_room=room,
        receptacle_corners=box_corners(a["receptacle_box"][slots]),
        object_ids=tuple(f"{c.name}|{s}" for c, s in zip(obj_cls, objects, strict=True)),
        object_classes=tuple(c.name for c in obj_cls),
        object_texts=tuple(c.text for c in obj_cls),
        allowed=a["object_allowed"][objects][:, slots].astype(bool),
        hours=np.arange(config.num_hours, dtype=np.int64),
        location=location,
        room_classes=tuple(config.room_types[t].name for t in a["room_type"]),
        room_boxes=a["room_box"].astype(np.float32),
        door_rooms=a["door_rooms"][doors].astype(np.int32),
        door_positions=a["door_position"][doors].astype(np.float32),
        distance=a["receptacle_distance"][slots][:, slots].astype(np.float32),
        source={"from": "flowsim-homes", "config": config.to_dict(), "home": int(home),
                "mask_fraction": mask_fraction, "mask_seed": seed,
                "mask_run_hours": MASK_RUN_HOURS})


def from_homes(homes: Homes, config: HomesConfig, *, mask_fraction: float = 0.0, seed: int = 0,
               names: Sequence[str] | None = None, progress=None,
               first_home: int = 0) -> Recorded:
    """FlowSim ``homes`` (E homes of ``config``) as a recorded world of E environments.

    mask_fraction: in [0, 1), about this fraction of the object-hours is hidden (-1), by whole
    rooms unvisited for runs of hours (see the module's docstring); seed: the masks' seed;
    names: E environment names (default ``home{first_home + e}``); progress: optional callable
    wrapping the range of homes (a tqdm); first_home: the number of ``homes``' first home in a
    larger set generated in chunks (names, masks and ``source["home"]`` follow it).
    ``ValueError`` naming the argument on bad input.
    """
    validate_homes(homes, config)
    mask_fraction = check_real("mask_fraction", mask_fraction, 0.0, 1.0, high_open=True)
    seed = check_seed("seed", seed)
    first_home = check_int("first_home", first_home, 0)
    arrays = {k: np.asarray(v) for k, v in homes.as_dict().items()}
    names = _check_names(names, homes.num_homes, first_home)
    homes_range = range(homes.num_homes) if progress is None else progress(
        range(homes.num_homes))
    return validate_recorded(Recorded(tuple(
        home_environment(arrays, e, config, names[e], mask_fraction, seed, first_home + e)
        for e in homes_range)))
