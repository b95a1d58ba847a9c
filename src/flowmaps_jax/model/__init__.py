"""FlowMaps model (Map Encoder + CDiT velocity network) and the MLP-Gaussian baseline.

Pure functions over explicit params pytrees; see ``docs/design.md`` for the shapes. Each model
family (:class:`ModelFamily`: init, training loss, jitted inference cores, memory estimate,
label) lives in one module (:mod:`~flowmaps_jax.model.flowmaps_family` over the network in
:mod:`~flowmaps_jax.model.flowmaps`; :mod:`~flowmaps_jax.model.baseline`) and is registered by
name in :data:`MODEL_FAMILIES` (:mod:`flowmaps_jax.model.families`), the one registry.
"""

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
