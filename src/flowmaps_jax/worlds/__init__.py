"""Worlds: where a run's data comes from and everything above it, one plug-in each, by name.

A world (:class:`World`) provides what the layers above need: its training data, batch sampler,
validation batches, objective and resource estimate; the Predictor's inference of its models
(:class:`Inference`); its run config and presets, its evaluate and search commands and the
options they read. Three are registered: ``flowsim`` (the 2-D maps,
:mod:`flowmaps_jax.worlds.flowsim`), ``homes`` (the 3-D FlowSim homes) and ``recorded`` (a
dataset read from files, ``--data PATH``, the homes network's input). A run config names its
world (its class attribute ``world``), a model its family (the first world listing it is the
family's); nothing above this package compares world or family names: it asks :func:`world`
or :func:`world_of_family` for the plug-in.
"""

from __future__ import annotations

from flowmaps_jax.worlds import flowsim, homes, recorded
from flowmaps_jax.worlds.world import Inference, World

WORLDS: dict[str, World] = {}
"""The registered worlds, by name (:func:`register`)."""


def register(plugin: World) -> World:
    """Add the world ``plugin`` to :data:`WORLDS` (under its name)."""
    WORLDS[plugin.name] = plugin
    return plugin


for _plugin in (flowsim.WORLD, homes.WORLD, recorded.WORLD):
    register(_plugin)


def world(name: str) -> World:
    """The registered world ``name`` (ValueError naming ``world`` and listing them otherwise)."""
    if name not in WORLDS:
        raise ValueError(f"world must be one of {list(WORLDS)}; got {name!r}")
    return WORLDS[name]


def world_of_files() -> World:
    """The registered world whose data is a dataset on disk (``--data PATH``)."""
    return next(w for w in WORLDS.values() if w.reads_files)


def families() -> tuple[str, ...]:
    """Every model family some world trains, in registration order."""
    return tuple(dict.fromkeys(f for w in WORLDS.values() for f in w.families))


def world_of_family(family: str) -> World:
    """The world whose models the family ``family`` is, the first registered that trains it
    (ValueError naming ``family``)."""
    found = next((w for w in WORLDS.values() if family in w.families), None)
    if found is None:
        raise ValueError(f"model family must be one of {families()}; got {family!r}")
    return found


__all__ = ["WORLDS", "Inference", "World", "families", "register", "world", "world_of_family",
           "world_of_files"]
