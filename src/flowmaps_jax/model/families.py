"""The model families by name: ``MODEL_FAMILIES[name]`` is a :class:`ModelFamily`, the one
registry (the name is a run config's ``family``, ``"model_kind"`` on disk).
"""

from __future__ import annotations

from flowmaps_jax.model import baseline, flowmaps_family
from flowmaps_jax.model.family import ModelFamily

MODEL_FAMILIES: dict[str, ModelFamily] = {
    "flowmaps": flowmaps_family.FAMILY,  # FlowMaps; its read-out head is ModelConfig.head
    "mlp": baseline.FAMILY,  # the MLP-Gaussian baseline
}


def model_family(name: str) -> ModelFamily:
    """The family registered as ``name``, or ``ValueError`` listing the names."""
    if not isinstance(name, str) or name not in MODEL_FAMILIES:
        raise ValueError(f"model family must be one of {tuple(MODEL_FAMILIES)}; got {name!r}")
    return MODEL_FAMILIES[name]
