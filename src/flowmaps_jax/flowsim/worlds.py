"""Named FlowSim worlds: which habits the objects follow (see :mod:`flowmaps_jax.flowsim.habits`).

``routine`` is the paper's world (every object on its cyclic routine); ``preferences`` and
``dynamic`` give every object that habit; ``mixed`` draws each object's habit from the three
evenly. One pretrained model is trained per world, as the authors do.
"""

from __future__ import annotations

import dataclasses

from flowmaps_jax.flowsim.config import DEFAULT_CONFIG, PAPER_HABITS, FlowSimConfig
from flowmaps_jax.validation import check_choice, check_instance

HABIT_WORLDS: dict[str, tuple[tuple[str, float], ...]] = {
    "routine": PAPER_HABITS,
    "preferences": (("preferences", 1.0),),
    "dynamic": (("dynamic", 1.0),),
    "mixed": (("routine", 1 / 3), ("preferences", 1 / 3), ("dynamic", 1 / 3)),
}
"""World name -> the habit mixture ``FlowSimConfig.habits`` of that world."""

HABITS_HISTORY = 8
"""Maps a habits model reads (the one at τ and 7 before it), and the observations the exact
reference posterior of the evaluate and search CLIs uses by default in a world with habits."""


def world_config(world: str, base: FlowSimConfig = DEFAULT_CONFIG) -> FlowSimConfig:
    """``base`` with the habits of ``world`` (a ``HABIT_WORLDS`` name)."""
    check_choice("world", world, tuple(HABIT_WORLDS))
    check_instance("base", base, FlowSimConfig)
    return dataclasses.replace(base, habits=HABIT_WORLDS[world])


def world_of(config: FlowSimConfig) -> str | None:
    """The ``HABIT_WORLDS`` name whose habits ``config`` has, or None for another mixture."""
    probs = config.habit_probs
    for name, habits in HABIT_WORLDS.items():
        if dataclasses.replace(DEFAULT_CONFIG, habits=habits).habit_probs == probs:
            return name
    return None
