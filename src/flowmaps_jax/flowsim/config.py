"""FlowSim configuration: the category table (data, not code) and the simulator's numbers.
``FlowSimConfig`` is frozen and hashable (a static ``jax.jit`` argument); a bad field raises
``ValueError`` naming it."""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

import numpy as np

from flowmaps_jax.validation import INT32_MAX, check_real
from flowmaps_jax.validation.fields import (
    Choice,
    Int,
    Probabilities,
    Real,
    Text,
    check_fields,
    check_keys,
    check_mixture,
    check_table,
)

ORDERINGS = ("clockwise", "counter_clockwise", "top_to_bottom", "left_to_right", "bottom_to_top")
"""Visiting-order rules. Angles are measured at the table centre around the map centre, 0 pointing
up and increasing clockwise on screen (y grows downwards); "clockwise" visits tables by ascending
angle, "counter_clockwise" by descending angle, the others by the centre's y or x coordinate."""

SHAPES = ("square", "circle", "triangle", "diamond", "pentagon", "hexagon", "star")
"""Marker shapes an object category may be drawn with (used by ``flowsim.render``)."""

MAX_MAP_SIZE = 1024
"""Largest map side: corners are drawn from 16 random bits, non-uniform by at most 1.6 % here."""

DYNAMICS = ("markov", "schedule_jitter")
"""``markov``: the paper's chain (stay / advance one / advance two). ``schedule_jitter``: the
reference code's variant, slot = (t + offset) mod K with an independent offset in {-1, 0, +1}."""

HABITS = ("routine", "preferences", "dynamic")
"""Habit families an object may follow (:mod:`flowmaps_jax.flowsim.habits`)."""

PAPER_HABITS = (("routine", 1.0),)
"""The paper's world: every object follows the routine."""


@dataclasses.dataclass(frozen=True)
class FurnitureKind:
    """A kind of static furniture. ``descriptor`` is its integer descriptor (colour) id."""

    name: str
    descriptor: int
    colour: str


@dataclasses.dataclass(frozen=True)
class ObjectCategory:
    """One object category (one object of it per environment), sitting on ``furniture_kind``
    tables visited by ``ordering`` (``ORDERINGS``); ``shape`` (``SHAPES``) for drawing."""

    name: str
    descriptor: int
    colour: str
    shape: str
    furniture_kind: str
    ordering: str


PAPER_FURNITURE_KINDS = (
    FurnitureKind("kitchen_table", 3, "black"),
    FurnitureKind("office_desk", 4, "brown"),
    FurnitureKind("dining_table", 5, "purple"),
)
PAPER_CATEGORIES = (
    ObjectCategory("fork", 0, "red", "square", "kitchen_table", "clockwise"),
    ObjectCategory("bottle", 1, "green", "circle", "dining_table", "counter_clockwise"),
    ObjectCategory("remote", 2, "blue", "triangle", "office_desk", "top_to_bottom"),
)


@dataclasses.dataclass(frozen=True)
class FlowSimConfig:
    """All of FlowSim's parameters; the defaults are the paper's.

    map_size: side of the square map in pixels.
    num_furniture: F, pieces of furniture per environment.
    min_per_kind: every furniture kind gets at least this many pieces; the rest get random kinds.
    table_min_frac, table_max_frac: table height and width are uniform integers in
        [floor(min_frac * map_size), floor(max_frac * map_size)] pixels.
    object_frac, min_object_px: object side s = max(min_object_px, floor(object_frac * min side of
        its start table)), constant over time.
    transition_probs: Markov chain (stay, advance one, advance two) per timestep.
    jitter_probs: schedule_jitter offsets (-1, 0, +1) around the one-place-per-step schedule.
    num_timesteps: T.
    max_tokens: S, scene tokens are padded to this length.
    layout_budget: at most this many layout redraws per environment before ``generate`` gives up
        (at least 1).
    layout_candidates: random positions proposed for the last furniture piece of a layout
        attempt (piece i of F gets ceil(layout_candidates * i / (F - 1)), at least 1).
    dynamics: one of ``DYNAMICS``.
    habits: the mixture each object's habit is drawn from, once per environment: pairs
        (name in ``HABITS``, probability) summing to 1. Default: routine only (the paper's).
    preference_move, preference_mass: the preferences habit moves with probability ρ per step,
        to a place drawn from π with this mass on its one or two favourites.
    dynamic_stay, dynamic_length: the dynamic habit stays with this probability, else moves to
        another place with weight exp(−distance / dynamic_length), distance in map sides.
    furniture_kinds, categories: the category table.
    """

    map_size: int = 256
    num_furniture: int = 10
    min_per_kind: int = 3
    table_min_frac: float = 0.10
    table_max_frac: float = 0.25
    object_frac: float = 0.4
    min_object_px: int = 5
    transition_probs: tuple[float, float, float] = (0.2, 0.7, 0.1)
    jitter_probs: tuple[float, float, float] = (0.1, 0.7, 0.2)
    num_timesteps: int = 20
    max_tokens: int = 20
    layout_budget: int = 64
    layout_candidates: int = 32
    dynamics: str = "markov"
    habits: tuple[tuple[str, float], ...] = PAPER_HABITS
    preference_move: float = 0.7
    preference_mass: float = 0.8
    dynamic_stay: float = 0.05
    dynamic_length: float = 0.3
    furniture_kinds: tuple[FurnitureKind, ...] = PAPER_FURNITURE_KINDS
    categories: tuple[ObjectCategory, ...] = PAPER_CATEGORIES

    def __post_init__(self) -> None:
        check_fields(self, _RULES)
        object.__setattr__(self, "habits", check_mixture("habits", self.habits, HABITS, "habit"))
        kinds = check_table("furniture_kinds", self.furniture_kinds, FurnitureKind,
                            _ENTRY_RULES, unique=("name", "descriptor"))
        object.__setattr__(self, "furniture_kinds", kinds)
        object.__setattr__(self, "categories", check_table(  # names and ids unique over both
            "categories", self.categories, ObjectCategory, _CATEGORY_RULES,
            unique=("name", "descriptor"), earlier=kinds, refers=("furniture_kind",),
            labels={"furniture_kind": "sits on furniture kind"}))
        object.__setattr__(self, "table_min_frac", check_real(
            "table_min_frac", self.table_min_frac, 0.0, self.table_max_frac, low_open=True))
        if self.has_habits and self.dynamics != "markov":
            raise ValueError(f"habits other than the routine need dynamics='markov'; got "
                             f"dynamics={self.dynamics!r} with habits={self.habits!r}")
        # Configs that cannot produce valid scenes (tables of 0 px are refused as too small).
        lo, _ = self.table_side_range
        if self.num_furniture * lo * lo > self.map_size ** 2:
            raise ValueError(
                f"map_size {self.map_size} is too small to place {self.num_furniture} tables of "
                f"at least {lo}x{lo} px without overlap")
        required = self.min_per_kind * len(self.furniture_kinds)
        if self.num_furniture < required:
            raise ValueError(
                f"num_furniture must be >= min_per_kind * number of furniture kinds = {required}; "
                f"got {self.num_furniture}")
        largest, start = self._largest_object(self.map_size)
        if largest > lo:
            fits = next((size for size in range(self.map_size + 1, MAX_MAP_SIZE + 1)
                         if self._largest_object(size)[0] <= math.floor(
                             self.table_min_frac * size)), None)
            hint = f"map_size >= {fits}" if fits else "a larger table_min_frac"
            raise ValueError(
                f"objects would leave the map: an object can be {largest} px wide "
                f"(max(min_object_px={self.min_object_px}, floor(object_frac={self.object_frac} "
                f"* its start table's side, up to {start} px))) but the smallest table is {lo} "
                f"px (table_min_frac={self.table_min_frac} * map_size={self.map_size}), and an "
                f"object centred on such a table at the map's edge would stick out; use {hint}, "
                f"or a smaller object_frac/min_object_px")
        needed = self.num_furniture + self.num_objects
        if needed > self.max_tokens:
            raise ValueError(f"max_tokens={self.max_tokens} is smaller than the {needed} tokens "
                             f"of a scene (num_furniture={self.num_furniture} + "
                             f"{self.num_objects} objects)")

    def _largest_object(self, map_size: int) -> tuple[int, int]:
        """(largest object side, the start-table side giving it) in px on a ``map_size`` map, as
        ``layout.object_sizes`` computes it: objects stay on the map iff it is at most the
        smallest table."""
        movable = (self.min_per_kind > 1
                   or self.num_furniture > self.min_per_kind * len(self.furniture_kinds))
        start = math.floor((self.table_max_frac if movable else self.table_min_frac) * map_size)
        side = np.floor(np.float32(self.object_frac) * np.float32(start))
        return max(self.min_object_px, int(side)), start

    # ----------------------------------------------------------------- derived quantities
    @property
    def num_objects(self) -> int:
        """M, one object per category."""
        return len(self.categories)

    @property
    def habit_probs(self) -> tuple[float, float, float]:
        """Probability of each family in ``HABITS`` order."""
        weights = dict(self.habits)
        return tuple(float(weights.get(name, 0.0)) for name in HABITS)

    @property
    def has_habits(self) -> bool:
        """Whether any object may follow a habit other than the routine."""
        return self.habit_probs != (1.0, 0.0, 0.0)

    @property
    def num_kinds(self) -> int:
        """Number of furniture kinds."""
        return len(self.furniture_kinds)

    @property
    def num_descriptors(self) -> int:
        """Size of the descriptor vocabulary: max descriptor id + 1."""
        ids = [k.descriptor for k in self.furniture_kinds] + [c.descriptor for c in self.categories]
        return max(ids) + 1

    @property
    def table_side_range(self) -> tuple[int, int]:
        """(lo, hi) inclusive integer table side in pixels."""
        return (math.floor(self.table_min_frac * self.map_size),
                math.floor(self.table_max_frac * self.map_size))

    @property
    def object_descriptors(self) -> tuple[int, ...]:
        """Descriptor ids of the object categories: the only ids a query may name."""
        return tuple(c.descriptor for c in self.categories)

    @property
    def category_kind_index(self) -> tuple[int, ...]:
        """For each category, the index into ``furniture_kinds`` of the kind it sits on."""
        names = [k.name for k in self.furniture_kinds]
        return tuple(names.index(c.furniture_kind) for c in self.categories)

    # ----------------------------------------------------------------- (de)serialisation
    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict (tuples become lists, table entries become dicts)."""
        return json.loads(json.dumps(dataclasses.asdict(self)))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FlowSimConfig:
        """Inverse of ``to_dict``; unknown keys raise ``ValueError``."""
        kwargs = dict(check_keys("FlowSimConfig.from_dict", data,
                                 [f.name for f in dataclasses.fields(cls)]))
        try:
            if "furniture_kinds" in kwargs:
                kwargs["furniture_kinds"] = tuple(
                    FurnitureKind(**k) for k in kwargs["furniture_kinds"])
            if "categories" in kwargs:
                kwargs["categories"] = tuple(ObjectCategory(**c) for c in kwargs["categories"])
        except TypeError as err:
            raise ValueError(f"FlowSimConfig.from_dict: bad category table entry: {err}") from err
        for name in ("transition_probs", "jitter_probs"):
            if name in kwargs and isinstance(kwargs[name], list):
                kwargs[name] = tuple(kwargs[name])
        if isinstance(kwargs.get("habits"), list):
            kwargs["habits"] = tuple(tuple(h) if isinstance(h, list) else h
                                     for h in kwargs["habits"])
        return cls(**kwargs)


_FRACTION = Real(0.0, 1.0, low_open=True)
_ENTRY_RULES = {"name": Text(strip=False), "descriptor": Int(0, INT32_MAX),
                "colour": Text(strip=False)}
_CATEGORY_RULES = {**_ENTRY_RULES, "ordering": Choice(ORDERINGS), "shape": Choice(SHAPES)}
_RULES = {
    "map_size": Int(2, MAX_MAP_SIZE, why="positions are drawn from 16 random bits"),
    # every count becomes an int32 array somewhere
    **{name: Int(low, INT32_MAX) for name, low in (
        ("num_furniture", 1), ("min_per_kind", 1), ("min_object_px", 1), ("num_timesteps", 2),
        ("max_tokens", 1), ("layout_budget", 1), ("layout_candidates", 1))},
    "table_max_frac": _FRACTION,  # table_min_frac, in (0, table_max_frac], in __post_init__
    "object_frac": _FRACTION,
    "transition_probs": Probabilities(3), "jitter_probs": Probabilities(3),
    "dynamics": Choice(DYNAMICS),
    "preference_move": _FRACTION, "preference_mass": _FRACTION,
    "dynamic_length": Real(1e-6, 1.0),  # a float32 normal number: its kernel cannot underflow
    "dynamic_stay": Real(0.0, 1.0, high_open=True),  # < 1: a dynamic object moves
}
"""What each field of :class:`FlowSimConfig` may hold (the tables: ``__post_init__``)."""

DEFAULT_CONFIG = FlowSimConfig()
"""The paper's configuration (used as the default argument everywhere)."""


@dataclasses.dataclass(frozen=True)
class SimShape:
    """The part of a config that fixes array shapes and control flow (a static jit argument):
    configs differing only in numbers share one compiled simulator."""

    num_furniture: int
    num_kinds: int
    num_timesteps: int
    layout_candidates: int
    dynamics: str
    habits: bool
    habit_families: tuple[int, ...]
    max_places: int
    orderings: tuple[str, ...]
    category_kind: tuple[int, ...]

    @property
    def num_objects(self) -> int:
        return len(self.orderings)


def sim_shape(config: FlowSimConfig) -> SimShape:
    """Static part of ``config`` (see ``SimShape``)."""
    return SimShape(
        num_furniture=config.num_furniture,
        num_kinds=config.num_kinds,
        num_timesteps=config.num_timesteps,
        layout_candidates=config.layout_candidates,
        dynamics=config.dynamics,
        habits=config.has_habits,
        habit_families=tuple(i for i, p in enumerate(config.habit_probs) if p > 0),
        # the most tables one kind can get: every other kind has at least min_per_kind
        max_places=config.num_furniture - (config.num_kinds - 1) * config.min_per_kind,
        orderings=tuple(c.ordering for c in config.categories),
        category_kind=config.category_kind_index,
    )


def sim_params(config: FlowSimConfig) -> dict[str, Any]:
    """Numeric part of ``config`` as a dict of numpy arrays (a traced jit argument)."""
    lo, hi = config.table_side_range
    return {
        "map_size": np.int32(config.map_size),
        "side_lo": np.int32(lo),
        "side_hi": np.int32(hi),
        "min_per_kind": np.int32(config.min_per_kind),
        "layout_budget": np.int32(config.layout_budget),
        "object_frac": np.float32(config.object_frac),
        "min_object_px": np.int32(config.min_object_px),
        "transition_probs": np.asarray(config.transition_probs, np.float32),
        "jitter_probs": np.asarray(config.jitter_probs, np.float32),
        "habit_probs": np.asarray(config.habit_probs, np.float32),
        "preference_move": np.float32(config.preference_move),
        "preference_mass": np.float32(config.preference_mass),
        "dynamic_stay": np.float32(config.dynamic_stay),
        "dynamic_length": np.float32(config.dynamic_length),
        "kind_descriptor": np.asarray([k.descriptor for k in config.furniture_kinds], np.int32),
        "category_descriptor": np.asarray([c.descriptor for c in config.categories], np.int32),
    }
