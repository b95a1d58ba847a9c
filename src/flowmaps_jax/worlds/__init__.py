"""Worlds: where a run's data comes from, one plug-in each, found by name.

A world is what the layers above (training, and next evaluation and search) need from a source
of homes: the training data (fixed or endless chunks of fresh environments), the traceable
batch sampler, the fixed validation batches, the model objective on its batches and the
resource estimate of a run. Three are registered: ``"flowsim"`` (the 2-D FlowSim maps and their
habit worlds, :mod:`flowmaps_jax.worlds.flowsim`), ``"homes"`` (the 3-D FlowSim homes,
:mod:`flowmaps_jax.worlds.homes`) and ``"recorded"`` (a recorded dataset read from files,
:mod:`flowmaps_jax.worlds.recorded`, the homes network's input; ``reads_files``). A run
config names its world (its class attribute ``world``); nothing above this package compares
world names: it asks :func:`world` for the plug-in, as a model family is found through
:data:`flowmaps_jax.model.families.MODEL_FAMILIES`.

Every hook takes the run config ``cfg`` first and reads the fields of its own world's config
class (``TrainConfig`` for FlowSim, ``HomesTrainConfig`` for homes).
"""

from __future__ import annotations

from flowmaps_jax.worlds import flowsim, homes, recorded
from flowmaps_jax.worlds.world import World

WORLDS: dict[str, World] = {"flowsim": flowsim.WORLD, "homes": homes.WORLD,
                            "recorded": recorded.WORLD}
"""The registered worlds, by name."""
WORLD_NAMES = tuple(WORLDS)


def world(name: str) -> World:
    """The registered world ``name`` (ValueError naming ``world`` and listing them otherwise)."""
    if name not in WORLD_NAMES:
        raise ValueError(f"world must be one of {list(WORLD_NAMES)}; got {name!r}")
    return WORLDS[name]


def world_of_files() -> World:
    """The registered world whose data is a dataset on disk (``--data PATH``)."""
    return next(WORLDS[name] for name in WORLD_NAMES if WORLDS[name].reads_files)


def world_of_family(family: str) -> World:
    """The world whose models the family ``family`` is, the first registered that trains it
    (ValueError naming ``family``)."""
    for name in WORLD_NAMES:
        if family in WORLDS[name].families:
            return WORLDS[name]
    known = [f for name in WORLD_NAMES for f in WORLDS[name].families]
    raise ValueError(f"model family must be one of {tuple(known)}; got {family!r}")


__all__ = ["WORLDS", "WORLD_NAMES", "World", "world", "world_of_family", "world_of_files"]
