"""FlowSim: procedurally generated maps in which household objects move along routines.

The model (defaults are the paper's; see ``FlowSimConfig``)
-----------------------------------------------------------
* **Map.** A square map of ``map_size`` = 256 px holding F = 10 axis-aligned, non-overlapping
  pieces of furniture (touching allowed), at least ``min_per_kind`` = 3 of each furniture kind
  (kitchen_table, office_desk, dining_table), the extras of random kinds. Heights and widths are
  uniform integers in [0.10, 0.25] × map side. Layouts are drawn by vectorised rejection
  sampling and are always valid: a layout in which some piece finds no free spot is redrawn
  whole (``Scenes.layout_redraws`` counts how often), never thinned out.
* **Objects.** One object per category; categories are data (``ObjectCategory``: name,
  descriptor id, colour, shape, furniture kind, ordering rule), so adding one is a config change.
  Paper: fork (red, 0) on kitchen tables, bottle (green, 1) on dining tables, remote (blue, 2) on
  office desks. An object is a square of side s = max(5, ⌊0.4 · min side of its start table⌋)
  px, centred on the centre of the table it is on.
* **Visiting orders.** Each category visits the tables of its kind in a cyclic order: by the
  angle of the table centre around the map centre (0 up, clockwise on screen) ascending
  ("clockwise", fork) or descending ("counter_clockwise", bottle), or by the centre's y
  ("top_to_bottom", remote; also "bottom_to_top") or x ("left_to_right"). The object starts at
  position 0 of its order.
* **Dynamics.** ``"markov"`` (paper): each timestep, independently per object, stay with 0.2,
  advance one place with 0.7, advance two with 0.1, cyclically over the K tables of its kind;
  T = 20 timesteps. ``"schedule_jitter"`` (the reference code's variant): position
  (t + o_t) mod K with an independent offset o_t ∈ {−1, 0, +1} drawn with 0.1 / 0.7 / 0.2.
* **Habits** (``FlowSimConfig.habits``, named mixtures in ``WORLDS``): each object may instead
  follow its own habit, drawn once per environment — the routine above, *preferences* (returns
  to one or two favourite places) or *dynamic* (moves almost every step, to nearer places more
  often). ``history_posterior`` is the exact posterior given the last H observations, the
  hidden habit marginalised over a finite hypothesis set (:mod:`flowmaps_jax.flowsim.habits`).
  The default (routine only) generates exactly as before habits existed.
* **Exact posterior.** Knowing the slot now, the Markov slot Δτ steps ahead is the Δτ-fold
  convolution of (0.2, 0.7, 0.1) shifted by the current slot and folded modulo K — equivalently
  ``onehot(slot) @ P^Δτ`` with the K × K ``transition_matrix`` P. ``exact_posterior`` returns it
  (padded to F). Under "schedule_jitter" it depends only on the absolute query time τ + Δτ.

Entry points
------------
``generate(key, num_envs, config) -> Scenes`` (jit-compiled, vectorised over environments,
rollouts in ``lax.scan``); ``exact_posterior``, ``transition_matrix``; model-facing views in
``flowsim.scenes`` (normalised boxes, ``scene_tokens``, ``slot_boxes``, ``draw_query_times``,
``make_train_batch``, ``train_split`` / ``validation_split``,
``save_scenes`` / ``load_scenes``); ``validate_scenes`` checks a ``Scenes`` (every public function
here checks its arguments with :mod:`flowmaps_jax.validation` before anything is jitted, and
raises ``ValueError`` naming the argument).
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
