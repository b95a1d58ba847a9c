"""Resource budgets, checked up front: a request above one is a ``ValueError`` naming it, the
estimate and the limit (:func:`check_resources`); memory :data:`MAX_BYTES_ENV`, work
:data:`MAX_FLOPS_ENV`. And the size a small request is computed at (:func:`computed_rows`).
"""

from __future__ import annotations

import functools
import math
import os
import re
from collections.abc import Sequence
from typing import Any

import jax
import numpy as np

MAX_BYTES_ENV = "FLOWMAPS_MAX_BYTES"
"""Environment variable overriding the memory budget of one request (bytes; ``64G`` etc.)."""
MAX_FLOPS_ENV = "FLOWMAPS_MAX_FLOPS"
"""Environment variable overriding the work budget of one uninterruptible call (FLOPs)."""
DEFAULT_MAX_FLOPS = 10**17
"""Default work budget: refuses sizes that would run for days (raise it with
:data:`MAX_FLOPS_ENV`)."""
SEQUENTIAL_FLOPS = 10**12
"""The least one step of a sequential loop (an ODE solver's evaluation) counts for in the work
budget: latency, not arithmetic, sets its time."""
_SUFFIXES = {"": 1, "K": 10**3, "M": 10**6, "G": 10**9, "T": 10**12, "P": 10**15,
             "KI": 2**10, "MI": 2**20, "GI": 2**30, "TI": 2**40, "PI": 2**50}


def _env_budget(variable: str) -> int | None:
    """The positive number in environment ``variable`` (e.g. ``64G``, ``1e12``), None if unset."""
    text = os.environ.get(variable, "").strip()
    if not text:
        return None
    match = re.fullmatch(r"([0-9.eE+]+)\s*([KMGTPkmgtp][Ii]?)?[Bb]?", text)
    try:
        value = float(match.group(1)) * _SUFFIXES[(match.group(2) or "").upper()]
    except (AttributeError, ValueError, KeyError):
        value = math.nan
    if not (math.isfinite(value) and value >= 1):
        raise ValueError(f"{variable} must be a positive number like 64G or 1e12; got {text!r}")
    return int(value)


def array_bytes(shape: Sequence[int], dtype: Any = np.float32) -> int:
    """Bytes of an array of ``shape`` and ``dtype`` (exact Python int, no overflow)."""
    return math.prod(int(s) for s in shape) * np.dtype(dtype).itemsize


@functools.lru_cache(maxsize=1)
def _device_memory() -> int:
    try:
        stats = jax.devices()[0].memory_stats() or {}
    except Exception:  # backends without memory stats
        stats = {}
    if stats.get("bytes_limit"):
        return int(stats["bytes_limit"])
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, OSError, ValueError):
        return 16 * 2**30


def memory_limit() -> int:
    """Bytes one request may use: ``$FLOWMAPS_MAX_BYTES`` when set, else the default device's
    memory limit when JAX reports one (accelerators), else the host's physical memory."""
    override = _env_budget(MAX_BYTES_ENV)
    return _device_memory() if override is None else override


def flops_limit() -> int:
    """Floating-point operations one uninterruptible call may take: ``$FLOWMAPS_MAX_FLOPS``
    when set, else :data:`DEFAULT_MAX_FLOPS`."""
    override = _env_budget(MAX_FLOPS_ENV)
    return DEFAULT_MAX_FLOPS if override is None else override


def check_request_size(name: str, num_bytes: int, limit: int | None = None) -> int:
    """``num_bytes`` if it is at most ``limit`` (default :func:`memory_limit`), else a
    ``ValueError`` saying how many GB the request ``name`` would need."""
    limit = memory_limit() if limit is None else int(limit)
    if num_bytes > limit:
        raise ValueError(f"{name} would need about {num_bytes / 1e9:.3g} GB, more than the "
                         f"{limit / 1e9:.3g} GB available ({MAX_BYTES_ENV} overrides it); ask "
                         f"for less or split the request")
    return int(num_bytes)


SMALL_REQUEST = 64
"""Requests of fewer rows (environments, homes) are computed at this many and cut back
(:func:`computed_rows`), so every small request of one configuration runs one compiled
program."""


def computed_rows(count: int, bytes_per_row: int) -> int:
    """The rows to compute for a request of ``count`` independent rows drawn from
    ``jax.random.split(key, rows)``: :data:`SMALL_REQUEST` for a smaller request when that
    many rows take at most 64 MB (and the memory limit), else ``count``. The first ``count``
    keys are those of ``split(key, count)`` (JAX's partitionable threefry, the default; without
    it, ``count``), so the first ``count`` rows are the request's, bit for bit."""
    small = min(2**26, memory_limit()) // SMALL_REQUEST
    if count < SMALL_REQUEST and bytes_per_row <= small and jax.config.jax_threefry_partitionable:
        return SMALL_REQUEST
    return count


def first_rows(tree: Any, count: int) -> Any:
    """Every leaf's first ``count`` rows, placed and committed as the leaf is (cut on the host:
    no program per size; a committed array would make later eager operations new programs)."""
    return jax.tree.map(lambda x: x if x.shape[0] == count else jax.device_put(
        np.asarray(x)[:count], x.sharding if x.committed else None), tree)


def check_resources(name: str, *, num_bytes: int = 0, flops: int = 0,
                    sequential: int = 0) -> None:
    """The shared budget check: ``ValueError`` naming ``name`` (the argument and its value)
    when the estimated memory (bytes) or work (FLOPs) is over :func:`memory_limit` /
    :func:`flops_limit`. ``sequential``: steps of the call that run one after another (an ODE
    solve's network evaluations), each counted as at least :data:`SEQUENTIAL_FLOPS`."""
    check_request_size(name, int(num_bytes))
    limit = flops_limit()
    if int(sequential) * SEQUENTIAL_FLOPS > limit:
        raise ValueError(f"{name} would run {float(sequential):.3g} network evaluations one "
                         f"after another, more than the {float(limit // SEQUENTIAL_FLOPS):.3g} "
                         f"the work budget allows ({MAX_FLOPS_ENV} overrides it; each counts "
                         f"as {float(SEQUENTIAL_FLOPS):.0e} operations); ask for fewer steps")
    if flops > limit:
        raise ValueError(f"{name} would take about {float(flops):.3g} floating-point operations, "
                         f"more than the budget of {float(limit):.3g} ({MAX_FLOPS_ENV} overrides "
                         f"it); ask for less")


def network_flops(model: Any, num_tokens: int, gaussian: bool = False) -> tuple[int, int]:
    """(FLOPs of one network evaluation of one query-sample, FLOPs of encoding one map of
    ``num_tokens`` tokens) for a model config (``ModelConfig``): its CDiT blocks, or with
    ``gaussian`` its MLP Gaussian head (a family with a ``gaussian`` core: the MLP baseline).
    A rough, generous estimate (2 FLOPs per weight use, attention included)."""
    dim, ratio = int(model.dim), int(model.mlp_ratio)
    per_layer = dim * dim * (4 + 2 * ratio)
    encoder = 2 * int(model.encoder_layers) * num_tokens * (per_layer + 2 * num_tokens * dim)
    encoder += num_tokens * embedding_flops(model, 4)  # each token's box
    query = embedding_flops(model, 5)  # a query's box and its time
    if gaussian:
        hidden = int(model.baseline_hidden)
        return 2 * (dim * hidden + hidden * hidden + 8 * hidden + 4 * dim * dim) + query, encoder
    blocks = int(model.cdit_blocks)
    return 2 * blocks * (per_layer + 6 * dim * dim + 2 * num_tokens * dim) + query, encoder


def solver_evaluations(num_steps: int, method: str = "midpoint") -> int:
    """Network evaluations of one ODE solve with ``num_steps`` grid points (midpoint 2 per
    interval, RK4 ("accurate") 4, Euler 1)."""
    return (int(num_steps) - 1) * {"midpoint": 2, "accurate": 4}.get(method, 1)


def embedding_bytes(model: Any, scalars: int) -> int:
    """Bytes of the sinusoidal features of ``scalars`` scalars of one row (5 floats per scalar
    and band)."""
    return 4 * 5 * int(scalars) * int(model.freq_bands)


def embedding_flops(model: Any, scalars: int) -> int:
    """FLOPs of the sinusoidal embedding of ``scalars`` scalars (their 2 × ``freq_bands``
    features through a dense layer of width ``model.dim``)."""
    return 2 * 2 * int(scalars) * int(model.freq_bands) * int(model.dim)
