"""Shared fixtures. JAX compile time dominates the suite, so generated data is made once per
session and always with the same number of environments (``SMALL_NUM_ENVS``): ``generate`` is
compiled once per (config shape, number of environments), and tests that call it themselves
should use this size to reuse the compiled function."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile

# One persistent XLA compilation cache per test session, shared by the xdist workers and by the
# subprocesses and notebook kernels the tests start (they inherit the environment): a function
# compiled by one process is loaded by the others. Set before JAX is imported, by the first
# process (removed when it exits); a user's own setting wins. Every program is stored, however
# fast it compiled: most of the suite's thousands of compiles are small, and the two workers and
# the children build many of the same ones (idle 2-core run: pytest 638 s with a 0.5 s floor,
# 538 s with none; docs/results.md, "Test suite time").
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    _cache = tempfile.mkdtemp(prefix="flowmaps-jax-xla-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _cache
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
# Compilation dominates the suite (tiny models, a few steps): XLA's
# ``jax_disable_most_optimizations`` about halves it. The programs are the same, their machine
# code less optimised; tests comparing two programs compare them under the same flag, and the
# stored numbers (the paper world's SHA-256, the shipped models' checks) hold under it too.
# Workers, subprocesses and notebook kernels inherit it; a user's own setting wins.
os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "true")
# XLA:CPU's newer fusion emitters take about twice as long to compile as the classic elemental
# emitter (docs/results.md, "Test suite time", measured by bench_compile.py before issue 49).
# Same programs, rounded differently in places (tests/test_distributed.py keeps the default
# emitter for the two-device comparison its tolerances were measured with). Appended unless
# XLA_FLAGS chooses.
if "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + " --xla_cpu_use_fusion_emitters=false").strip()

import jax
import pytest

from flowmaps_jax.flowsim import FlowSimConfig, Scenes, generate

SMALL_NUM_ENVS = 256


@pytest.fixture(scope="module")
def fast_compiled_module():
    """For a module that compiles under ``support.fast_compile``: JAX's caches are dropped when
    it is done, unless the whole suite compiles that way (above), so that later tests do not
    reuse its less optimised programs (the flag is not part of ``jax.jit``'s cache key)."""
    flag_was_on = jax.config.read("jax_disable_most_optimizations")
    yield
    if not flag_was_on:
        jax.clear_caches()


@pytest.fixture(scope="session")
def flowsim_config() -> FlowSimConfig:
    """The paper's FlowSim configuration."""
    return FlowSimConfig()


@pytest.fixture(scope="session")
def small_scenes(flowsim_config) -> Scenes:
    """SMALL_NUM_ENVS environments from the default config, key 0."""
    return generate(jax.random.key(0), SMALL_NUM_ENVS, flowsim_config)


# tests/multidevice needs several JAX devices, fixed when JAX starts: tests/test_distributed.py
# runs it in a subprocess with XLA_FLAGS=--xla_force_host_platform_device_count=2 and
# FLOWMAPS_MULTIDEVICE=1. A plain `pytest` does not collect it directly.
collect_ignore_glob = [] if os.environ.get("FLOWMAPS_MULTIDEVICE") else ["multidevice/*"]

