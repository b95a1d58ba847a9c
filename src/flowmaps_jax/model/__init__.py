"""FlowMaps model (Map Encoder + CDiT velocity network) and the MLP-Gaussian baseline: pure
functions over explicit params pytrees; each family lives in one module and is registered in
:data:`MODEL_FAMILIES` (docs/design.md)."""

from flowmaps_jax.model.baseline import (
    baseline_log_prob,
    baseline_loss,
    baseline_predict,
    init_baseline,
)
from flowmaps_jax.model.config import ModelConfig
from flowmaps_jax.model.families import MODEL_FAMILIES, model_family
from flowmaps_jax.model.family import LossOptions, ModelFamily
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
    "MODEL_FAMILIES",
    "Context",
    "LossOptions",
    "ModelConfig",
    "ModelFamily",
    "baseline_log_prob",
    "baseline_loss",
    "baseline_predict",
    "check_inputs",
    "encode",
    "forward",
    "init_baseline",
    "init_params",
    "make_velocity_fn",
    "model_family",
    "velocity",
]
