"""The model families by name: ``MODEL_FAMILIES[name]`` is a :class:`ModelFamily`, the one registry.

The name is what a run config holds (``TrainConfig.family``, stored in ``config.json`` under the
older key ``"model_kind"``) and what :class:`flowmaps_jax.predictor.Predictor` carries
(``Predictor.family_name``, ``ModelSpec.family_name``; a pretrained model's ``.json`` stores it
as ``"kind"``). The on-disk keys keep their old names so that every checkpoint and the
pretrained weights read as before. Adding a
family is one module that defines its ``FAMILY`` (network, loss, cores; see
:mod:`flowmaps_jax.model.baseline`) plus one line here; training then finds its loss through
the family (``ModelFamily.loss``).
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
