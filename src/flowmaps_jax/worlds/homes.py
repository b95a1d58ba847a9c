"""The FlowSim homes world: endless fresh homes, the batch sampler, the objective, the estimate.

Every chunk of ``chunk_steps`` steps draws ``chunk_homes`` fresh homes (``generate_homes``
with a key derived from the run's data key and the chunk only, so a resumed run draws the same
homes; regime ``"mixed"`` by default, so one model covers all four regimes); each step draws
``batch_size`` of them, each at one map hour τ with ``queries_per_scene`` queries (objects
uniformly; horizons ``default_horizon_frac`` from ``DEFAULT_HORIZONS``, the rest log-uniform in
1 … ``max_horizon``). The validation homes are fixed, from :data:`VAL_SEED` (never a training
key, nor the evaluation's seed), and scored by the EMA weights' cross-entropy against the
receptacle each object stands on at τ_q: the criterion that tracks the exact posterior, which
picks the ``best`` checkpoint.

``cfg`` is a ``flowmaps_jax.training.config.HomesTrainConfig`` throughout.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp

from flowmaps_jax.flowsim.homes.queries import DEFAULT_HORIZONS, HomesQueries
from flowmaps_jax.flowsim.homes.rollout import generate_homes
from flowmaps_jax.model import homes_inference
from flowmaps_jax.model.homes_family import (
    FAMILY_NAME,
    HISTORY_KEY,
    HomesSpec,
    homes_loss,
    homes_spec,
    init_params,
)
from flowmaps_jax.model.homes_inputs import HomesBatch, shared_tau_batch
from flowmaps_jax.worlds.world import Inference, World, chunk_key

VAL_SEED = 0x40E5_0001
"""The fixed seed of the validation homes (distinct from every training key and from the
evaluation's ``EVAL_SEED``)."""
_CHUNK_SALT = 0x7A1E_0002


def draw_batch(key, homes, cfg, index=None) -> HomesBatch:
    """A training batch (B = ``batch_size`` homes × Q = ``queries_per_scene`` queries) from the
    homes ``homes``: homes ``index`` (B,) (default: uniformly drawn), each at one map hour τ.
    Jittable."""
    b, q, h = cfg.batch_size, cfg.queries_per_scene, cfg.model.history
    k_home, k_tau, k_obj, k_mix, k_set, k_log = jax.random.split(key, 6)
    if index is None:
        index = jax.random.randint(k_home, (b,), 0, homes.num_homes)
    homes = jax.tree.map(lambda a: a[index], homes)
    top = cfg.homes.num_hours - 1 - cfg.max_horizon
    tau = jax.random.randint(k_tau, (b,), h - 1, top + 1)
    logits = jnp.where(homes.object_valid, 0.0, -jnp.inf)[:, None, :]
    obj = jax.random.categorical(k_obj, jnp.broadcast_to(logits, (b, q, logits.shape[-1])))
    fixed = [d for d in DEFAULT_HORIZONS if d <= cfg.max_horizon] or [1]
    chosen = jnp.asarray(fixed, jnp.int32)[jax.random.randint(k_set, (b, q), 0, len(fixed))]
    spread = jnp.floor(jnp.exp(jax.random.uniform(k_log, (b, q))
                               * math.log(cfg.max_horizon + 1.0))).astype(jnp.int32)
    spread = jnp.clip(spread, 1, cfg.max_horizon)
    dt = jnp.where(jax.random.uniform(k_mix, (b, q)) < cfg.default_horizon_frac, chosen, spread)
    tau = jnp.broadcast_to(tau[:, None], (b, q))
    queries = HomesQueries(object_index=obj.astype(jnp.int32), tau=tau, tau_q=tau + dt)
    return shared_tau_batch(homes, queries, cfg.homes, h)


def splits(cfg, log: Callable[[str], None] = print, mesh=None):
    """(None: the training homes are endless, the fixed validation homes from
    :data:`VAL_SEED`)."""
    start = time.perf_counter()
    log(f"Generating the validation homes ({cfg.val_homes} homes) ...")
    val = generate_homes(jax.random.key(VAL_SEED), cfg.homes, cfg.val_homes)
    jax.block_until_ready(val)
    log(f"  data ready in {time.perf_counter() - start:.1f} s")
    return None, val


def endless_homes(cfg, data_key, step: int, mesh=None):
    """The ``chunk_homes`` fresh homes of the chunk holding ``step``, from (data key, chunk)."""
    chunk = int(step) // cfg.chunk_steps
    return generate_homes(chunk_key(data_key, _CHUNK_SALT, chunk), cfg.homes, cfg.chunk_homes)


def validation_batches(cfg, homes) -> HomesBatch:
    """``val_batches`` fixed batches (stacked on a leading axis): batch j holds validation homes
    j·B … (j + 1)·B − 1, drawn with a key from :data:`VAL_SEED`."""
    key = jax.random.fold_in(jax.random.key(VAL_SEED), 1)
    draw = jax.jit(lambda k, h, index: draw_batch(k, h, cfg, index))
    batches = [draw(jax.random.fold_in(key, j), homes,
                    jnp.arange(j * cfg.batch_size, (j + 1) * cfg.batch_size))
               for j in range(cfg.val_batches)]
    return jax.tree.map(lambda *a: jnp.stack(a), *batches)


def objective(cfg):
    """``(init, loss)``: the homes network's init and its loss (cross-entropy of the
    receptacle weights + ``cfm_weight`` × the placement flow's CFM; ``aux["selection"]`` is the
    cross-entropy). The network has no dropout: ``train`` changes nothing."""

    def init(key):
        return init_params(key, cfg.model, cfg.homes)

    def loss(params, batch, key, train):
        return homes_loss(params, cfg.model, cfg.homes, batch, key, cfg.cfm_weight)

    return init, loss


def check_batch(batch) -> None:
    """ValueError unless ``batch`` is a :class:`~flowmaps_jax.model.homes_inputs.HomesBatch`."""
    if not isinstance(batch, HomesBatch):
        raise ValueError(f"batch must be a HomesBatch; got {type(batch).__name__}")


def resource_estimate(cfg, devices: int = 1) -> list[tuple[str, int, int]]:
    """What a homes run needs, part by part (``[(what, bytes, FLOPs), ...]``, each part's
    ``what`` naming the fields that set it), on each of ``devices`` devices: a rough, generous
    estimate, so that a run too large for this machine is refused before anything is
    written."""
    net, homes = cfg.model, cfg.homes
    d, s = net.dim, homes.max_tokens
    r, m, hist = homes.max_receptacles, homes.max_objects, net.history
    blocks = net.encoder_layers + 2 * net.weight_blocks + net.cdit_blocks
    per_block = d * d * (4 + 2 * net.mlp_ratio) + 6 * d * d
    params = (blocks * per_block + homes.max_vocabulary * d * 2
              + 2 * net.freq_bands * 6 * d + 64 * d * (hist + 8))
    b, q = -(-cfg.batch_size // max(1, int(devices))), cfg.queries_per_scene
    rows = b * q * (r + 1)  # the weight rows and the placement row of every query
    tokens = b * s + rows
    events = b * q * hist * (net.history_heads * (HISTORY_KEY + 4 * r) + 2 * r)  # the read-out
    act = (4 * tokens * d * (net.mlp_ratio + 8) * blocks * 2 + 4 * b * net.heads * s * s * blocks
           + 4 * 3 * events)
    step_flops = 6 * (tokens * per_block * blocks + b * q * r * hist * 64 + events * 32)
    home_bytes = 4 * (homes.num_hours * m + m * r + r * r + s * 8)
    return [
        (f"the model (model.dim={d}, model.encoder_layers={net.encoder_layers}, "
         f"model.weight_blocks={net.weight_blocks}, model.cdit_blocks={net.cdit_blocks}, "
         f"model.mlp_ratio={net.mlp_ratio}, homes.max_vocabulary={homes.max_vocabulary}: about "
         f"{params:,} parameters, with EMA, optimiser state and gradients)", 4 * 5 * params, 0),
        (f"a train step (batch_size={cfg.batch_size} x queries_per_scene={q} at model.dim={d}, "
         f"homes.max_tokens={s}, model.history={hist}, model.history_heads="
         f"{net.history_heads})", act, step_flops),
        (f"the validation batches (val_batches={cfg.val_batches} of batch_size="
         f"{cfg.batch_size})", cfg.val_batches * 4 * b * (s * 10 + q * r * (hist + 8)),
         cfg.val_batches * step_flops // 3),
        (f"the data (chunk_homes={cfg.chunk_homes} + val_homes={cfg.val_homes} homes of "
         f"homes.num_hours={homes.num_hours} hours)",
         (cfg.chunk_homes + cfg.val_homes) * home_bytes * 3, 0),
    ]


def host_part(cfg) -> None:
    """Homes training runs on one host (its devices share the batch): ValueError on a
    multi-host job."""
    if jax.process_count() > 1:
        raise ValueError("homes training runs on one host (any number of its devices); this "
                         f"job has {jax.process_count()} processes")
    return None


INFERENCE = Inference(
    read_spec=homes_spec, spec_of=lambda p: HomesSpec(p.family_name, p.model, p.homes),
    fields=lambda spec: {"homes": spec.homes}, check=homes_inference.check_model,
    sample=homes_inference.sample, probabilities=homes_inference.probabilities,
    as_prior=homes_inference.as_prior, scenes=False, label=lambda p: "FlowMaps")
"""The Predictor on homes (:mod:`flowmaps_jax.model.homes_inference`)."""

WORLD = World(
    name="homes", splits=splits, endless=endless_homes,
    chunk_steps=lambda cfg: cfg.chunk_steps, is_endless=lambda cfg: True,
    batch_fn=lambda cfg: lambda key, homes: draw_batch(key, homes, cfg),
    val_batches=validation_batches, objective=objective, check_batch=check_batch,
    resources=resource_estimate, host_part=host_part, families=(FAMILY_NAME,),
    inference=INFERENCE, config="flowmaps_jax.training.config:HomesTrainConfig",
    presets="flowmaps_jax.training.config:HOMES_PRESETS",
    evaluate="flowmaps_jax.evaluation.receptacle_protocol:evaluate",
    search="flowmaps_jax.evaluation.receptacle_protocol:search",
    options={"evaluate": ("samples", "queries", "regime", "horizons", "history"),
             "search": ("samples", "queries", "regime", "horizons", "history", "budget")})
"""The FlowSim homes world."""
