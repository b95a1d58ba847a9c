"""The 2-D FlowSim world: its training data, batch sampler, objective and resource estimate.

* :func:`load_splits` generates the fixed train / validation splits once per process.
* :func:`default_batch_fn` ``(key, scenes) -> TrainBatch`` draws B scenes with Q queries each,
  inside the jitted train step (no host round trip).
* With ``data="endless"``, :func:`endless_scenes` regenerates a chunk of fresh environments every
  :func:`endless_chunk_steps` steps, from a key that depends only on (data key, chunk).
* :func:`make_val_batches` fixes the validation batches of a run (its val passes use them).
* :func:`objective` binds the run's model family (:data:`~flowmaps_jax.model.families.
  MODEL_FAMILIES`) to its recipe; :func:`resource_estimate` sizes a run.

``cfg`` is a ``flowmaps_jax.training.config.TrainConfig`` throughout.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from flowmaps_jax.boxes import from_centre, to_centre
from flowmaps_jax.distributed import host_part
from flowmaps_jax.flowsim.config import FlowSimConfig
from flowmaps_jax.flowsim.generate import generate, layout_bytes
from flowmaps_jax.flowsim.scenes import make_train_batch, train_split, validation_split
from flowmaps_jax.model.config import ModelConfig
from flowmaps_jax.model.families import MODEL_FAMILIES, model_family
from flowmaps_jax.model.family import LossOptions, ModelFamily
from flowmaps_jax.model.flowmaps_family import DEFAULT_NUM_STEPS
from flowmaps_jax.resources import embedding_bytes, network_flops, solver_evaluations
from flowmaps_jax.tables import protocol_sigma
from flowmaps_jax.tokens import TrainBatch, check_train_batch, trim_padding
from flowmaps_jax.validation import check_instance, check_int
from flowmaps_jax.worlds.world import Inference, World, chunk_key

# batch_fn(key, scenes) -> TrainBatch, traceable
BatchFn = Callable[[jax.Array, Any], TrainBatch]

# Fixed seed offset of the val batches' key: val passes at different steps use the same noise.
EVAL_KEY_SALT = 0x5EED


def load_splits(cfg, log: Callable[[str], None] = print, mesh=None):
    """(train scenes or None for endless data, validation scenes), generated in-process.

    The splits are fixed datasets (their seeds live in ``flowsim.scenes``), so they are cached
    per (simulator config, sizes) for later runs in the same process. ``mesh`` splits the
    generation over devices (same environments). On a multi-host job each host generates only
    its share of the training environments (:func:`host_train_part`); no data crosses hosts.
    """
    train_envs = cfg.train_envs if cfg.data == "train" else None
    part = host_train_part(cfg) if train_envs is not None else None
    key = (cfg.flowsim, train_envs, cfg.val_envs, None if part is None else (part.start, part.stop))
    if key not in _SPLIT_CACHE:
        start = time.perf_counter()
        train = None
        if train_envs is not None:
            share = "" if part is None else f", this host's {part.start}..{part.stop - 1}"
            log(f"Generating the FlowSim training split ({train_envs} environments{share}) ...")
            train = train_split(cfg.flowsim, num_envs=train_envs, mesh=mesh, part=part)
        log(f"Generating the FlowSim validation split ({cfg.val_envs} environments) ...")
        val = validation_split(cfg.flowsim, num_envs=cfg.val_envs, mesh=mesh)
        jax.block_until_ready((train, val))
        log(f"  data ready in {time.perf_counter() - start:.1f} s")
        _SPLIT_CACHE.clear()  # keep at most one dataset in memory
        _SPLIT_CACHE[key] = (train, val)
    return _SPLIT_CACHE[key]


def host_train_part(cfg) -> slice | None:
    """This host's share of the ``train_envs`` environments on a multi-host job (None on one
    host). ValueError if ``train_envs`` or ``batch_size`` does not divide over the hosts."""
    hosts = jax.process_count()
    if hosts == 1:
        return None
    for name in ("train_envs", "batch_size"):
        if getattr(cfg, name) % hosts:
            raise ValueError(f"{name}={getattr(cfg, name)} does not divide over the {hosts} "
                             f"hosts of this job (each host draws its share); use a multiple "
                             f"of {hosts}")
    return host_part(cfg.train_envs)


_SPLIT_CACHE: dict = {}


def jitter_targets(key: jax.Array, boxes: jnp.ndarray, scale: float) -> jnp.ndarray:
    """Boxes (..., 4) moved by ``scale`` × the evaluation protocol's ground-truth std
    (:func:`flowmaps_jax.tables.protocol_sigma`): at scale 1, a draw from the smoothed q around
    each box."""
    centres = to_centre(boxes)
    noise = jax.random.normal(key, boxes.shape, boxes.dtype)
    return from_centre(centres + scale * protocol_sigma(boxes) * noise)


def default_batch_fn(cfg) -> BatchFn:
    """``batch_fn(key, scenes)``: B scenes drawn from ``scenes`` with Q queries each.

    Token padding beyond the F + M real tokens is trimmed (exact: padding is masked anyway).
    """
    b, q, sim, history = cfg.batch_size, cfg.queries_per_scene, cfg.flowsim, cfg.model.history
    real_tokens = sim.num_furniture + sim.num_objects * history  # the rest of S is padding

    def batch_fn(key, scenes):
        if cfg.target_noise > 0:
            key, noise_key = jax.random.split(key)
        batch = make_train_batch(key, scenes, b, q, sim, cfg.short_horizon_frac,
                                 cfg.short_horizon_max, history)
        batch = batch.replace(tokens=trim_padding(batch.tokens, real_tokens))
        if cfg.target_noise > 0:
            batch = batch.replace(target=jitter_targets(noise_key, batch.target,
                                                        cfg.target_noise))
        return batch

    return batch_fn


_CHUNK_SALT = 0x7FFFFFFF


def endless_chunk_steps(cfg) -> int:
    """With ``data="endless"``, steps served by one chunk of ``train_envs`` fresh environments
    (each environment is then drawn about once)."""
    return max(1, cfg.train_envs // cfg.batch_size)


def endless_scenes(cfg, data_key: jax.Array, step: int, mesh=None):
    """Fresh FlowSim environments (``cfg.train_envs`` of them) for the chunk holding ``step``.

    Chunk c = step // endless_chunk_steps(cfg) is generated from a key derived from
    (data_key, c) only, so a resumed run regenerates exactly the same environments. ``mesh``
    splits the work over devices; a multi-host job generates this host's share only.
    """
    chunk = int(step) // endless_chunk_steps(cfg)
    key = chunk_key(data_key, _CHUNK_SALT, chunk)
    return generate(key, cfg.train_envs, cfg.flowsim, mesh=mesh, part=host_train_part(cfg))


def make_val_batches(cfg, scenes, batch_fn: BatchFn | None = None) -> TrainBatch:
    """``cfg.val_batches`` fixed batches stacked on a leading axis, drawn with a fixed key.

    Built once per run (not a hot path); each batch reuses the compiled batch sampler.
    """
    batch_fn = batch_fn or default_batch_fn(cfg)
    keys = jax.random.split(jax.random.PRNGKey(cfg.seed + EVAL_KEY_SALT), cfg.val_batches)
    batches = [batch_fn(key, scenes) for key in keys]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *batches)


def objective(cfg):
    """``(init, loss)`` of the run's model family (``cfg.family``: FlowMaps' flow-matching loss
    or the MLP baseline's Gaussian negative log-likelihood), bound to the run's recipe
    (:class:`~flowmaps_jax.model.family.LossOptions`: ``t_sampler``, ``pointer_loss``,
    ``flowsim.num_objects``)."""
    family = model_family(cfg.family)
    options = LossOptions(t_sampler=cfg.t_sampler, pointer_loss=cfg.pointer_loss,
                          num_objects=cfg.flowsim.num_objects)

    def init(key):
        return family.init(key, cfg.model)

    def loss(params, batch, key, train):
        return family.loss(params, cfg.model, batch, key, train, options)

    return init, loss


# --------------------------------------------------------------------------- resource bounds


_ROUTINE_QUERIES = 3 * 2  # the routine probe: 3 objects per environment, at two horizon laws


def resource_estimate(cfg, devices: int = 1) -> list[tuple[str, int, int]]:
    """What a run of ``cfg`` needs, part by part, on each of ``devices`` data-parallel devices:
    ``[(what, bytes, FLOPs), ...]`` where ``what`` names the fields that set the part's size.
    FLOPs are those of one uninterruptible call (a train step, a val pass); ``steps`` is not
    bounded (a run stops and resumes between steps). A rough, generous estimate
    (:func:`flowmaps_jax.validation.network_flops`)."""
    net, sim = cfg.model, cfg.flowsim
    tokens = sim.num_furniture + sim.num_objects
    b, q = cfg.batch_size, cfg.queries_per_scene
    per_layer = net.dim * net.dim * (4 + 2 * net.mlp_ratio)
    params = (net.encoder_layers * per_layer + net.cdit_blocks * (per_layer + 6 * net.dim ** 2)
              + 2 * net.dim * net.baseline_hidden + net.baseline_hidden ** 2
              + 2 * net.freq_bands * net.dim * (4 + 4 + 1)  # the box, query and time embeddings
              + 2 * net.num_descriptors * net.dim  # the descriptor embeddings
              + (net.weight_blocks * (per_layer + 6 * net.dim ** 2)
                 if net.head == "mixture" else 0))  # the mixture head's weight rows
    query_flops, scene_flops = network_flops(
        net, tokens, model_family(cfg.family).gaussian is not None)
    # activations kept for the backward pass: per query row and per scene token, every layer
    row = 4 * net.dim * (net.mlp_ratio + 8) * net.cdit_blocks * 2 + 2 * embedding_bytes(net, 5)
    token = (4 * (net.dim * (net.mlp_ratio + 8) + tokens * net.heads) * net.encoder_layers * 2
             + 2 * embedding_bytes(net, 4))
    shard = max(1, int(devices))
    step_bytes = -(-b // shard) * (q * row + tokens * token)
    batch_bytes = 4 * (b * sim.max_tokens * 7 + b * q * 6)
    envs = cfg.train_envs + cfg.val_envs
    env_bytes = 4 * (sim.num_furniture * 5 + sim.num_objects * (3 + sim.num_furniture)
                     + sim.num_timesteps * sim.num_objects * 5 + 1)
    routine_envs = min(cfg.routine_envs, cfg.val_envs)
    routine_rows = routine_envs * _ROUTINE_QUERIES * cfg.routine_samples
    uses_solver = model_family(cfg.family).uses_solver
    evaluations = solver_evaluations(DEFAULT_NUM_STEPS) if uses_solver else 1
    return [
        (f"the model (model.dim={net.dim}, model.encoder_layers={net.encoder_layers}, "
         f"model.cdit_blocks={net.cdit_blocks}, model.mlp_ratio={net.mlp_ratio}, "
         f"model.freq_bands={net.freq_bands}, model.baseline_hidden={net.baseline_hidden}, "
         f"model.num_descriptors={net.num_descriptors}: about "
         f"{params:,} parameters, with EMA, optimiser state and gradients)",
         4 * 5 * params, 0),
        (f"a train step (batch_size={b} x queries_per_scene={q} at model.dim={net.dim}, "
         f"model.freq_bands={net.freq_bands})",
         step_bytes, 3 * (b * q * query_flops + b * scene_flops)),
        (f"the validation batches (val_batches={cfg.val_batches} of batch_size={b} x "
         f"queries_per_scene={q}, flowsim.max_tokens={sim.max_tokens})",
         cfg.val_batches * batch_bytes + step_bytes // 2,
         cfg.val_batches * (b * q * query_flops + b * scene_flops)),
        (f"the data (train_envs={cfg.train_envs} + val_envs={cfg.val_envs} environments, "
         f"flowsim.layout_candidates={sim.layout_candidates})",
         envs * env_bytes + layout_bytes(sim, envs), 0),
        (f"the routine diagnostic (routine_envs={routine_envs} environments x "
         f"{_ROUTINE_QUERIES} queries x routine_samples={cfg.routine_samples} samples, "
         f"model.freq_bands={net.freq_bands})",
         routine_rows * (4 * net.dim * (net.mlp_ratio + 4) + 4 * (4 + sim.num_furniture)
                         + embedding_bytes(net, 5)),
         routine_rows * evaluations * query_flops + routine_envs * 2 * scene_flops),
    ]


# --------------------------------------------------------------------------- inference

DEFAULT_FAMILY = "flowmaps"
"""The family of a stored config without ``model_kind`` (``TrainConfig``'s default)."""


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """The part of a stored 2-D run config that inference needs (``family_name``: stored as
    ``"model_kind"``, a pretrained ``.json``'s ``"kind"``); made only for a model that fits its
    simulator (ValueError otherwise)."""

    family_name: str
    model: ModelConfig
    flowsim: FlowSimConfig

    @property
    def family(self) -> ModelFamily:
        """The model family itself (:func:`flowmaps_jax.model.families.model_family`)."""
        return model_family(self.family_name)

    def __post_init__(self):
        check_instance("flowsim", self.flowsim, FlowSimConfig)
        check_instance("model", self.model, ModelConfig)
        # a time embedding for each of its timesteps, descriptor ids for all its descriptors
        if self.model.tau_max != self.flowsim.num_timesteps:
            raise ValueError(f"model.tau_max must be flowsim.num_timesteps = "
                             f"{self.flowsim.num_timesteps}; got {self.model.tau_max}")
        check_int("model.num_descriptors", self.model.num_descriptors,
                  self.flowsim.num_descriptors)

    def abstract_params(self):
        """Structure, shapes and dtypes of the params this model initialises."""
        return jax.eval_shape(lambda key: self.family.init(key, self.model), jax.random.key(0))


def read_spec(config: dict) -> ModelSpec:
    """The :class:`ModelSpec` of a stored 2-D run config (its training fields not read)."""
    family_name = config.get("model_kind", DEFAULT_FAMILY)
    model_family(family_name)  # ValueError listing the families
    model = ModelConfig.from_dict(config["model"]) if "model" in config else ModelConfig()
    flowsim = FlowSimConfig.from_dict(config["flowsim"]) if "flowsim" in config \
        else FlowSimConfig()
    return ModelSpec(family_name=family_name, model=model, flowsim=flowsim)


def _check_model(predictor) -> None:
    model_family(predictor.family_name)  # ValueError listing the families
    check_instance("model", predictor.model, ModelConfig)
    check_instance("flowsim", predictor.flowsim, FlowSimConfig)
    if predictor.homes is not None:
        raise ValueError(f"homes must be None for a {predictor.family_name!r} model (it reads "
                         "2-D FlowSim maps)")


def _no_receptacles(predictor, *args, **kwargs):
    raise ValueError(f"probabilities and as_prior take homes; this is a "
                     f"{predictor.family_name!r} model of 2-D FlowSim maps: use table_weights "
                     "or table_probabilities(tokens, queries, ...)")


INFERENCE = Inference(
    read_spec=read_spec, spec_of=lambda p: ModelSpec(p.family_name, p.model, p.flowsim),
    fields=lambda spec: {"flowsim": spec.flowsim}, check=_check_model,
    sample=lambda p, *args, **options: p._sample_scenes(*args, **options),
    probabilities=_no_receptacles, as_prior=_no_receptacles, scenes=True,
    label=lambda p: p.family.label(p.model))
"""The Predictor's 2-D methods (scene tokens and queries)."""

WORLD = World(
    name="flowsim", splits=load_splits,
    endless=lambda cfg, data_key, step, mesh=None: endless_scenes(cfg, data_key, step, mesh),
    chunk_steps=endless_chunk_steps, is_endless=lambda cfg: cfg.data == "endless",
    batch_fn=default_batch_fn, val_batches=make_val_batches, objective=objective,
    check_batch=check_train_batch, resources=resource_estimate, host_part=host_train_part,
    families=tuple(MODEL_FAMILIES), inference=INFERENCE,
    config="flowmaps_jax.training.config:TrainConfig",
    presets="flowmaps_jax.training.config:FLOWSIM_PRESETS",
    evaluate="flowmaps_jax.evaluation.cli:evaluate_flowsim",
    search="flowmaps_jax.search.cli:search_flowsim",
    options={"evaluate": ("baseline", "samples", "kl_draws", "num_steps", "logp_steps",
                          "likelihood_steps", "likelihood_draws", "method", "chunk_envs",
                          "scenes", "devices", "world", "history"),
             "search": ("baseline", "times_per_env", "horizons", "world", "history", "samples",
                        "table_method", "policies", "budget", "p_miss", "start", "chunk_rows",
                        "devices")})
"""The 2-D FlowSim world."""
