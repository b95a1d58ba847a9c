"""Data parallelism on two (forced host) devices: the numbers must not depend on the device count.

Run by tests/test_distributed.py in a subprocess with
``XLA_FLAGS=--xla_force_host_platform_device_count=2 FLOWMAPS_MULTIDEVICE=1`` (the device count is
fixed when JAX starts). Everything runs on the smoke preset.
"""

from __future__ import annotations

import pathlib
import shutil

import jax
import numpy as np
import pytest
from support import TINY, perturb

from flowmaps_jax import distributed
from flowmaps_jax.flowsim import generate
from flowmaps_jax.model import init_params
from flowmaps_jax.predictor import Predictor
from flowmaps_jax.store import checkpoints
from flowmaps_jax.training import loop, state
from flowmaps_jax.training.config import apply_overrides, get_preset

assert jax.device_count() == 2, "run with XLA_FLAGS=--xla_force_host_platform_device_count=2"

STEPS = 6
SMOKE = apply_overrides(get_preset("smoke"), [f"steps={STEPS}", "routine_envs=0", "log_every=1",
                                              "val_every=3", "ckpt_every=3"])
# Measured between 1 and 2 devices after 6 steps (float summation order is the only
# difference): 1e-7 (loss, relative) and 1.4e-5 (state; Adam magnifies the rounding of tiny
# gradients) with the suite's classic XLA:CPU emitter (tests/conftest.py), 6e-8 and 1.6e-7 with
# the default fusion emitters. Adam moves a parameter by about lr = 1e-3 a step whatever the
# scale of its gradient: a step with a wrong gradient is off by about that much.
LOSS_TOL, PARAM_TOL = 1e-5, 1e-4


def _train(tmp: pathlib.Path, devices: int, **kwargs):
    cfg = apply_overrides(SMOKE, [f"devices={devices}"])
    losses: list[float] = []
    result = loop.run(cfg, tmp, progress=False, log=lambda _: None,
                      on_step=lambda _, m: losses.append(m["loss"]), **kwargs)
    return result, losses


def _max_diff(a, b) -> float:
    return max(float(np.max(np.abs(np.asarray(x) - np.asarray(y))))
               for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The same smoke training on 1 and on 2 devices (checkpoints at steps 3 and 6)."""
    root = tmp_path_factory.mktemp("runs")
    return {"one": _train(root / "one", 1), "two": _train(root / "two", 2)}


def test_two_devices_train_like_one(runs):
    (one, losses_1), (two, losses_2) = runs["one"], runs["two"]
    assert one.status == two.status == "done" and len(losses_1) == len(losses_2) == STEPS
    np.testing.assert_allclose(losses_2, losses_1, rtol=LOSS_TOL, atol=0)
    assert _max_diff(one.state.params, two.state.params) < PARAM_TOL
    assert _max_diff(one.state.opt_state, two.state.opt_state) < PARAM_TOL
    # The 2-device state really is replicated over both devices, the 1-device one is not.
    leaf = jax.tree.leaves(two.state.params)[0]
    assert leaf.sharding.is_fully_replicated and len(leaf.sharding.device_set) == 2
    assert len(jax.tree.leaves(one.state.params)[0].sharding.device_set) == 1


def test_checkpoint_from_two_devices_continues_on_one(runs, tmp_path):
    two, straight = runs["two"]
    run_dir = tmp_path / "copy"
    shutil.copytree(two.run_dir, run_dir)
    ckpt = run_dir / "checkpoints"
    on_two = checkpoints.restore(ckpt, state.abstract_state(SMOKE, mesh=distributed.data_mesh()),
                                step=3).state
    on_one = checkpoints.restore(ckpt, state.abstract_state(SMOKE), step=3).state
    assert int(on_one.step) == 3
    assert len(jax.tree.leaves(on_one.params)[0].sharding.device_set) == 1
    assert len(jax.tree.leaves(on_two.params)[0].sharding.device_set) == 2
    assert _max_diff(on_one, on_two) == 0.0  # bit-exact, every leaf of the state
    # Continue on one device from step 3: the remaining steps match the 2-device run.
    resumed, losses = _train(run_dir, 1, resume=True, from_step=3)
    assert resumed.status == "done" and len(losses) == STEPS - 3
    np.testing.assert_allclose(losses, straight[3:], rtol=LOSS_TOL, atol=0)
    assert _max_diff(resumed.state.params, two.state.params) < PARAM_TOL


def test_batch_that_does_not_divide_is_refused(tmp_path):
    cfg = apply_overrides(SMOKE, ["batch_size=7"])
    with pytest.raises(ValueError, match=r"batch_size=7 does not divide evenly over the 2 "
                                         r"devices.*multiple of 2"):
        loop.run(cfg, tmp_path / "r", progress=False, log=lambda _: None)
    assert not (tmp_path / "r").exists() or not any((tmp_path / "r").iterdir())
    with pytest.raises(ValueError, match=r"devices \(JAX sees 2 .*\) must be an int in 1\.\.2; "
                                         r"got 3"):
        loop.run(apply_overrides(SMOKE, ["devices=3", "batch_size=9"]), tmp_path / "s",
                 progress=False, log=lambda _: None)


def test_incompatible_checkpoint_is_a_value_error(runs):
    run_dir = runs["two"][0].run_dir
    other = apply_overrides(SMOKE, ["model.dim=48"])
    with pytest.raises(ValueError, match="does not match the model"):
        checkpoints.restore(run_dir / "checkpoints",
                           state.abstract_state(other, mesh=distributed.data_mesh()))
    with pytest.raises(ValueError, match=r"--resume cannot change model\.dim"):
        loop.run(apply_overrides(other, ["steps=8"]), run_dir, resume=True, progress=False,
                 log=lambda _: None)


@pytest.mark.parametrize("num_envs", [63, 64])  # 63: padded to 64 on two devices
def test_sharded_generate_equals_unsharded(num_envs):
    key = jax.random.key(5)
    whole = generate(key, num_envs)
    split = generate(key, num_envs, mesh=distributed.data_mesh())
    for a, b in zip(jax.tree.leaves(whole), jax.tree.leaves(split), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    if num_envs % 2 == 0:  # the work really was split over both devices
        assert len(split.furniture_boxes.sharding.device_set) == 2


def test_sharded_sampling_and_evaluation_equal_unsharded():
    """Predictor.sample / log_prob split over both devices equal one device's, and so does the
    evaluation protocol built on them (6 environments in chunks of 3: padded to 4 on two
    devices; the paper's likelihood only: the solver is inside the model's log_prob, which the
    split wraps the same way for every solver). The direct calls use the protocol's shapes, so
    both share compiled code; the scenes are 6 of 64, the size of the other tests' (one compiled
    generator)."""
    from flowmaps_jax.evaluation import build_eval_queries, run_evaluation
    from flowmaps_jax.flowsim import FlowSimConfig, validation_split

    sim = FlowSimConfig()
    scenes = jax.tree.map(lambda a: a[:6], validation_split(sim, SMOKE.val_envs,
                                                            mesh=distributed.data_mesh()))
    params = perturb(init_params(jax.random.key(0), TINY), jax.random.key(1))
    one = Predictor.from_params(params, TINY)
    two = one.sharded()
    assert two.mesh is not None and two.mesh.size == 2 and one.sharded(1) is one
    assert len(two.params["query_pos"].sharding.device_set) == 2  # params replicated

    part = build_eval_queries(scenes, sim, jax.random.key(0), kl_draws=8).take(np.arange(3))
    keys = jax.random.split(jax.random.key(2), 3)
    a, b = (p.sample(part.tokens, part.queries, 4, keys) for p in (one, two))
    assert a.shape == b.shape == (3, 3, 4, 4)
    # Measured with support.perturb's host-drawn noise (classic emitter): 7.2e-7 (samples),
    # 5.4e-7 relative and 2.9e-6 absolute (log p).
    np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=0, atol=2e-5)
    np.testing.assert_allclose(np.asarray(two.log_prob(part.tokens, part.queries, part.kl_points)),
                               np.asarray(one.log_prob(part.tokens, part.queries, part.kl_points)),
                               rtol=1e-5, atol=1e-5)

    reports = [run_evaluation([p], scenes, sim, None, seed=0, sample_counts=(4,), kl_draws=8,
                              chunk_envs=3, likelihood_steps=None, figures=False,
                              progress=False)[0]
               for p in (one, two)]
    rows = [r["rows"] for r in reports]
    assert rows[0].keys() == rows[1].keys()
    for name in rows[0]:
        a, b = _numbers(rows[0][name]), _numbers(rows[1][name])
        assert a.keys() == b.keys() and a
        for key in (k for k in a if "seconds" not in k):  # wall-clock times differ
            assert b[key] == pytest.approx(a[key], rel=1e-5, abs=1e-6), (name, key)


def _numbers(tree, prefix="") -> dict[str, float]:
    """Every number in a nested dict/list, by its path."""
    if isinstance(tree, dict):
        return {k: v for key, sub in tree.items() for k, v in _numbers(sub, f"{prefix}{key}/")
                .items()}
    if isinstance(tree, list):
        return {k: v for i, sub in enumerate(tree) for k, v in _numbers(sub, f"{prefix}{i}/")
                .items()}
    if isinstance(tree, (int, float)) and not isinstance(tree, bool):
        return {prefix: float(tree)}
    return {}
