"""Recorded worlds: data from files instead of a simulator (docs/data.md).

Modules, one idea each: ``format`` (the files, the in-memory ``Recorded`` / ``Environment``,
``load_recorded`` / ``save_recorded`` / ``validate_environment``), ``from_homes`` (FlowSim
homes as a recorded world, with rooms masked as a robot would miss them), ``flowmaps2026``
(the authors' 2026 dataset format, both ways).
"""

from flowmaps_jax.recorded.format import (
    FORMAT,
    VERSION,
    Environment,
    Recorded,
    load_recorded,
    save_recorded,
    validate_environment,
)
from flowmaps_jax.recorded.from_homes import from_homes

__all__ = [
    "FORMAT",
    "VERSION",
    "Environment",
    "Recorded",
    "from_homes",
    "load_recorded",
    "save_recorded",
    "validate_environment",
]
