"""FlowSim scenes: the ``Scenes`` pytree and ``generate(key, num_envs, config)``.

(Stub by the lead: the dataclass fields are the contract; ``generate`` is filled in by the FlowSim work.)
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct


@struct.dataclass
class Scenes:
    """E environments with F furniture pieces, M objects (one per category), T timesteps.

    furniture_boxes: (E, F, 4) float32 pixels (y0, x0, y1, x1), y1/x1 exclusive (h = y1 - y0).
    furniture_kind: (E, F) int32 descriptor id of each piece's furniture kind.
    object_kind: (E, M) int32 descriptor id of each object (category order of the config).
    object_size: (E, M) float32 side of each object's square box in pixels.
    visit_order: (E, M, F) int32 furniture indices in visiting order, padded with -1.
    num_slots: (E, M) int32 number of valid entries in visit_order (furniture of that kind).
    slot: (E, T, M) int32 position along visit_order at each timestep (0 at t = 0).
    object_boxes: (E, T, M, 4) float32 pixels (y0, x0, y1, x1), centred on the current table.
    layout_redraws: (E,) int32 how many times each environment's layout was redrawn.
    """

    furniture_boxes: jnp.ndarray
    furniture_kind: jnp.ndarray
    object_kind: jnp.ndarray
    object_size: jnp.ndarray
    visit_order: jnp.ndarray
    num_slots: jnp.ndarray
    slot: jnp.ndarray
    object_boxes: jnp.ndarray
    layout_redraws: jnp.ndarray

    @property
    def num_envs(self) -> int:
        return self.furniture_boxes.shape[0]
