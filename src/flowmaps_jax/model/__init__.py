"""FlowMaps model (Map Encoder + CDiT velocity network) and the MLP-Gaussian baseline.

Pure functions over explicit params pytrees; see ``docs/design.md`` for the shapes.
"""

from flowmaps_jax.model.baseline import (
    baseline_log_prob,
    baseline_loss,
    baseline_predict,
    init_baseline,
)
from flowmaps_jax.model.config import ModelConfig
from flowmaps_jax.model.flowmaps import (
    Context,
    check_inputs,
    encode,
    forward,
    init_params,
    make_velocity_fn,
    velocity,
)

__all__ = [
    "Context",
    "ModelConfig",
    "baseline_log_prob",
    "baseline_loss",
    "baseline_predict",
    "check_inputs",
    "encode",
    "forward",
    "init_baseline",
    "init_params",
    "make_velocity_fn",
    "velocity",
]
