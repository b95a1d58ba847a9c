"""Inference API: load a trained model and draw box samples or exact log-likelihoods.

    predictor = load("runs/flowmaps-cpu-.../checkpoints")          # FlowMaps or MLP baseline
    predictor = load_pretrained("flowmaps")                        # or a pretrained model
    boxes = predictor.sample(tokens, queries, num_samples=25, key=jax.random.key(0))
    log_p = predictor.log_prob(tokens, queries, boxes)               # (B, Q, 25)

Shapes: ``tokens`` a :class:`~flowmaps_jax.tokens.SceneTokens` (B,), ``queries`` a
:class:`~flowmaps_jax.tokens.Queries` (B, Q); boxes normalised ``(y, x, h, w)`` (``pixels=True``:
pixel corners ``(y0, x0, y1, x1)``). Inputs are validated on the host (``ValueError`` naming the
argument), then one jitted core of the model's family runs. Scene b's samples come from
``split(key, B)[b]``, or ``key[b]`` for a batch of B keys (then independent of the other scenes
in the batch, and the same under ``predictor.sharded()``). Loading needs neither optax nor the
training code (:mod:`flowmaps_jax.store`).
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from flowmaps_jax import distributed, flow, tables
from flowmaps_jax.flowsim.config import FlowSimConfig
from flowmaps_jax.flowsim.homes.config import HomesConfig
from flowmaps_jax.flowsim.scenes import denormalise_boxes
from flowmaps_jax.model.config import ModelConfig
from flowmaps_jax.model.families import model_family
from flowmaps_jax.model.family import DENSITY_FACTOR, ModelFamily, canonical_inputs
from flowmaps_jax.model.flowmaps import check_inputs
from flowmaps_jax.model.flowmaps_family import DEFAULT_NUM_STEPS
from flowmaps_jax.resources import (
    check_resources,
    embedding_bytes,
    network_flops,
    solver_evaluations,
)
from flowmaps_jax.store import checkpoints, pretrained
from flowmaps_jax.store.model_spec import DEFAULT_FAMILY, check_params
from flowmaps_jax.tokens import FURNITURE, Queries, SceneTokens
from flowmaps_jax.validation import (
    check_array,
    check_concrete,
    check_flag,
    check_instance,
    check_int,
    check_key,
    check_real_array,
)
from flowmaps_jax.worlds import Inference, world_of_family

SOLVERS = flow.SOLVERS
FAR_LIMIT = 1e3
"""Boxes with a number beyond ±this (normalised units; the map is [0, 1]) have log-density −inf:
the noise prior alone puts exp(−5·10⁵) there, and the ODE would overflow to NaN."""


# --------------------------------------------------------------------------- validation helpers


def _query_shape(queries: Queries) -> tuple[int, int]:
    """(B, Q) of ``queries`` (a :class:`~flowmaps_jax.tokens.Queries` whose ``descriptor`` is a
    (B, Q) array), read before the sizes that depend on it are checked."""
    check_instance("queries", queries, Queries)
    check_array("queries.descriptor", queries.descriptor, (None, None))
    return np.shape(queries.descriptor)


def scene_keys(key: jax.Array, num_scenes: int) -> jax.Array:
    """One typed PRNG key per scene from a single typed key (split) or a batch of B keys (as
    given): the keys the family cores take. ``key`` is checked by the caller
    (:meth:`Predictor.sample`'s ``key`` rule, which also wraps raw ``jax.random.PRNGKey`` keys
    so both kinds share compiled code)."""
    return jax.random.split(key, num_scenes) if key.shape == () else key


# --------------------------------------------------------------------------- the predictor


@dataclasses.dataclass(frozen=True)
class Predictor:
    """A trained (or freshly initialised) model of any world, ready for inference: FlowMaps or
    the MLP baseline on 2-D FlowSim maps, or FlowMaps on FlowSim homes.

    params: the model's parameter pytree (EMA weights when loaded with ``use_ema=True``).
    model: its config (static: defines the compiled functions): a
        :class:`~flowmaps_jax.model.ModelConfig` on 2-D maps, a
        :class:`~flowmaps_jax.model.homes_family.HomesModelConfig` on homes.
    family_name: the name of its model family, as its run config's ``family``: "flowmaps"
        (flow matching) or "mlp" (Gaussian baseline; variant in ``model.baseline_variance``)
        on 2-D maps (:attr:`family` is the family itself), "flowmaps-homes" on homes. Its world
        (:func:`flowmaps_jax.worlds.world_of_family`) says how it runs (its ``inference``).
    flowsim: the 2-D simulator config the model was trained on (map size for pixel boxes).
    homes: a homes model's :class:`~flowmaps_jax.flowsim.homes.HomesConfig` (None on 2-D).
    source: where the params came from (checkpoint path) and step, for reports.
    mesh: a 1-D device mesh (:mod:`flowmaps_jax.distributed`) to split the scenes of every call
        over, params replicated; None (default) runs on one device. Results do not depend on
        it: scene b's samples come from its own key. See :meth:`sharded`.

    On 2-D maps: :meth:`sample`, :meth:`log_prob`, :meth:`table_weights`,
    :meth:`table_probabilities`, :meth:`gaussian` take scene tokens and queries. On homes:
    :meth:`probabilities` (receptacle weights), :meth:`sample` (boxes in metres) and
    :meth:`as_prior` take homes and queries (:mod:`flowmaps_jax.model.homes_inference`).
    """

    params: Any = dataclasses.field(repr=False)  # a pytree of arrays: too long to print
    model: Any
    family_name: str = "flowmaps"
    flowsim: FlowSimConfig = dataclasses.field(default_factory=FlowSimConfig)
    source: str | None = None
    step: int | None = None
    mesh: Mesh | None = dataclasses.field(default=None, repr=False)
    homes: HomesConfig | None = None

    def __post_init__(self):
        self._inference.check(self)  # ValueError naming the field (or listing the families)
        check_params(self.params, self._inference.spec_of(self), "params")
        if self.mesh is not None:
            check_instance("mesh", self.mesh, Mesh)
            # Replicate once, not at every call (a frozen dataclass: set the field directly).
            object.__setattr__(self, "params", distributed.replicate(self.params, self.mesh))

    @property
    def _inference(self) -> Inference:
        """How this model's world runs it (its family's world's inference)."""
        return world_of_family(self.family_name).inference

    def _scenes_only(self, method: str, *arguments) -> None:
        """ValueError unless this model reads 2-D scene tokens (``method`` names the call) and
        ``arguments`` are concrete (not traced: the methods check values on the host)."""
        check_concrete(f"Predictor.{method}", *arguments)
        if not self._inference.scenes:
            raise ValueError(f"{method} takes 2-D FlowSim scene tokens; this is a "
                             f"{self.family_name!r} model of FlowSim homes: use "
                             "probabilities(homes, queries, config) or sample(homes, "
                             "queries, num_samples, key, config=config)")

    def sharded(self, devices: int | None = None) -> Predictor:
        """This predictor with every call split over ``devices`` of this host's devices (None:
        all of them) by scenes; with one device, itself. Same results, faster on several
        accelerators. (On a multi-host job each host samples on its own devices.) A homes
        model runs on one device: itself."""
        mesh = distributed.local_mesh(devices) if self._inference.scenes else None
        return self if mesh is None else dataclasses.replace(self, mesh=mesh)

    def with_precision(self, precision: str) -> Predictor:
        """This predictor computing in ``precision`` ("float32" or "bf16" matmuls; the params
        stay float32). A model keeps the precision it was trained with unless changed here."""
        self._scenes_only("with_precision")
        return dataclasses.replace(self, model=dataclasses.replace(self.model,
                                                                   precision=precision))

    def _on_mesh(self, *trees):
        """The per-scene arguments split over the mesh (padded to a multiple of its size)."""
        return tuple(distributed.shard_rows(tree, self.mesh) for tree in trees)

    def _rows(self, out, b: int):
        """Drop the padding scenes :meth:`_on_mesh` added."""
        return out if self.mesh is None else jax.tree.map(lambda x: x[:b], out)

    @classmethod
    def from_params(cls, params, model: ModelConfig, family_name: str = "flowmaps",
                    flowsim: FlowSimConfig | None = None, **info) -> Predictor:
        """Wrap params you already have (tests, notebooks, a training loop) without a checkpoint.

        Example: ``Predictor.from_params(model.init_params(key, cfg), cfg)``.
        """
        return cls(params=params, model=model, family_name=family_name,
                   flowsim=FlowSimConfig() if flowsim is None else flowsim, **info)

    @property
    def family(self) -> ModelFamily:
        """The model family: init, the jitted cores, the memory estimate, the label."""
        return model_family(self.family_name)

    @property
    def name(self) -> str:
        """Row label for reports: "FlowMaps", "MLP (mean)" or "MLP (learned)"."""
        return self._inference.label(self)

    # ----------------------------------------------------------------------- validation

    def validate(self, tokens: SceneTokens, queries: Queries) -> tuple[int, int]:
        """Check tokens (B, S) and queries (B, Q) for this model; returns (B, Q).

        Raises ``ValueError`` for wrong shapes or dtypes, boxes outside [0, 1], unknown
        descriptors, a query that names a table instead of an object category, more token slots
        than ``flowsim.max_tokens``, τ out of range or τ_q ≤ τ.
        """
        self._scenes_only("validate", tokens, queries)
        check_inputs(self.model, tokens, queries,  # every field: type, dtype, shape, range, role
                     object_descriptors=self.flowsim.object_descriptors)
        b, q = np.shape(queries.descriptor)
        slots = np.shape(tokens.boxes)[1]
        if slots > self.flowsim.max_tokens:
            raise ValueError(f"tokens has {slots} token slots, more than the "
                             f"max_tokens={self.flowsim.max_tokens} of the maps the model was "
                             "trained on (flowsim.max_tokens)")
        return b, q

    def _check_request(self, what: str, b: int, q: int, n: int, with_density: bool,
                       num_steps: int, method: str, slots: int) -> None:
        """Refuse (ValueError) a request whose working memory or work would not fit the shared
        budget (:func:`flowmaps_jax.resources.check_resources`), before XLA tries: the rows'
        memory (``model.freq_bands`` included), the solver's ``num_steps`` (its time grid, and
        its evaluations one after another) and the FLOPs of every evaluation. The solver's
        arguments are checked already (:func:`flowmaps_jax.flow.check_solver_args`)."""
        rows = b * q * n
        factor = DENSITY_FACTOR if with_density else 1
        evaluations = solver_evaluations(num_steps, method) if self.family.uses_solver else 1
        per_row, per_map = network_flops(self.model, slots,
                                           self.family.gaussian is not None)
        check_resources(
            f"{what} of {b} scenes x {q} queries x {n} boxes with num_steps={num_steps} "
            f"(model.freq_bands={self.model.freq_bands})",
            num_bytes=self.family.request_bytes(self.model, rows, with_density)
            + rows * factor * embedding_bytes(self.model, 5) + 8 * num_steps,
            flops=rows * evaluations * factor * per_row + b * per_map,
            sequential=evaluations)

    # ----------------------------------------------------------------------- inference

    def sample(self, inputs, queries, num_samples: int, key,
               num_steps: int = DEFAULT_NUM_STEPS, **options):
        """``num_samples`` samples per query of the model, in its world's inputs and options:

        * 2-D maps: ``inputs`` scene tokens, ``options`` ``method="midpoint"``,
          ``pixels=False``, ``return_log_prob=False`` → boxes (B, Q, N, 4)
          (:meth:`_sample_scenes`);
        * homes: ``inputs`` homes, ``options`` ``config=None``, ``observed=None``,
          ``return_receptacles=False``, ``not_at=None`` → boxes (E, Q, N, 6) in metres
          (:func:`flowmaps_jax.model.homes_inference.sample`).
        """
        return self._inference.sample(self, inputs, queries, num_samples, key, num_steps,
                                      **options)

    def probabilities(self, homes, queries, config=None, observed=None,
                      not_at=None) -> jnp.ndarray:
        """A homes model's receptacle weights (E, Q, R) for ``homes`` and ``queries`` (``config``:
        the homes' config, default the model's; ``observed`` (E, T, M) bool: the hours each
        object was seen, None for every hour, required by a model trained on partial
        observation; ``not_at`` (E, T, M, R) bool: looked for on r at hour t, not there),
        read without sampling
        (:func:`flowmaps_jax.model.homes_inference.probabilities`); a 2-D model's are
        :meth:`table_weights`."""
        return self._inference.probabilities(self, homes, queries, config, observed, not_at)

    def as_prior(self, config=None, observed=None, not_at=None):
        """A homes model as a prior ``(homes, queries) -> (E, Q, R)`` (:meth:`probabilities`)."""
        return self._inference.as_prior(self, config, observed, not_at)

    def _sample_scenes(self, tokens: SceneTokens, queries: Queries, num_samples: int, key,
                       num_steps: int = DEFAULT_NUM_STEPS, method: str = "midpoint",
                       pixels: bool = False, return_log_prob: bool = False):
        """Draw num_samples boxes per query → (B, Q, num_samples, 4).

        Normalised (y, x, h, w) by default; ``pixels=True`` gives pixel corners (y0, x0, y1, x1).
        key: one PRNG key (split over the B scenes) or one key per scene (B,). The solver
        (``num_steps`` grid points, ``method`` "midpoint" or "euler") is ignored by the MLP.
        Same key and inputs → the same samples.

        ``return_log_prob=True`` returns ``(boxes, log_p)`` with log_p (B, Q, num_samples) the
        exact log-density of each normalised box, from the same forward solve (FlowMaps
        integrates the augmented ODE with the exact divergence: no second, backward solve;
        the boxes equal those without it, to float rounding; the mixture head sums the near
        tables' terms, so it solves backwards once more). Planners weigh samples with it.
        """
        check_concrete("Predictor.sample", tokens, queries, key)
        scenes, _ = _query_shape(queries)
        key = check_key(key, "key", ((), (scenes,)))  # one key, or one per scene
        num_samples = check_int("num_samples", num_samples)
        pixels = check_flag("pixels", pixels)
        return_log_prob = check_flag("return_log_prob", return_log_prob)
        num_steps, method = flow.check_solver_args(num_steps, method)
        b, q = self.validate(tokens, queries)
        self._check_request("sample", b, q, num_samples, return_log_prob, num_steps, method,
                            np.shape(tokens.boxes)[1])
        keys = scene_keys(key, b)
        tokens, queries, keys = self._on_mesh(*canonical_inputs(tokens, queries), keys)
        family = self.family
        draw = family.sample_with_log_prob if return_log_prob else family.sample
        out = self._rows(draw(self.params, self.model, tokens, queries, keys, num_samples,
                              num_steps=num_steps, method=method), b)
        boxes, log_p = out if return_log_prob else (out, None)
        if pixels:
            boxes = denormalise_boxes(boxes, self.flowsim)
        return (boxes, log_p) if return_log_prob else boxes

    def table_probabilities(self, tokens: SceneTokens, queries: Queries, num_samples: int, key,
                            method: str = "samples", **sample_kwargs) -> jnp.ndarray:
        """Mass (B, Q, S + 1) on each table of the map (furniture tokens; zero on other tokens)
        plus an "off" mass in the last entry: the prior a search planner calls. ``method``
        "samples" counts ``num_samples`` samples per query; "weights" reads the route head's
        mixture weights (:meth:`table_weights`, no sampling noise). See
        :func:`flowmaps_jax.tables.table_probabilities` (also ``search.table_probabilities``)."""
        self._scenes_only("table_probabilities", tokens, queries, key)
        return tables.table_probabilities(self, tokens, queries, num_samples, key,
                                          method=method, **sample_kwargs)

    def log_prob(self, tokens: SceneTokens, queries: Queries, x,
                 num_steps: int = DEFAULT_NUM_STEPS, method: str = "midpoint") -> jnp.ndarray:
        """Exact log-density (B, Q, N) of normalised boxes x (B, Q, N, 4) (y, x, h, w).

        FlowMaps: instantaneous change of variables with the exact divergence, integrated back
        from t = 1 to 0 on ``num_steps`` grid points (the only error is the ODE discretisation).
        MLP: the closed-form diagonal Gaussian.
        """
        self._scenes_only("log_prob", tokens, queries, x)
        scenes, per_scene = _query_shape(queries)
        x = check_real_array("x", x, (scenes, per_scene, None, 4))
        if 0 in np.shape(x):
            raise ValueError(f"x must not be empty (at least one box per query); got shape "
                             f"{tuple(np.shape(x))}")
        num_steps, method = flow.check_solver_args(num_steps, method)
        b, q = self.validate(tokens, queries)
        x = jnp.asarray(x, jnp.float32)  # (B, Q, N, 4), checked: N >= 1
        self._check_request("log_prob", b, q, x.shape[2], True, num_steps, method,
                            np.shape(tokens.boxes)[1])
        far = jnp.any(jnp.abs(x) > FAR_LIMIT, axis=-1)  # (B, Q, N): density 0, not NaN
        x = jnp.where(far[..., None], 0.5, x)
        tokens, queries, x = self._on_mesh(*canonical_inputs(tokens, queries), x)
        log_p = self._rows(self.family.log_prob(
            self.params, self.model, tokens, queries, x, num_steps=num_steps, method=method), b)
        return jnp.where(far, -jnp.inf, log_p)

    @property
    def has_table_weights(self) -> bool:
        """Whether :meth:`table_weights` applies: FlowMaps with a mixture, pointer or route
        read-out (on 2-D maps)."""
        return self._inference.scenes and self.family.has_table_weights(self.model)

    def table_weights(self, tokens: SceneTokens, queries: Queries) -> jnp.ndarray:
        """FlowMaps with a read-out head (``model.head`` "mixture", "pointer" or "route"): the
        mass (B, Q, S + 1) its mixture puts on each table of the map, read from the model without
        sampling (:func:`flowmaps_jax.model.flowmaps_family.table_weights`). Weight on tokens
        that are not tables goes to the "off" entry (last). The mixture head's weights are its
        posterior over tables itself (its samples draw their table from them); the route head's
        samples follow them while its residual is zero; the pointer head's are its weights at
        t = 0.
        """
        self._scenes_only("table_weights", tokens, queries)
        if not self.has_table_weights:
            raise ValueError("table_weights needs a FlowMaps model with model.head 'mixture', "
                             f"'pointer' or 'route' (explicit mixture weights); this one is "
                             f"{self.name} with "
                             f"head={self.model.head!r}: use table_probabilities with samples")
        b, _ = self.validate(tokens, queries)
        tables.check_query_objects(tokens, queries)  # as table_probabilities' samples do
        s = np.shape(tokens.boxes)[1]
        is_table = jnp.asarray(tokens.mask, bool) & (jnp.asarray(tokens.kind) == FURNITURE)
        tokens, queries = self._on_mesh(*canonical_inputs(tokens, queries))
        w = self._rows(self.family.table_weights(self.params, self.model, tokens, queries), b)
        w = jnp.pad(w, ((0, 0), (0, 0), (0, s - w.shape[-1])))  # trimmed padding back
        w = jnp.where(is_table[:, None, :], w, 0.0)
        return jnp.concatenate([w, 1.0 - w.sum(-1, keepdims=True)], axis=-1).clip(0.0, 1.0)

    def gaussian(self, tokens: SceneTokens, queries: Queries) -> tuple[jnp.ndarray, jnp.ndarray]:
        """MLP baseline only: (mean, log_var), each (B, Q, 4), of the predicted Gaussian."""
        self._scenes_only("gaussian", tokens, queries)
        if self.family.gaussian is None:
            raise ValueError("gaussian() is only defined for the MLP baseline (family_name='mlp')")
        b, _ = self.validate(tokens, queries)
        tokens, queries = self._on_mesh(*canonical_inputs(tokens, queries))
        return self._rows(self.family.gaussian(self.params, self.model, tokens, queries), b)


# --------------------------------------------------------------------------- loading


def _from_weights(weights, source: str) -> Predictor:
    """The predictor of verified weights (a checkpoint's or a pretrained model's): their
    family, model config and the world config their spec holds (``flowsim`` or ``homes``)."""
    spec = weights.spec
    return Predictor(params=weights.params, model=spec.model, family_name=spec.family_name,
                     source=source, step=weights.step,
                     **world_of_family(spec.family_name).inference.fields(spec))


def load(checkpoint_dir: str | pathlib.Path, which: str = "best",
         use_ema: bool = True, step: int | None = None) -> Predictor:
    """Load a trained model from a checkpoint directory (or a run directory holding one).

    which: "best" (lowest validation loss; falls back to the latest save when no validation
    has run yet) or "latest". step: load this saved step instead (from last/ or best/), e.g.
    the older intact step that the error about a damaged newest step names. use_ema: the EMA
    weights (default) or the raw training weights. The model family (FlowMaps, the MLP
    baseline, the homes model) and sizes come from the config saved with the checkpoint. Every
    array is checked against the checksums saved with it and for NaN/inf. Raises
    ``ValueError`` for a missing, empty, damaged or non-finite checkpoint (naming the newest
    intact step when there is one).
    """
    weights = checkpoints.load_weights(checkpoint_dir, which, use_ema, step)
    return _from_weights(weights, str(weights.root))


def load_pretrained(name: str, directory: str | pathlib.Path = pretrained.PRETRAINED_DIR
                    ) -> Predictor:
    """A trained model packaged with flowmaps-jax (:data:`flowmaps_jax.store.pretrained.NAMES`:
    ``"flowmaps"``, ``"mlp"``, ``"mlp-learned"``, the habit worlds' models, ``"flowmaps-homes"``),
    the same :class:`Predictor` as :func:`load` of its run. ``directory``: where the weights are
    (the package's ``pretrained/`` folder by default). Raises ``ValueError`` for an unknown name
    (listing the names), or weights that are missing, damaged (SHA-256 mismatch) or do not fit
    their config. See :mod:`flowmaps_jax.store.pretrained`."""
    weights = pretrained.read_weights(name, directory)
    return _from_weights(weights, f"pretrained:{weights.name}")


PRETRAINED_PREFIX = pretrained.PREFIX


def load_model(spec: str, which: str = "best", devices: int | None = None) -> Predictor:
    """What the CLIs' ``--checkpoint``/``--baseline`` name: a run or checkpoint directory
    (:func:`load`), or ``pretrained:NAME`` (:func:`load_pretrained`), split over ``devices``
    devices (None: every device JAX sees; see :meth:`Predictor.sharded`)."""
    if spec.startswith(PRETRAINED_PREFIX):
        predictor = load_pretrained(spec[len(PRETRAINED_PREFIX):])
    else:
        predictor = load(spec, which=which)
    return predictor.sharded(devices)


def stored_run(spec: str, which: str = "best") -> tuple[str, dict]:
    """(model family, run config) stored with what a CLI's ``--checkpoint`` names (a run or
    checkpoint directory, or ``pretrained:NAME``: its family and {}), read once and without
    the weights: the CLIs find the model's world from them before loading it."""
    if spec.startswith(PRETRAINED_PREFIX):
        return pretrained.describe(spec[len(PRETRAINED_PREFIX):])["kind"], {}
    config = checkpoints.stored_config(spec, which)
    return config.get("model_kind", DEFAULT_FAMILY), config
