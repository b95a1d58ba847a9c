"""Shared fixtures. JAX compile time dominates the suite, so generated data is made once per
session and always with the same number of environments (``SMALL_NUM_ENVS``): ``generate`` is
compiled once per (config shape, number of environments), and tests that call it themselves
should use this size to reuse the compiled function."""

from __future__ import annotations

import jax
import pytest

from flowmaps_jax.flowsim import FlowSimConfig, Scenes, generate

SMALL_NUM_ENVS = 256


@pytest.fixture(scope="session")
def flowsim_config() -> FlowSimConfig:
    """The paper's FlowSim configuration."""
    return FlowSimConfig()


@pytest.fixture(scope="session")
def small_scenes(flowsim_config) -> Scenes:
    """SMALL_NUM_ENVS environments from the default config, key 0."""
    return generate(jax.random.key(0), SMALL_NUM_ENVS, flowsim_config)
