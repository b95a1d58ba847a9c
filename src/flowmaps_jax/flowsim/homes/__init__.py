"""FlowSim homes: 3-D multi-room homes, hourly object schedules and their exact posterior
(docs/flowsim.md, "Homes")."""

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
