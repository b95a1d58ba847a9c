"""The world interface: what the layers above need from a world (:class:`World`)."""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


class Inference(NamedTuple):
    """How the :class:`~flowmaps_jax.predictor.Predictor` runs a world's models.

    read_spec(stored config dict) -> spec: ``family_name``, ``model``, ``abstract_params()``
        and the world's config (ValueError naming what is wrong).
    spec_of(predictor) -> its spec; fields(spec) -> the Predictor's world fields of a spec.
    check(predictor): its fields (ValueError naming the field).
    sample(predictor, inputs, queries, num_samples, key, num_steps, **options),
    probabilities(predictor, homes, queries, config, observed), as_prior(predictor, config,
        observed): the verbs in the world's inputs.
    scenes: whether the model reads 2-D scene tokens; label(predictor): its row in reports.
    """

    read_spec: Callable
    spec_of: Callable
    fields: Callable
    check: Callable
    sample: Callable
    probabilities: Callable
    as_prior: Callable
    scenes: bool
    label: Callable


def resolve(hook):
    """A hook of a layer above the worlds, named ``"module:attribute"`` (imported when first
    used, so that a world sits below the layers that use it), or the hook itself."""
    if not isinstance(hook, str):
        return hook
    module, _, name = hook.partition(":")
    return getattr(importlib.import_module(module), name)


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
    families: the model families that train on this world (the first world listing a family
        is the world of its models).
    inference: how the Predictor runs its models (:class:`Inference`).
    configs: its run config class (``from_dict``, ``to_dict``, ``world``) and presets
        ``{name: () -> cfg}``; evaluate, search: its commands ``(parser, args, argv) -> exit
        code``; options: ``{command: the options it reads beyond the common ones}``; each a
        ``"module:attribute"`` of the layer above (:func:`resolve`) or the object itself.
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
    inference: Inference
    config: Any
    presets: Any
    evaluate: Any
    search: Any
    options: dict
    reads_files: bool = False

    def hook(self, name: str):
        """The hook ``name`` (``"config"``, ``"presets"``, ``"evaluate"``, ``"search"``)."""
        return resolve(getattr(self, name))


def chunk_key(data_key, salt: int, chunk: int) -> jax.Array:
    """The typed key of endless chunk ``chunk``: ``fold_in(fold_in(data_key, salt), chunk)``, a
    function of (data key, chunk) only, so that a resumed run draws the same data. Uncommitted,
    as the fixed splits' keys are, so that generation and the train step (which specialise on
    key type and device commitment) reuse their compiled code."""
    raw = jax.random.fold_in(jax.random.fold_in(np.asarray(data_key), salt), chunk)
    return jax.random.wrap_key_data(jnp.asarray(np.asarray(raw)))
