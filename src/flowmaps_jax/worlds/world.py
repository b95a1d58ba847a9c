"""The world interface: what the layers above need from a world (:class:`World`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class World:
    """One world's hooks (``cfg``: a run config of this world).

    splits(cfg, log, mesh) -> (train data or None for endless data, validation data).
    endless(cfg, data_key, step, mesh) -> the fresh training data of the chunk holding ``step``
        (a function of (data_key, chunk) only, so a resumed run draws the same data).
    chunk_steps(cfg) -> the steps one chunk of endless data serves.
    is_endless(cfg) -> whether the run draws endless data.
    batch_fn(cfg) -> ``batch_fn(key, data) -> batch``, traceable (drawn inside the train step).
    val_batches(cfg, val_data) -> ``cfg.val_batches`` fixed batches stacked on a leading axis.
    objective(cfg) -> ``(init(key) -> params, loss(params, batch, key, train) -> (loss, aux))``;
        ``aux["selection"]``, where given, is what picks the best checkpoint.
    check_batch(batch) -> None: ValueError naming the array of a batch that does not fit.
    resources(cfg, devices) -> ``[(what, bytes, FLOPs), ...]``: what a run needs, part by part.
    host_part(cfg) -> this host's share of the training data on a multi-host job (None on one).
    families: the model families that train on this world.
    reads_files: whether the world's data is a dataset on disk (``--data PATH``) rather than
        generated.
    """

    name: str
    splits: Callable[..., tuple[Any, Any]]
    endless: Callable[..., Any]
    chunk_steps: Callable[[Any], int]
    is_endless: Callable[[Any], bool]
    batch_fn: Callable[[Any], Callable]
    val_batches: Callable[[Any, Any], Any]
    objective: Callable[[Any], tuple[Callable, Callable]]
    check_batch: Callable[[Any], None]
    resources: Callable[[Any, int], list]
    host_part: Callable[[Any], slice | None]
    families: tuple[str, ...]
    reads_files: bool = False


def chunk_key(data_key, salt: int, chunk: int) -> jax.Array:
    """The typed key of endless chunk ``chunk``: ``fold_in(fold_in(data_key, salt), chunk)``, a
    function of (data key, chunk) only, so that a resumed run draws the same data. Uncommitted,
    as the fixed splits' keys are, so that generation and the train step (which specialise on
    key type and device commitment) reuse their compiled code."""
    raw = jax.random.fold_in(jax.random.fold_in(np.asarray(data_key), salt), chunk)
    return jax.random.wrap_key_data(jnp.asarray(np.asarray(raw)))
