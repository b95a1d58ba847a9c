"""``HomesConfig``: the numbers and the vocabulary of the homes world, frozen and hashable (a
static jit argument); ``validate()`` raises ``ValueError`` naming the field. Hour t = 0 starts
on a Monday at 00:00; the preferences regime's ``NUM_CONTEXTS`` = 8 contexts are four phases of
the day (starting at ``day_phases``) on weekdays and weekends (docs/flowsim.md, "Homes").
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any

from flowmaps_jax.flowsim.homes.vocabulary import (
    DEFAULT_ROOMS,
    OBJECT_CLASSES,
    RECEPTACLE_CLASSES,
    ROOM_TYPES,
    ObjectClass,
    ReceptacleClass,
    RoomType,
)
from flowmaps_jax.validation.errors import prefix_errors
from flowmaps_jax.validation.fields import (
    Choice,
    Each,
    Int,
    Pair,
    Probabilities,
    Real,
    Text,
    check_fields,
    check_keys,
    check_table,
)
from flowmaps_jax.validation.files import check_plain_name
from flowmaps_jax.validation.scalars import check_int

REGIMES = ("preferences", "balanced", "frequent", "routine")
"""Schedule regimes (index = the ``regime`` id stored per object). ``HomesConfig.regime`` may
also be ``"mixed"``: each object draws one of the four uniformly."""

MAX_OBJECTS = 15
"""At most this many dynamic objects per home (FlowMaps 2026's homes)."""

MAX_PER_ROOM = 4
"""Receptacles per room at most: a room is split into 2 × 2 cells, one receptacle per cell."""

NUM_CONTEXTS = 8
"""Preference contexts: 4 phases of the day × (weekday, weekend)."""

DEFAULT_PHASES = (0, 6, 12, 18)
"""The start hours of the four phases of the day (``HomesConfig.day_phases``)."""

HOURS_PER_WEEK = 24 * 7

MAX_METRES = 1000.0
"""The largest length a config may set (home sides, door width, wall margin, class sizes),
metres: homes stay finite, and so do their distances."""

MAX_HOURS = 2**16
"""The most hours a config's homes may span (about 7.5 years)."""

MAX_TOKENS = 4096
"""The largest scene token budget (``max_tokens``): attention is quadratic in it."""

MAX_VOCABULARY = 2**16
"""The largest descriptor budget (``max_vocabulary``): the network embeds every descriptor."""

FREQUENT_LENGTH = (1e-3, 1e4)
"""The range of ``frequent_length``, metres (its kernel is a softmax of −distance / length,
which cannot underflow; the bounds keep −distance / length finite in float32)."""

DEFAULT_ACTIVITY = tuple(0.2 if (h < 7 or h == 23) else 1.0 for h in range(24))
"""Hourly activity (multiplies the move probability of every regime but the routine, which
moves every hour): low at night (23:00–07:00)."""


@dataclasses.dataclass(frozen=True)
class HomesConfig:
    """Everything the homes world is made of; the defaults give 6-room homes over 4 weeks.

    rooms: the room type of every room of a home (a multiset, shuffled over the grid cells).
    grid_rows: the floor plan is ``grid_rows`` × (len(rooms) / grid_rows) cells.
    home_width, home_depth: (lo, hi) metres, the footprint's x and y sides (uniform).
    split_jitter: cell widths (and each column's cell depths) ∝ 1 + j·U[−1, 1].
    door_width, wall_margin: metres; receptacles keep ``wall_margin`` from the walls of their
        cell, doors keep it from the ends of their wall.
    extra_door_prob: the chance of a door on each further wall long enough for one (every home
        is connected).
    receptacles_per_room: (lo, hi) receptacles in each room, uniform, distinct classes.
    objects_per_home: (lo, hi) dynamic objects drawn (distinct classes); hi <= MAX_OBJECTS.
    num_hours: T, hourly steps (default 4 weeks).
    regime: one of ``REGIMES`` or "mixed".
    routine_probs: the routine's (stay, advance one, advance two) each hour.
    preference_move, preference_mass: preferences move with ρ · activity per hour to a place
        drawn from π_c, with this mass (in (0, 1)) on the context's favourite.
    balanced_move, balanced_cycle: balanced moves with ρ · activity, to the next place of its
        cycle with this probability, else uniformly to another.
    frequent_move, frequent_length: frequent moves with ρ · activity to another place j with
        weight exp(−geodesic distance / length), metres.
    activity: 24 hourly multipliers in [0, 1] (of every regime's move but the routine's).
    day_phases: the start hours of the 4 phases of the day (strictly increasing, in 0..23) of
        the preference contexts (``context_of``).
    size_jitter: receptacle sizes are the class's × (1 + s·U[−1, 1]).
    max_tokens: scene token budget, >= rooms + max receptacles + max objects.
    max_vocabulary: descriptor budget, >= room types + receptacle classes + object classes.
    room_types, receptacle_classes, object_classes: the vocabulary (``homes.vocabulary``).
    """

    rooms: tuple[str, ...] = DEFAULT_ROOMS
    grid_rows: int = 2
    home_width: tuple[float, float] = (10.0, 14.0)
    home_depth: tuple[float, float] = (7.5, 10.0)
    split_jitter: float = 0.3
    door_width: float = 0.9
    wall_margin: float = 0.1
    extra_door_prob: float = 0.3
    receptacles_per_room: tuple[int, int] = (2, 3)
    objects_per_home: tuple[int, int] = (10, 15)
    num_hours: int = 4 * HOURS_PER_WEEK
    regime: str = "preferences"
    routine_probs: tuple[float, float, float] = (0.2, 0.7, 0.1)
    preference_move: float = 0.3
    preference_mass: float = 0.8
    balanced_move: float = 0.3
    balanced_cycle: float = 0.5
    frequent_move: float = 0.9
    frequent_length: float = 3.0
    activity: tuple[float, ...] = DEFAULT_ACTIVITY
    day_phases: tuple[int, int, int, int] = DEFAULT_PHASES
    size_jitter: float = 0.1
    max_tokens: int = 48
    max_vocabulary: int = 128
    room_types: tuple[RoomType, ...] = ROOM_TYPES
    receptacle_classes: tuple[ReceptacleClass, ...] = RECEPTACLE_CLASSES
    object_classes: tuple[ObjectClass, ...] = OBJECT_CLASSES

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise ``ValueError`` naming the field if this config cannot make valid homes."""
        # the vocabulary's tables on their own (names distinct)
        for field, cls, rules in (("room_types", RoomType, _ENTRY_RULES),
                                  ("receptacle_classes", ReceptacleClass, _SIZED_ENTRY_RULES),
                                  ("object_classes", ObjectClass, _SIZED_ENTRY_RULES)):
            object.__setattr__(self, field, check_table(field, getattr(self, field), cls, rules,
                                                        unique=("name",)))
        # names must be strings (hashable) before they are compared
        _check_name_tuple("rooms", self.rooms, "room type")
        for entry in self.receptacle_classes:
            _check_name_tuple(f"receptacle_classes: {entry.name!r} rooms", entry.rooms,
                              "room type")
        for entry in self.object_classes:
            _check_name_tuple(f"object_classes: {entry.name!r} receptacles", entry.receptacles,
                              "receptacle class")
        # what the classes name must exist
        room_types = _names(self.room_types)
        for entry in self.receptacle_classes:
            _check_names(f"receptacle_classes: {entry.name!r} rooms", entry.rooms, room_types,
                         "room type")
        receptacle_classes = _names(self.receptacle_classes)
        for entry in self.object_classes:
            _check_names(f"object_classes: {entry.name!r} receptacles", entry.receptacles,
                         receptacle_classes, "receptacle class")
        _check_names("rooms", self.rooms, room_types, "room type", distinct=False)  # two bedrooms
        check_fields(self, _RULES)  # the other fields on their own
        # one object per class (with fewer than MAX_OBJECTS classes); a descriptor for each class
        check_int("objects_per_home[1]", self.objects_per_home[1], 1,
                  min(MAX_OBJECTS, len(self.object_classes)))
        object.__setattr__(self, "max_vocabulary", check_int(
            "max_vocabulary", self.max_vocabulary, self.vocabulary_size,
            MAX_VOCABULARY))  # as a Python int
        # how the fields fit together
        if len(self.rooms) % self.grid_rows:
            raise ValueError(f"rooms: {len(self.rooms)} rooms do not fill a grid of grid_rows="
                             f"{self.grid_rows} rows")
        lo = self.receptacles_per_room[0]
        for room in set(self.rooms):
            count = sum(room in r.rooms for r in self.receptacle_classes)
            if count < lo:
                raise ValueError(f"rooms: room type {room!r} holds {count} receptacle classes, "
                                 f"fewer than receptacles_per_room[0]={lo}")
        placed = {r.name for r in self.receptacle_classes if set(r.rooms) & set(self.rooms)}
        for obj in self.object_classes:
            if not set(obj.receptacles) & placed:
                raise ValueError(f"object_classes: {obj.name!r} may stand on no receptacle class "
                                 f"that a room of rooms={self.rooms} holds")
        door = self.door_width + 2 * self.wall_margin
        narrow_w, narrow_d = self.smallest_room
        if min(narrow_w, narrow_d) < door or min(narrow_w, narrow_d) / 2 <= 2 * self.wall_margin:
            raise ValueError(f"home_width/home_depth: the smallest room can be {narrow_w:.2f} x "
                             f"{narrow_d:.2f} m, too small for a door of door_width="
                             f"{self.door_width} m + 2 x wall_margin (or for its 2 x 2 cells)")
        overlap = self.home_depth[0] / (2 * self.grid_rows - 1) if self.grid_cols > 1 else door
        if overlap < door:
            raise ValueError(f"home_depth[0]={self.home_depth[0]} m is too small: neighbouring "
                             f"columns may share no wall of door_width + 2 x wall_margin = "
                             f"{door} m (needs home_depth[0] >= {door * (2 * self.grid_rows - 1)})")
        tokens = self.num_rooms + self.max_receptacles + self.max_objects
        if tokens > self.max_tokens:
            raise ValueError(f"max_tokens={self.max_tokens} is smaller than the {tokens} tokens "
                             f"of a home ({self.num_rooms} rooms + {self.max_receptacles} "
                             f"receptacles + {self.max_objects} objects)")

    # ----------------------------------------------------------------- derived
    @property
    def num_rooms(self) -> int:
        return len(self.rooms)

    @property
    def grid_cols(self) -> int:
        return self.num_rooms // self.grid_rows

    @property
    def max_receptacles(self) -> int:
        """R: receptacle slots per home (rooms × receptacles_per_room[1])."""
        return self.num_rooms * self.receptacles_per_room[1]

    @property
    def max_objects(self) -> int:
        """M: object slots per home."""
        return self.objects_per_home[1]

    @property
    def max_doors(self) -> int:
        """D: door slots: every stacked pair in a column, every row pair across a boundary."""
        rows, cols = self.grid_rows, self.grid_cols
        return cols * (rows - 1) + (cols - 1) * rows * rows

    @property
    def vocabulary_size(self) -> int:
        return sum(len(getattr(self, f)) for f in _CLASSES)

    @property
    def descriptor_offsets(self) -> tuple[int, int, int]:
        """Where room types, receptacle classes and object classes start in the shared
        descriptor vocabulary (``vocabulary``)."""
        return (0, len(self.room_types), len(self.room_types) + len(self.receptacle_classes))

    @property
    def vocabulary(self) -> tuple[str, ...]:
        """The text descriptor of every descriptor id (room types, receptacles, objects)."""
        return tuple(c.text for c in (*self.room_types, *self.receptacle_classes,
                                      *self.object_classes))

    @property
    def smallest_room(self) -> tuple[float, float]:
        """The narrowest (x, y) sides a room can have, metres."""
        j = self.split_jitter

        def narrow(total: float, n: int) -> float:
            return total * (1 - j) / ((1 - j) + (n - 1) * (1 + j))

        return (narrow(self.home_width[0], self.grid_cols),
                narrow(self.home_depth[0], self.grid_rows))

    @property
    def room_type_index(self) -> tuple[int, ...]:
        names = [r.name for r in self.room_types]
        return tuple(names.index(r) for r in self.rooms)

    def room_allows(self) -> list[list[bool]]:
        """(room types, receptacle classes): may a receptacle class go in a room type."""
        return [[rt.name in rc.rooms for rc in self.receptacle_classes] for rt in self.room_types]

    def object_allows(self) -> list[list[bool]]:
        """(object classes, receptacle classes): may an object class stand on a class."""
        return [[rc.name in oc.receptacles for rc in self.receptacle_classes]
                for oc in self.object_classes]

    @property
    def regimes_used(self) -> tuple[int, ...]:
        """The ``REGIMES`` indices objects of this config can follow (static)."""
        return tuple(range(len(REGIMES))) if self.regime == "mixed" else (
            REGIMES.index(self.regime),)

    # ----------------------------------------------------------------- (de)serialisation
    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict (tuples become lists, vocabulary entries dicts)."""
        return json.loads(json.dumps(dataclasses.asdict(self)))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> HomesConfig:
        """Inverse of ``to_dict``; unknown keys or bad entries raise ``ValueError``."""
        check_keys("HomesConfig.from_dict", data, [f.name for f in dataclasses.fields(cls)])
        kwargs = {k: _tuples(v) for k, v in data.items()}
        with prefix_errors("HomesConfig.from_dict: bad vocabulary entry: ",
                           also=(TypeError, AttributeError)):
            for field, entry in (("room_types", RoomType),
                                 ("receptacle_classes", ReceptacleClass),
                                 ("object_classes", ObjectClass)):
                if field in data:
                    kwargs[field] = tuple(entry(**{k: _tuples(v) for k, v in e.items()})
                                          for e in data[field])
        return cls(**kwargs)


def _tuples(value: Any) -> Any:
    """Lists (from JSON) as tuples, recursively."""
    return tuple(_tuples(v) for v in value) if isinstance(value, list) else value


def _names(entries) -> frozenset:
    return frozenset(e.name for e in entries)


def _check_name_tuple(name: str, value: Any, what: str) -> None:
    """``value`` must be a non-empty tuple of strings (``what`` names, e.g. "room type")."""
    if (not isinstance(value, tuple) or not value
            or not all(isinstance(v, str) for v in value)):
        raise ValueError(f"{name} must be a non-empty tuple of {what} names (strings); got "
                         f"{value!r}"[:300])


def _check_names(name: str, value: Any, known: frozenset, what: str, distinct: bool = True):
    """``value`` must be a non-empty tuple of names, each one of ``known`` (``what`` says what
    they name, e.g. "room type"), each at most once if ``distinct``."""
    if not isinstance(value, tuple) or not value:
        raise ValueError(f"{name} must be a non-empty tuple of {what} names; got {value!r}")
    for entry in value:
        if entry not in known:
            raise ValueError(f"{name}: unknown {what} {entry!r} (known: {sorted(known)})")
    if distinct and len(set(value)) != len(value):
        raise ValueError(f"{name} names a {what} twice: {value!r}")


def _day_phases(name: str, value: Any) -> tuple[int, ...]:
    """4 start hours in 0..23, strictly increasing."""
    starts = Each(Int(0, 23), 4, "start hours in 0..23", index=True)(name, value)
    if list(starts) != sorted(set(starts)):
        raise ValueError(f"{name} must be strictly increasing; got {value!r}")
    return starts


_ENTRY_RULES = {"name": check_plain_name, "text": Text()}
_SIZED_ENTRY_RULES = {**_ENTRY_RULES,
                      "size": Each(Real(0.0, MAX_METRES, low_open=True), 3,
                                   "(w, d, h) sizes in metres")}
_METRES = Real(0.0, MAX_METRES, low_open=True)
_UNIT = Real(0.0, 1.0)
_JITTER = Real(0.0, 1.0, high_open=True)
_CLASSES = ("room_types", "receptacle_classes", "object_classes")
"""The class tables, whose entries together are the vocabulary (one descriptor each)."""
_RULES = {
    "grid_rows": Int(1),
    # one receptacle per cell of a 2 x 2 split of the room
    "receptacles_per_room": Pair(1, integer=True, high=MAX_PER_ROOM),
    "objects_per_home": Pair(1, integer=True, high=MAX_OBJECTS),
    "num_hours": Int(2, MAX_HOURS),
    "regime": Choice((*REGIMES, "mixed")),
    "routine_probs": Probabilities(3),
    "preference_mass": Real(0.0, 1.0, low_open=True, high_open=True),
    **{name: _UNIT for name in ("preference_move", "balanced_move",
                                "balanced_cycle", "frequent_move", "extra_door_prob")},
    "frequent_length": Real(*FREQUENT_LENGTH),
    "split_jitter": _JITTER, "size_jitter": _JITTER,
    "activity": Each(_UNIT, 24, "hourly values in [0, 1]"),
    "day_phases": _day_phases,
    "home_width": Pair(0.0, high=MAX_METRES), "home_depth": Pair(0.0, high=MAX_METRES),
    "door_width": _METRES, "wall_margin": Real(0.0, MAX_METRES),
    "max_tokens": Int(1, MAX_TOKENS),
}
"""What the other fields of :class:`HomesConfig` may hold on their own (``validate`` checks the
rest and how the fields fit together)."""

DEFAULT_HOMES_CONFIG = HomesConfig()


def context_of(t, phases: tuple[int, ...] = DEFAULT_PHASES):
    """Preference context of hour t (an int or an array, NumPy or JAX): the phase of the day
    (the last of ``phases`` <= t mod 24; the last phase before the first) + 4 on weekends."""
    phase = (sum(t % 24 >= start for start in phases) - 1) % len(phases)
    return phase + 4 * ((t // 24) % 7 >= 5)

