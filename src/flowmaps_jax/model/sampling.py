"""Deprecated alias of flowmaps_jax.model.inference (and model.baseline), removed next release."""

from flowmaps_jax.model.baseline import (  # noqa: F401
    gaussian_log_prob,
    gaussian_sample,
    gaussian_sample_with_log_prob,
)
from flowmaps_jax.model.flowmaps_family import (  # noqa: F401
    DEFAULT_NUM_STEPS,
    flow_log_prob,
    flow_sample,
    flow_sample_with_log_prob,
    flow_space_log_det,
    from_flow_space,
    route_mixture_log_prob,
    table_weights,
    to_flow_space,
)
