"""``ModelConfig``: the sizes of the FlowMaps network and of the MLP baseline, frozen (a static
``jax.jit`` argument); the defaults are the paper's size, the presets live in
:mod:`flowmaps_jax.training.config`."""

from __future__ import annotations

import dataclasses

from flowmaps_jax.validation import check_flag
from flowmaps_jax.validation.fields import Choice, Int, Real, check_fields, check_keys

BASELINE_VARIANCES = ("mean", "learned")
HEADS = ("velocity", "pointer", "route", "mixture")
PRECISIONS = ("float32", "bf16")
POINTER_WIDTHS = ("absolute", "relative")
WEIGHT_ATTENTION = ("cross", "self")
WEIGHT_GEOMETRY = ("none", "relative", "offsets")
REMOVED_FIELDS = ("max_tokens",)
"""Fields that older configs carry and that configured nothing: :meth:`ModelConfig.from_dict`
drops them, so configs saved with them still load."""


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Network sizes.

    dim: model width D (tokens, conditioning, query token).
    encoder_layers: pre-norm transformer layers in the Map Encoder.
    cdit_blocks: cross-attention-only CDiT blocks in the velocity network.
    heads: attention heads (must divide ``dim``).
    mlp_ratio: hidden width of every MLP is ``mlp_ratio * dim``.
    dropout: dropout rate in the encoder layers and the CDiT residual branches.
    num_descriptors: number of descriptor ids (FlowSim: 6 colours).
    tau_max: number of timesteps; ``tau`` and ``tau_q`` lie in ``[0, tau_max)``.
    freq_bands: sinusoidal frequencies per scalar (each gives a sin and a cos feature).
    max_frequency: highest angular frequency (radians per unit); frequencies are geometric in
        ``[1, max_frequency]``.
    baseline_variance: MLP baseline variant, ``"mean"`` (unit variance, as the paper's reference) or
        ``"learned"`` (diagonal log-variance trained by Gaussian NLL).
    baseline_hidden: hidden width of the MLP baseline's head.
    box_offset, box_scale: FlowMaps' flow runs on z = box_scale · (box − box_offset) ((0, 1):
        the identity).
    head: the velocity read-out: ``"velocity"`` (the paper's linear head), ``"pointer"``
        (:mod:`~flowmaps_jax.model.readout`), ``"route"`` (:mod:`~flowmaps_jax.model.route`) or
        ``"mixture"`` (:mod:`~flowmaps_jax.model.mixture`).
    weight_blocks: blocks of the mixture head's table-weight rows (``head="mixture"``).
    weight_attention: how those rows attend (``head="mixture"``): ``"cross"`` (CDiT blocks over
        the map's context tokens) or ``"self"`` (transformer layers over one object's rows).
    weight_geometry: what each table-weight row knows of where its table lies (``head="mixture"``):
        ``"none"`` (its context token), ``"relative"`` (Fourier features of its centre and of its
        angle around the map centre, relative to the object's table) or ``"offsets"`` (the
        centre features and the distance, no angle).
    pointer_width_scale: the pointer/route widths' log-variance is this × its parameter.
    pointer_widths: ``"absolute"`` (flow units) or ``"relative"`` (fractions of the object's
        own height and width, as the protocol's q).
    condition_on_dtau: add an embedding of Δτ = τ_q − τ to the CDiT conditioning.
    precision: matmul and attention precision, ``"float32"`` or ``"bf16"``
        (:mod:`flowmaps_jax.model.precision`).
    history: H, the maps the Map Encoder reads (the one at τ and the H − 1 before it).
    """

    dim: int = 256
    encoder_layers: int = 8
    cdit_blocks: int = 8
    heads: int = 8
    mlp_ratio: int = 4
    dropout: float = 0.1
    num_descriptors: int = 6
    tau_max: int = 20
    freq_bands: int = 16
    max_frequency: float = 1000.0
    baseline_variance: str = "mean"
    baseline_hidden: int = 512
    box_offset: float = 0.0
    box_scale: float = 1.0
    head: str = "velocity"
    pointer_width_scale: float = 1.0
    pointer_widths: str = "absolute"
    condition_on_dtau: bool = False
    precision: str = "float32"
    history: int = 1
    weight_blocks: int = 2
    weight_attention: str = "cross"
    weight_geometry: str = "none"

    def __post_init__(self):
        check_fields(self, _RULES, prefix="ModelConfig.", store=False)
        if self.dim % self.heads:
            raise ValueError(
                f"ModelConfig.dim={self.dim} must be divisible by ModelConfig.heads={self.heads}")

    @property
    def head_dim(self) -> int:
        """Width of one attention head, ``dim // heads``."""
        return self.dim // self.heads

    @classmethod
    def from_dict(cls, data: dict) -> ModelConfig:
        """The config a JSON dict describes (unknown keys: ``ValueError`` naming them; the
        :data:`REMOVED_FIELDS` dropped)."""
        known = [*(field.name for field in dataclasses.fields(cls)), *REMOVED_FIELDS]
        data = check_keys("the model config (ModelConfig.from_dict)", data, known,
                          what="unknown keys")
        return cls(**{k: v for k, v in data.items() if k not in REMOVED_FIELDS})


_RULES = {
    **{name: Int() for name in ("dim", "encoder_layers", "cdit_blocks", "heads", "mlp_ratio",
                                "num_descriptors", "freq_bands", "baseline_hidden", "history",
                                "weight_blocks")},
    "tau_max": Int(2),
    "dropout": Real(0.0, 1.0, high_open=True),
    "max_frequency": Real(1.0),
    "box_scale": Real(0.0, low_open=True),
    "box_offset": Real(),
    "head": Choice(HEADS),
    "pointer_width_scale": Real(0.0, 1000.0, low_open=True),
    "pointer_widths": Choice(POINTER_WIDTHS),
    "weight_attention": Choice(WEIGHT_ATTENTION),
    "weight_geometry": Choice(WEIGHT_GEOMETRY),
    "condition_on_dtau": check_flag,
    "baseline_variance": Choice(BASELINE_VARIANCES),
    "precision": Choice(PRECISIONS),
}
"""What each field of :class:`ModelConfig` may hold (checked, not converted)."""
