"""The model families by name: ``MODEL_FAMILIES[name]`` is a :class:`ModelFamily`.

The name is what a run config stores (``TrainConfig.model_kind``) and what
:class:`flowmaps_jax.predictor.Predictor` carries (``Predictor.kind``). Adding a family is one
module that defines its ``FAMILY`` (see :mod:`flowmaps_jax.model.baseline`) plus one line here;
to train it, one more line registers its loss in :data:`flowmaps_jax.training.objectives.LOSSES`.
"""

from __future__ import annotations

from flowmaps_jax.model import baseline, inference
from flowmaps_jax.model.family import ModelFamily

MODEL_FAMILIES: dict[str, ModelFamily] = {
    "flowmaps": inference.FAMILY,  # FlowMaps; its read-out head is ModelConfig.head
    "mlp": baseline.FAMILY,  # the MLP-Gaussian baseline
}


def model_family(name: str) -> ModelFamily:
    """The family registered as ``name``, or ``ValueError`` listing the names."""
    if not isinstance(name, str) or name not in MODEL_FAMILIES:
        raise ValueError(f"model kind must name a model family, one of "
                         f"{tuple(MODEL_FAMILIES)}; got {name!r}")
    return MODEL_FAMILIES[name]
