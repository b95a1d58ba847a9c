"""FlowSim: procedurally generated maps in which household objects move along routines
(specification: docs/flowsim.md; defaults: the paper's). Every public function checks its
arguments before anything is jitted (``ValueError`` naming the argument).
"""

from flowmaps_jax.flowsim.config import (
    DYNAMICS,
    HABITS,
    ORDERINGS,
    SHAPES,
    FlowSimConfig,
    FurnitureKind,
    ObjectCategory,
)
from flowmaps_jax.flowsim.dynamics import exact_posterior, transition_matrix
from flowmaps_jax.flowsim.generate import Scenes, generate, validate_scenes
from flowmaps_jax.flowsim.habits import empirical_frequency, history_posterior
from flowmaps_jax.flowsim.scenes import (
    denormalise_boxes,
    draw_query_times,
    load_scenes,
    make_train_batch,
    normalise_boxes,
    save_scenes,
    scene_tokens,
    slot_boxes,
    train_split,
    validation_split,
)
from flowmaps_jax.flowsim.worlds import HABIT_WORLDS, world_config, world_of

__all__ = [
    "DYNAMICS",
    "HABITS",
    "HABIT_WORLDS",
    "ORDERINGS",
    "SHAPES",
    "FlowSimConfig",
    "FurnitureKind",
    "ObjectCategory",
    "Scenes",
    "denormalise_boxes",
    "draw_query_times",
    "empirical_frequency",
    "exact_posterior",
    "generate",
    "history_posterior",
    "load_scenes",
    "make_train_batch",
    "normalise_boxes",
    "save_scenes",
    "scene_tokens",
    "slot_boxes",
    "train_split",
    "transition_matrix",
    "validate_scenes",
    "validation_split",
    "world_config",
    "world_of",
]
