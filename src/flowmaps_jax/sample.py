"""Deprecated alias of flowmaps_jax.predictor, removed next release."""

from flowmaps_jax.predictor import (  # noqa: F401
    DEFAULT_NUM_STEPS,
    FAR_LIMIT,
    PRETRAINED_PREFIX,
    SOLVERS,
    Predictor,
    load,
    load_model,
    load_pretrained,
    scene_keys,
)
