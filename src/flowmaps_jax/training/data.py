"""Training data: FlowSim splits generated in-process, and the traceable batch sampler.

* :func:`load_splits` generates the fixed train / validation splits once per process.
* :func:`default_batch_fn` ``(key, scenes) -> TrainBatch`` draws B scenes with Q queries each,
  inside the jitted train step (no host round trip).
* With ``data="endless"``, :func:`endless_scenes` regenerates a chunk of fresh environments every
  :func:`endless_chunk_steps` steps, from a key that depends only on (data key, chunk).
* :func:`make_val_batches` fixes the validation batches of a run (its val passes use them).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.distributed import host_part
from flowmaps_jax.flowsim.generate import generate
from flowmaps_jax.flowsim.scenes import make_train_batch, train_split, validation_split
from flowmaps_jax.tokens import TrainBatch, trim_padding
from flowmaps_jax.training.config import TrainConfig
from flowmaps_jax.training.objectives import jitter_targets

# batch_fn(key, scenes) -> TrainBatch, traceable
BatchFn = Callable[[jax.Array, Any], TrainBatch]

# Fixed seed offset of the val batches' key: val passes at different steps use the same noise.
EVAL_KEY_SALT = 0x5EED


def load_splits(cfg: TrainConfig, log: Callable[[str], None] = print, mesh=None):
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


def host_train_part(cfg: TrainConfig) -> slice | None:
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


def default_batch_fn(cfg: TrainConfig) -> BatchFn:
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


def endless_chunk_steps(cfg: TrainConfig) -> int:
    """With ``data="endless"``, steps served by one chunk of ``train_envs`` fresh environments
    (each environment is then drawn about once)."""
    return max(1, cfg.train_envs // cfg.batch_size)


def endless_scenes(cfg: TrainConfig, data_key: jax.Array, step: int, mesh=None):
    """Fresh FlowSim environments (``cfg.train_envs`` of them) for the chunk holding ``step``.

    Chunk c = step // endless_chunk_steps(cfg) is generated from a key derived from
    (data_key, c) only, so a resumed run regenerates exactly the same environments. ``mesh``
    splits the work over devices; a multi-host job generates this host's share only.
    """
    chunk = int(step) // endless_chunk_steps(cfg)
    raw = jax.random.fold_in(jax.random.fold_in(np.asarray(data_key), _CHUNK_SALT), chunk)
    # An uncommitted typed key, as the fixed splits use, so that generation and the train step
    # (which specialise on key type and device commitment) reuse their compiled code.
    key = jax.random.wrap_key_data(jnp.asarray(np.asarray(raw)))
    return generate(key, cfg.train_envs, cfg.flowsim, mesh=mesh, part=host_train_part(cfg))


def make_val_batches(cfg: TrainConfig, scenes, batch_fn: BatchFn | None = None) -> TrainBatch:
    """``cfg.val_batches`` fixed batches stacked on a leading axis, drawn with a fixed key.

    Built once per run (not a hot path); each batch reuses the compiled batch sampler.
    """
    batch_fn = batch_fn or default_batch_fn(cfg)
    keys = jax.random.split(jax.random.PRNGKey(cfg.seed + EVAL_KEY_SALT), cfg.val_batches)
    batches = [batch_fn(key, scenes) for key in keys]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *batches)
