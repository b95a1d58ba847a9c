"""The model a stored run config describes: its family, sizes and simulator, and the check that
stored weights fit it. Read from a checkpoint's ``config`` item or a pretrained model's
``.json``; the training fields of the config are not read (no training code, no optax)."""

from __future__ import annotations

import functools
from collections.abc import Mapping

import jax
import numpy as np

from flowmaps_jax.store.integrity import leaf_name
from flowmaps_jax.validation import check_instance
from flowmaps_jax.worlds import world_of_family
from flowmaps_jax.worlds.flowsim import DEFAULT_FAMILY, ModelSpec

__all__ = ["DEFAULT_FAMILY", "ModelSpec", "check_params", "model_spec"]


def model_spec(config: dict):
    """The spec of a stored run config (a checkpoint's ``config`` item or a pretrained model's
    ``.json`` ``config``): ``family_name``, ``model``, ``abstract_params()`` and its world's
    config, read by the world of its family (``"model_kind"``; the training fields are not
    read). Raises ``ValueError`` naming what is wrong; ``config`` is a dict."""
    family_name = config.get("model_kind", DEFAULT_FAMILY)
    return world_of_family(family_name).inference.read_spec(config)


def _leaves(tree) -> dict:
    return {leaf_name(path): (tuple(np.shape(leaf)), np.dtype(getattr(leaf, "dtype", object)))
            for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]}


@functools.lru_cache(maxsize=16)
def _initialised(spec) -> dict:
    return _leaves(spec.abstract_params())


def check_params(params, spec, where: str) -> None:
    """``ValueError`` unless ``params`` has the leaves (paths, shapes and dtypes) that
    ``spec``'s family initialises (weights that do not fit their config), naming the first
    leaf that differs."""
    check_instance(where, params, Mapping)
    got, want = _leaves(params), _initialised(spec)
    if got != want:
        key = next(k for k in sorted(got.keys() | want.keys()) if got.get(k) != want.get(k))
        def what(leaf):
            return "absent" if leaf is None else f"{leaf[0]} {leaf[1]}"
        raise ValueError(f"{where}: parameter {key} is {what(got.get(key))}; the "
                         f"{spec.family_name!r} model its config describes has "
                         f"{what(want.get(key))}")
