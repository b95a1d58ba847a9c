"""Training: EMA, schedule, the jitted step, validation loss, and the train CLI end to end.

Compiled functions are shared through module-scoped fixtures; models are the tiny smoke preset.
"""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from flowmaps_jax.predictor import load
from flowmaps_jax.store import checkpoints
from flowmaps_jax.tokens import Queries, SceneTokens, TrainBatch
from flowmaps_jax.training import loop, objectives
from flowmaps_jax.training import state as train_state
from flowmaps_jax.training.config import apply_overrides, get_preset
from flowmaps_jax.worlds import flowsim as data

SMOKE = get_preset("smoke")


def synthetic_batch(key, batch_size=8, queries=2, tokens=20, real=13) -> TrainBatch:
    """A valid random TrainBatch (13 real tokens: 10 furniture + 3 objects, then padding)."""
    k_box, k_desc, k_tau, _, k_target = jax.random.split(key, 5)  # same keys as before
    mask = jnp.broadcast_to(jnp.arange(tokens) < real, (batch_size, tokens))
    boxes = jax.random.uniform(k_box, (batch_size, tokens, 4), maxval=0.5) * mask[..., None]
    kind = (jnp.arange(tokens) >= 10).astype(jnp.int32) * mask
    desc = jax.random.randint(k_desc, (batch_size, tokens), 0, 6) * mask
    tau = jax.random.randint(k_tau, (batch_size,), 0, 18)
    tau_q = jnp.broadcast_to(tau[:, None] + 1, (batch_size, queries))
    scene = SceneTokens(boxes=boxes, descriptor=desc.astype(jnp.int32),
                        kind=kind.astype(jnp.int32), mask=mask, tau=tau.astype(jnp.int32))
    query = Queries(descriptor=jnp.zeros((batch_size, queries), jnp.int32),
                    tau_q=tau_q.astype(jnp.int32))
    target = jax.random.uniform(k_target, (batch_size, queries, 4), maxval=0.5)
    return TrainBatch(tokens=scene, queries=query, target=target)


FIXED_BATCH = synthetic_batch(jax.random.PRNGKey(42))


def fixed_batch_fn(key, scenes):
    """Stand-in data: always the same batch (the loss on it must fall)."""
    del key, scenes
    return FIXED_BATCH


# --------------------------------------------------------------------------------------------
# Pure pieces


def test_ema_update_matches_the_formula():
    ema = {"a": jnp.array([1.0, 2.0]), "b": {"c": jnp.array(3.0)}}
    params = {"a": jnp.array([5.0, -2.0]), "b": {"c": jnp.array(0.0)}}
    out = train_state.ema_update(ema, params, 0.9)
    np.testing.assert_allclose(out["a"], 0.9 * np.array([1.0, 2.0]) + 0.1 * np.array([5.0, -2.0]),
                               rtol=1e-6)
    np.testing.assert_allclose(out["b"]["c"], 2.7, rtol=1e-6)
    np.testing.assert_array_equal(train_state.ema_update(ema, params, 0.0)["a"], params["a"])


def test_schedule_warmup_then_cosine():
    cfg = apply_overrides(SMOKE, {"lr": 1e-3, "warmup_steps": 10, "steps": 110})
    schedule = train_state.make_schedule(cfg)
    assert float(schedule(0)) == 0.0
    np.testing.assert_allclose(float(schedule(5)), 0.5e-3, rtol=1e-5)
    np.testing.assert_allclose(float(schedule(10)), 1e-3, rtol=1e-5)
    np.testing.assert_allclose(float(schedule(60)), 0.5e-3, rtol=1e-4)  # half-way down the cosine
    assert abs(float(schedule(110))) < 1e-9


def test_schedule_without_warmup_starts_at_peak():
    cfg = apply_overrides(SMOKE, {"lr": 1e-4, "warmup_steps": 0, "steps": 100})
    schedule = train_state.make_schedule(cfg)
    np.testing.assert_allclose(float(schedule(0)), 1e-4, rtol=1e-6)
    np.testing.assert_allclose(float(schedule(50)), 0.5e-4, rtol=1e-4)


def test_optimizer_applies_decoupled_weight_decay_and_clipping():
    cfg = apply_overrides(SMOKE, {"lr": 0.1, "warmup_steps": 0, "steps": 10,
                                  "weight_decay": 0.5, "clip_norm": "none"})
    tx = train_state.make_optimizer(cfg)
    params = {"w": jnp.array([2.0, -4.0])}
    updates, _ = tx.update({"w": jnp.zeros(2)}, tx.init(params), params)
    np.testing.assert_allclose(updates["w"], -0.1 * 0.5 * params["w"], rtol=1e-6)
    # Clipping: AdamW normalises the gradient's scale, so check the first moment, which after
    # one step is (1 - b1) * the (clipped) gradient.
    big = {"w": jnp.array([3e3, 4e3])}
    for clip, norm in ((1.0, 1.0), ("none", 5e3)):
        tx = train_state.make_optimizer(apply_overrides(cfg, {"clip_norm": clip}))
        _, state = tx.update(big, tx.init(params), params)
        mu = optax.tree_utils.tree_get(state, "mu")
        np.testing.assert_allclose(optax.tree.norm(mu), (1 - cfg.b1) * norm, rtol=1e-5)


def test_default_batches_trim_only_padding(small_scenes):
    """The trainer's batches keep the F + M real tokens and drop only padding slots."""
    cfg = SMOKE
    key = jax.random.PRNGKey(3)
    from flowmaps_jax.flowsim.scenes import make_train_batch
    full = make_train_batch(key, small_scenes, cfg.batch_size, cfg.queries_per_scene,
                            cfg.flowsim)
    trimmed = data.default_batch_fn(cfg)(key, small_scenes)
    real = cfg.flowsim.num_furniture + cfg.flowsim.num_objects
    assert trimmed.tokens.mask.shape == (cfg.batch_size, real)
    assert bool(full.tokens.mask[:, :real].all()) and not bool(full.tokens.mask[:, real:].any())
    np.testing.assert_array_equal(trimmed.tokens.boxes, full.tokens.boxes[:, :real])
    np.testing.assert_array_equal(trimmed.target, full.target)


# --------------------------------------------------------------------------------------------
# The jitted step (real FlowMaps smoke model, stand-in data)


@pytest.fixture(scope="module")
def flow_setup():
    """The smoke FlowMaps model with a compiled (unfused) train step, shared. The objective and
    eval loss are the CLI's cached ones for SMOKE, so their compilation is shared too."""
    cfg = apply_overrides(SMOKE, {"lr": 3e-3, "steps": 200, "warmup_steps": 0})
    objective, _, eval_fn = loop.compiled_functions(SMOKE)
    return {"cfg": cfg, "objective": objective,
            "step_fn": train_state.make_train_step(cfg, objective),
            "eval_fn": eval_fn,
            # same shapes as SMOKE's validation batches (val_batches=2 stacked)
            "stacked": jax.tree.map(lambda x: jnp.stack([x, x]), FIXED_BATCH)}


@pytest.fixture(scope="module")
def fitted(flow_setup):
    """80 steps on one fixed batch (fresh noise per step); loss before/after on fixed noise."""
    cfg, step_fn, eval_fn = flow_setup["cfg"], flow_setup["step_fn"], flow_setup["eval_fn"]
    state = train_state.init_state(cfg, objective=flow_setup["objective"])
    start = float(eval_fn(state.params, flow_setup["stacked"]))
    losses = []
    for i in range(80):
        state, metrics = step_fn(state, FIXED_BATCH, jax.random.PRNGKey(i))
        losses.append(float(metrics["loss"]))
    end = float(eval_fn(state.params, flow_setup["stacked"]))
    return {**flow_setup, "state": state, "start": start, "end": end, "losses": losses}


def test_loss_falls_well_below_its_start(fitted):
    assert all(math.isfinite(x) for x in fitted["losses"])
    assert fitted["end"] < 0.6 * fitted["start"], (fitted["start"], fitted["end"])
    assert np.mean(fitted["losses"][-10:]) < 0.7 * np.mean(fitted["losses"][:5])
    assert int(fitted["state"].step) == 80


def test_eval_loss_is_deterministic(fitted):
    eval_fn, state = fitted["eval_fn"], fitted["state"]
    first = float(eval_fn(state.ema_params, fitted["stacked"]))
    assert first == float(eval_fn(state.ema_params, fitted["stacked"]))
    # No dropout and fixed noise: the EMA and raw params give different, repeatable values.
    raw = float(eval_fn(state.params, fitted["stacked"]))
    assert raw != first and raw == float(eval_fn(state.params, fitted["stacked"]))


def test_train_step_updates_params_ema_and_step(flow_setup):
    cfg = flow_setup["cfg"]
    state = train_state.init_state(cfg, objective=flow_setup["objective"])
    before = jax.tree.map(np.array, state)  # copies: a zero-copy view would block donation
    new, metrics = flow_setup["step_fn"](state, FIXED_BATCH, jax.random.PRNGKey(3))
    assert int(new.step) == 1
    assert {"loss", "grad_norm", "lr"} <= set(metrics)
    assert all(np.ndim(v) == 0 and np.isfinite(v) for v in metrics.values())
    assert state.params["query_pos"].is_deleted()  # the input state was donated
    expected_ema = jax.tree.map(lambda e, p: cfg.ema_decay * e + (1 - cfg.ema_decay) * p,
                                before.ema_params, jax.tree.map(np.asarray, new.params))
    for got, want in zip(jax.tree.leaves(new.ema_params), jax.tree.leaves(expected_ema),
                         strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-7)
    changed = [not np.array_equal(a, b) for a, b in
               zip(jax.tree.leaves(before.params), jax.tree.leaves(new.params), strict=True)]
    assert any(changed)


def test_bad_step_inputs_raise_value_error(flow_setup):
    state = train_state.init_state(flow_setup["cfg"], objective=flow_setup["objective"])
    bad = FIXED_BATCH.replace(target=FIXED_BATCH.target[:, :1])  # Q = 1 target for Q = 2
    with pytest.raises(ValueError, match="batch"):
        flow_setup["step_fn"](state, bad, jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="TrainBatch"):
        flow_setup["step_fn"](state, {"target": FIXED_BATCH.target}, jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="TrainConfig"):
        train_state.init_state({"lr": 1.0})


def test_same_state_batch_and_key_give_the_same_step(flow_setup):
    cfg, step_fn = flow_setup["cfg"], flow_setup["step_fn"]
    a, _ = step_fn(train_state.init_state(cfg, objective=flow_setup["objective"]), FIXED_BATCH,
                   jax.random.PRNGKey(5))
    b, _ = step_fn(train_state.init_state(cfg, objective=flow_setup["objective"]), FIXED_BATCH,
                   jax.random.PRNGKey(5))
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)
    keys = [train_state.step_keys(a)[0], train_state.step_keys(a.replace(step=a.step + 1))[0]]
    assert not np.array_equal(*keys)  # each step draws a different batch


def test_mlp_baseline_trains_with_learned_variance():
    cfg = apply_overrides(SMOKE, {"family": "mlp", "model.baseline_variance": "learned",
                                  "lr": 3e-3, "steps": 100})
    objective = objectives.objective_for(cfg)
    step_fn = train_state.make_fused_train_step(cfg, objective, batch_fn=fixed_batch_fn)
    state = train_state.init_state(cfg, objective=objective)
    losses = []
    for _ in range(30):
        state, metrics = step_fn(state, None)
        losses.append(float(metrics["loss"]))
    assert all(math.isfinite(x) for x in losses)
    assert np.mean(losses[-5:]) < np.mean(losses[:3])


# --------------------------------------------------------------------------------------------
# The CLI / run loop on real FlowSim data (all runs share SMOKE, so they share one compilation)


def _leaves(state):
    return [np.asarray(x) for x in jax.tree.leaves(state)]


@pytest.fixture(scope="module")
def straight_run(flowsim_runs):
    """``python -m flowmaps_jax.train --preset smoke`` in-process: 20 steps straight (the
    session's run, tests/conftest.py): (exit code, run dir, what it printed)."""
    return 0, flowsim_runs.straight, flowsim_runs.printed


def test_cli_smoke_run_writes_config_metrics_and_checkpoints(straight_run):
    code, run_dir, printed = straight_run
    assert code == 0
    assert "model.dim" in printed and "Generating the FlowSim training split" in printed
    assert f"python -m flowmaps_jax.evaluate --checkpoint {run_dir / 'checkpoints'}" in printed
    from flowmaps_jax.training.config import TrainConfig

    assert TrainConfig.from_dict(json.loads((run_dir / "config.json").read_text())) == SMOKE
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    train_steps = [r["step"] for r in records if r["kind"] == "train"]
    val_steps = [r["step"] for r in records if r["kind"] == "val"]
    assert train_steps == [5, 10, 15, 20] and val_steps == [0, 10, 20]
    assert all(math.isfinite(r["loss"]) and r["lr"] >= 0 for r in records if r["kind"] == "train")
    # the routine diagnostic runs at every validation and its learning curve is drawn
    routine = [r for r in records if r["kind"] == "routine"]
    assert [r["step"] for r in routine] == val_steps
    assert all(0.0 <= r["offset_+1"] <= 1.0 and r["search_cost_ratio"] >= 1.0 for r in routine)
    assert "Routines at step 20" in printed
    assert (run_dir / "routine_curve.png").stat().st_size > 10_000
    state, config = checkpoints.restore(run_dir, train_state.abstract_state(SMOKE))[:2]
    assert int(state.step) == 20 and config == SMOKE.to_dict()
    best = checkpoints.restore(run_dir, train_state.abstract_state(SMOKE), which="best").state
    assert int(best.step) in (10, 20)
    # the run directory is printed at the start; the summary names the best step and the last
    start = printed.index(f"Run directory: {run_dir.absolute()}")
    assert start < printed.index("Compiling")
    assert f"at step {int(best.step)})" in printed.split("best validation loss")[1].split("\n")[0]
    assert (f"load the best step, {int(best.step)}, by default; --which latest loads step 20"
            if int(best.step) != 20 else "the best step is the last, 20") in printed
    assert "rank cost" in printed and "search cost" not in printed
    predictor = load(run_dir)
    assert predictor.model == SMOKE.model and predictor.step == int(best.step)
    for got, want in zip(_leaves(predictor.params), _leaves(best.ema_params), strict=True):
        np.testing.assert_array_equal(got, want)


def test_nan_loss_stops_and_keeps_the_last_good_checkpoint(tmp_path, monkeypatch, capsys):
    objective, step_fn, eval_fn = loop.compiled_functions(SMOKE)

    def poisoned_step(state, scenes):
        step = int(state.step)
        state, metrics = step_fn(state, scenes)
        if step >= 12:  # pretend the loss blew up from step 13 on
            metrics = {**metrics, "loss": jnp.float32(jnp.nan)}
        return state, metrics

    monkeypatch.setattr(loop, "compiled_functions",
                        lambda cfg, mesh=None: loop.Compiled(objective, poisoned_step,
                                                              eval_fn))
    result = loop.run(SMOKE, tmp_path, progress=False)
    assert result.status == "nan" and result.step == 12 and result.state is None
    assert "Loss is nan at step 13" in capsys.readouterr().out
    state = checkpoints.restore(tmp_path, train_state.abstract_state(SMOKE)).state
    assert int(state.step) == 10  # the last good checkpoint; nothing saved after the NaN
    assert sorted(int(p.name) for p in (tmp_path / "checkpoints" / "last").iterdir()) == [10]


def test_endless_data_is_fresh_and_resumes_exactly(straight_run, tmp_path):
    cfg = apply_overrides(SMOKE, {"data": "endless"})  # chunks of 64 new envs every 8 steps
    straight = loop.run(cfg, tmp_path / "straight", progress=False)
    loop.run(cfg, tmp_path / "split", stop_at=10, progress=False)  # stops mid-chunk
    resumed = loop.run(cfg, tmp_path / "split", resume=True, progress=False)
    assert straight.status == resumed.status == "done"
    for a, b in zip(_leaves(straight.state), _leaves(resumed.state), strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)
    fixed_split = checkpoints.restore(straight_run[1], train_state.abstract_state(SMOKE)).state
    pairs = zip(_leaves(straight.state.params), _leaves(fixed_split.params), strict=True)
    assert any(not np.allclose(a, b) for a, b in pairs)  # other data, other weights


def test_init_from_starts_at_the_given_weights(straight_run, tmp_path):
    """A warm start (``--init-from``): step 1 starts from the source's EMA weights, not from
    a random init; a run that cannot use them stops before writing anything."""
    source = load(straight_run[1])
    cfg = apply_overrides(SMOKE, {"init_from": str(straight_run[1])})
    result = loop.run(cfg, tmp_path / "warm", stop_at=1, progress=False)
    fresh = train_state.init_state(SMOKE).params  # the source's own init, 20 steps before it
    warm_gap = max(float(np.max(np.abs(a - b))) for a, b in
                   zip(_leaves(result.state.ema_params), _leaves(source.params), strict=True))
    fresh_gap = max(float(np.max(np.abs(a - b))) for a, b in
                    zip(_leaves(fresh), _leaves(source.params), strict=True))
    # one step (lr 1e-3, EMA 0.9) from the source: far closer than the random init it came from
    assert warm_gap < fresh_gap / 10
    with pytest.raises(ValueError, match="init_from"):
        loop.run(apply_overrides(SMOKE, {"init_from": str(tmp_path / "missing")}),
                 tmp_path / "bad", progress=False)
    wider = apply_overrides(cfg, {"model.dim": 48})
    with pytest.raises(ValueError, match=r"init_from=.*shape"):
        loop.run(wider, tmp_path / "wider", progress=False)
    assert not (tmp_path / "bad" / "config.json").exists()
    assert not (tmp_path / "wider" / "config.json").exists()


def test_overlay_params_keeps_new_leaves_and_refuses_other_architectures():
    fresh = {"params": {"a": jnp.zeros((2,)), "age_embed": jnp.ones((3, 2))}}
    out = train_state.overlay_params(fresh, {"params": {"a": np.full((2,), 5.0)}})
    np.testing.assert_array_equal(out["params"]["a"], [5.0, 5.0])
    np.testing.assert_array_equal(out["params"]["age_embed"], np.ones((3, 2)))
    with pytest.raises(ValueError, match=r"init_from.*no parameter.*'b'"):
        train_state.overlay_params(fresh, {"params": {"b": np.zeros(2)}})
    with pytest.raises(ValueError, match=r"init_from.*shape \(3,\)"):
        train_state.overlay_params(fresh, {"params": {"a": np.zeros(3)}})
