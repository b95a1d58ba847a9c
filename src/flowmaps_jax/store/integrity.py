"""What makes a stored state trustworthy (docs/guarantees.md, "Integrity checks"): the ``meta``
item of every step (:func:`describe_state`: SHA-256 of every array leaf and of the config, plus
the unlogged metrics window), :class:`NonFiniteStateError` on save and :func:`verify` on restore.
"""

from __future__ import annotations

import hashlib
import json

import jax
import jax.numpy as jnp
import numpy as np

META_FORMAT = 2
"""The version of the ``meta`` item :func:`describe_state` writes (2: the store adds the packed
state's ``layout``, :mod:`flowmaps_jax.store.packing`; 1: a state of one array per leaf)."""


class NonFiniteStateError(ValueError):
    """A state with NaN or inf in its params, EMA params or optimiser state was not saved."""


class Damaged(ValueError):
    """One saved copy of a step failed to restore or verify (the store reports it in full)."""


def leaf_name(path) -> str:
    """``params/encoder/kernel`` for a key path, the same for a TrainState and its raw restore."""
    parts = []
    for entry in path:
        for attr in ("name", "key", "idx"):
            if hasattr(entry, attr):
                parts.append(str(getattr(entry, attr)))
                break
    return "/".join(parts)


def name_list(names: list[str], limit: int = 3) -> str:
    """The first ``limit`` names, then how many more."""
    more = f" and {len(names) - limit} more" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


def shorten(err: Exception | str, limit: int = 400) -> str:
    """An error's text, cut to ``limit`` characters."""
    text = str(err)
    return text if len(text) <= limit else text[:limit] + " ..."


def host_leaves(tree) -> list[tuple[str, np.ndarray]]:
    """(:func:`leaf_name`, host copy) of every leaf of ``tree`` in flattening order; a typed
    PRNG key as its key data."""
    out = []
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        if jnp.issubdtype(getattr(leaf, "dtype", np.float32), jax.dtypes.prng_key):
            leaf = jax.random.key_data(leaf)
        out.append((leaf_name(path), np.asarray(jax.device_get(leaf))))
    return out


def _digest(arr: np.ndarray) -> str:
    header = f"{arr.dtype.name}{arr.shape}".encode()
    return hashlib.sha256(header + np.ascontiguousarray(arr).tobytes()).hexdigest()


def config_checksum(config: dict) -> str:
    """SHA-256 of a JSON config dict (key order does not matter)."""
    return hashlib.sha256(json.dumps(config, sort_keys=True).encode()).hexdigest()


def _non_finite(leaves: list[tuple[str, np.ndarray]]) -> list[str]:
    """``name (k of n)`` for every floating leaf holding NaN or inf."""
    bad = []
    for name, arr in leaves:
        if jnp.issubdtype(arr.dtype, jnp.inexact):
            count = arr.size - int(np.count_nonzero(np.isfinite(arr)))
            if count:
                bad.append(f"{name} ({count} of {arr.size})")
    return bad


def state_checksums(state) -> tuple[dict[str, str], list[str]]:
    """(SHA-256 of every array leaf of ``state`` by :func:`leaf_name`, ``name (k of n)`` of every
    floating leaf holding NaN or inf): what a save records and a restore checks."""
    return leaf_checksums(host_leaves(state))


def leaf_checksums(leaves: list[tuple[str, np.ndarray]]) -> tuple[dict[str, str], list[str]]:
    """:func:`state_checksums` of a state given as its (:func:`leaf_name`, host array) pairs."""
    return {name: _digest(arr) for name, arr in leaves}, _non_finite(leaves)


def describe_state(state, config: dict, log_window: dict | None = None) -> dict:
    """The ``meta`` item of a save: SHA-256 of every array leaf and of ``config``, plus the
    loop's ``log_window``. Raises :class:`NonFiniteStateError` if a float leaf is NaN or inf."""
    checksums, bad = state_checksums(state)
    if bad:
        raise NonFiniteStateError(
            f"refusing to save step {int(state.step)}: the state holds NaN or inf values in "
            f"{name_list(bad)}")
    return {"format": META_FORMAT, "checksums": checksums,
            "config_sha256": config_checksum(config), "log_window": log_window}


def verify_config(config: dict, meta: dict | None) -> None:
    """Raise :class:`Damaged` unless ``config`` matches the checksum in ``meta`` (None: a step
    saved before checksums existed, not checked)."""
    if meta is not None and meta.get("config_sha256") != config_checksum(config):
        raise Damaged("fails its checksums: the stored config differs from what was saved")


def verify(state, config: dict, meta: dict | None) -> None:
    """Raise :class:`Damaged` unless ``state``/``config`` match the checksums in ``meta`` and
    are finite (``meta`` None: finiteness only)."""
    verify_leaves(host_leaves(state), config, meta)


def verify_leaves(leaves: list[tuple[str, np.ndarray]], config: dict, meta: dict | None) -> None:
    """:func:`verify` of a state given as its (:func:`leaf_name`, host array) pairs (a packed
    step's arrays as read: no copy back from the devices)."""
    got, bad = leaf_checksums(leaves)
    if meta is not None:
        expected = meta.get("checksums") if isinstance(meta, dict) else None
        if not isinstance(expected, dict):
            raise Damaged("has an unreadable meta item (no checksums)")
        if set(got) != set(expected):
            raise Damaged(f"does not match its checksums: arrays "
                          f"{name_list(sorted(set(got) ^ set(expected)))} differ in name")
        changed = [name for name in got if got[name] != expected[name]]
        if changed:
            raise Damaged(f"fails its checksums: {len(changed)} of {len(got)} arrays differ "
                          f"from what was saved ({name_list(changed)})")
        verify_config(config, meta)
    if bad:
        raise Damaged(f"holds NaN or inf values in {name_list(bad)}")
