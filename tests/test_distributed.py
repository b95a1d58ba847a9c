"""Scale-out (flowmaps_jax.distributed): the mesh, its checks, multi-host start-up, and the
two-device tests of tests/multidevice run in a subprocess with two forced host devices."""

from __future__ import annotations

import os
import pathlib
import re
import subprocess
import sys

import jax
import pytest

from flowmaps_jax import distributed
from flowmaps_jax.training.config import apply_overrides, get_preset

TESTS = pathlib.Path(__file__).parent


def _forced_devices_env(count: int) -> dict[str, str]:
    env = dict(os.environ)
    env["XLA_FLAGS"] = (f"{env.get('XLA_FLAGS', '')} "
                        f"--xla_force_host_platform_device_count={count}").strip()
    env["FLOWMAPS_MULTIDEVICE"] = "1"
    env["JAX_PLATFORMS"] = "cpu"
    # These tests compare programs with each other, not with stored numbers: skipping most of
    # XLA's optimisation passes halves their compile time (the partitioner still runs; the
    # tests check that the arrays really are split over both devices).
    env["JAX_DISABLE_MOST_OPTIMIZATIONS"] = "true"
    return env


@pytest.mark.slow
def test_two_forced_host_devices():
    """tests/multidevice: 2-device training equals 1-device training, sharded generation and
    sampling equal unsharded, a 2-device checkpoint continues on 1 device, bad batches and
    incompatible checkpoints are ValueErrors."""
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-o", "addopts=", "-q", "-p", "no:cacheprovider",
         "-W", "ignore::pytest.PytestUnraisableExceptionWarning", str(TESTS / "multidevice")],
        cwd=TESTS.parent, env=_forced_devices_env(2), capture_output=True, text=True,
        timeout=900)
    assert proc.returncode == 0, proc.stdout[-6000:] + proc.stderr[-3000:]
    summary = proc.stdout.strip().splitlines()[-1]
    assert re.search(r"\b\d+ passed", summary) and "skipped" not in summary, summary


def test_one_device_builds_no_mesh():
    """On one device nothing is sharded: the training compiles its single-device program."""
    assert jax.device_count() == 1
    assert distributed.training_mesh() is None
    assert distributed.data_mesh().size == 1
    assert distributed.shard_rows({"x": jax.numpy.ones(3)}, None)["x"].shape == (3,)
    assert distributed.describe(None).startswith("1 device (cpu")


def test_mesh_size_checks():
    with pytest.raises(ValueError, match=r"devices \(JAX sees 1 cpu device\(s\); none: all\) "
                                         r"must be an int in 1\.\.1; got 2"):
        distributed.data_mesh(2)
    with pytest.raises(ValueError, match=r"devices .* must be an int in 1\.\.1; got 0"):
        distributed.data_mesh(0)
    mesh = distributed.data_mesh()
    distributed.check_divides("batch_size", 7, mesh)  # one device: anything divides


def test_check_divides_says_how():
    class FakeMesh:  # only .size is read
        size = 4

    with pytest.raises(ValueError, match=r"batch_size=6 does not divide evenly over the 4 "
                                         r"devices.*multiple of 4 \(e\.g\. 4 or 8\)"):
        distributed.check_divides("batch_size", 6, FakeMesh())
    with pytest.raises(ValueError, match=r"multiple of 4 \(e\.g\. 4\)"):
        distributed.check_divides("batch_size", 3, FakeMesh())
    distributed.check_divides("batch_size", 8, FakeMesh())


def test_devices_field_is_checked():
    cfg = get_preset("smoke")  # batch_size 8
    assert apply_overrides(cfg, ["devices=4"]).devices == 4
    assert apply_overrides(cfg, ["devices=none"]).devices is None
    with pytest.raises(ValueError, match="batch_size=8 does not divide evenly over devices=3"):
        apply_overrides(cfg, ["devices=3"])
    with pytest.raises(ValueError, match="devices"):
        apply_overrides(cfg, ["devices=0"])


def test_host_part():
    assert distributed.host_part(64, 0, 2) == slice(0, 32)
    assert distributed.host_part(64, 1, 2) == slice(32, 64)
    assert distributed.host_part(10, 0, 1) == slice(0, 10)
    with pytest.raises(ValueError, match="65 does not divide over 2 hosts"):
        distributed.host_part(65, 0, 2)


@pytest.mark.parametrize("env, expected", [
    ({}, None),
    ({"SLURM_JOB_ID": "7", "SLURM_NTASKS": "1"}, None),  # a one-task Slurm job: one host
    ({"SLURM_JOB_ID": "7", "SLURM_NTASKS": "4"}, "SLURM_JOB_ID"),
    ({"OMPI_COMM_WORLD_SIZE": "2"}, "OMPI_COMM_WORLD_SIZE"),
    ({"JAX_COORDINATOR_ADDRESS": "h:1234"}, None),  # no process count: one process
    ({"JAX_COORDINATOR_ADDRESS": "h:1234", "JAX_NUM_PROCESSES": "2"}, "JAX_COORDINATOR_ADDRESS"),
    ({"TPU_WORKER_HOSTNAMES": "a,b"}, "TPU_WORKER_HOSTNAMES"),
    ({"TPU_WORKER_HOSTNAMES": "a"}, None),
])
def test_cluster_environment(env, expected):
    assert distributed.cluster_environment(env) == expected


def test_initialize_single_host_and_bad_cluster_env():
    assert distributed.initialize({}) is False  # nothing to connect
    with pytest.raises(ValueError, match="JAX_PROCESS_ID is not"):
        distributed.initialize({"JAX_COORDINATOR_ADDRESS": "127.0.0.1:1",
                                "JAX_NUM_PROCESSES": "2"})


@pytest.mark.skipif(not os.environ.get("FLOWMAPS_TEST_MULTIHOST"),
                    reason="opt-in (about 2 minutes on 2 cores): FLOWMAPS_TEST_MULTIHOST=1")
def test_two_hosts():
    """Two processes joined by jax.distributed train one model, each on its share of the data,
    and one process continues their checkpoint (experiments/check_multihost.py). Opt-in:
    FLOWMAPS_TEST_MULTIHOST=1 pytest tests/test_distributed.py."""
    proc = subprocess.run([sys.executable, str(TESTS.parent / "experiments/check_multihost.py")],
                          capture_output=True, text=True, timeout=1800)
    assert proc.returncode == 0, proc.stdout[-6000:] + proc.stderr[-3000:]
    assert "multi-host check: passed" in proc.stdout
