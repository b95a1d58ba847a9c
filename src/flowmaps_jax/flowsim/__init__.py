"""FlowSim: procedurally generated maps in which household objects move along routines.

The specification (the map, furniture, objects, visiting orders, the Markov dynamics and
``schedule_jitter``, habits, the exact posterior) is docs/flowsim.md; the defaults are the
paper's (``FlowSimConfig``).

Entry points: ``generate(key, num_envs, config) -> Scenes`` (jitted, vectorised over
environments); ``exact_posterior``, ``transition_matrix``, ``history_posterior``; model-facing
views in ``flowsim.scenes`` (normalised boxes, ``scene_tokens``, ``slot_boxes``,
``draw_query_times``, ``make_train_batch``, the splits, ``save_scenes`` / ``load_scenes``);
``validate_scenes``. Every public function checks its arguments before anything is jitted
(``ValueError`` naming the argument).
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
from flowmaps_jax.flowsim.worlds import WORLDS, world_config, world_of

__all__ = [
    "DYNAMICS",
    "HABITS",
    "ORDERINGS",
    "SHAPES",
    "WORLDS",
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
