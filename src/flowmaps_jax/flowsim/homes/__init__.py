"""FlowSim homes: 3-D multi-room homes, hourly object schedules and their exact posterior.

Modules, one idea each: ``vocabulary`` (room types, receptacle and object classes, as data),
``config`` (``HomesConfig``), ``floorplan`` (rooms on a grid, doors, geodesic distances),
``furnish`` (receptacles in rooms by type, objects on allowed receptacles, cycles),
``schedules`` (the four regimes' hourly transition laws), ``world`` (the ``Homes`` pytree and
its field table), ``rollout`` (``generate_homes``), ``posterior`` (the exact posterior, also
given a history, or filtered over a partial one), ``export`` (``save_homes`` /
``load_homes``). See docs/flowsim.md, "Homes".
"""

from flowmaps_jax.flowsim.homes.config import (
    DEFAULT_HOMES_CONFIG,
    MAX_OBJECTS,
    NUM_CONTEXTS,
    REGIMES,
    HomesConfig,
    context_of,
)
from flowmaps_jax.flowsim.homes.export import homes_schema, load_homes, save_homes
from flowmaps_jax.flowsim.homes.floorplan import geodesic_distances, room_adjacency
from flowmaps_jax.flowsim.homes.posterior import (
    favourite_weights,
    filtered_posterior,
    homes_history_posterior,
    homes_posterior,
    transition_matrix,
)
from flowmaps_jax.flowsim.homes.queries import DEFAULT_HORIZONS, HomesQueries, draw_queries
from flowmaps_jax.flowsim.homes.rollout import generate_homes, homes_from_keys, simulate
from flowmaps_jax.flowsim.homes.vocabulary import ObjectClass, ReceptacleClass, RoomType
from flowmaps_jax.flowsim.homes.world import FIELDS, Homes, object_boxes, validate_homes

__all__ = [
    "DEFAULT_HOMES_CONFIG",
    "DEFAULT_HORIZONS",
    "FIELDS",
    "MAX_OBJECTS",
    "NUM_CONTEXTS",
    "REGIMES",
    "Homes",
    "HomesConfig",
    "HomesQueries",
    "ObjectClass",
    "ReceptacleClass",
    "RoomType",
    "context_of",
    "draw_queries",
    "favourite_weights",
    "filtered_posterior",
    "generate_homes",
    "geodesic_distances",
    "homes_from_keys",
    "homes_history_posterior",
    "homes_posterior",
    "homes_schema",
    "load_homes",
    "object_boxes",
    "room_adjacency",
    "save_homes",
    "simulate",
    "transition_matrix",
    "validate_homes",
]
