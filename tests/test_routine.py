"""Learning the routines: the pointer read-out's mixture velocity, the routine diagnostic,
short-horizon sampling, target jitter and Δτ conditioning."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from flowmaps_jax import flow
from flowmaps_jax.boxes import to_centre
from flowmaps_jax.evaluation import routine
from flowmaps_jax.evaluation.kl import gt_mixture_sigma
from flowmaps_jax.evaluation.priors import oracle_slots
from flowmaps_jax.evaluation.slots import ROUTE_OFFSET_LABELS, route_offset_mass
from flowmaps_jax.flowsim.scenes import make_train_batch
from flowmaps_jax.model import ModelConfig, encode, init_params, velocity
from flowmaps_jax.model.readout import mixture_velocity
from flowmaps_jax.predictor import Predictor
from flowmaps_jax.tokens import Queries
from flowmaps_jax.training.config import get_preset
from flowmaps_jax.worlds import flowsim as flowsim_world

POINTER = ModelConfig(dim=32, encoder_layers=1, cdit_blocks=1, heads=2, mlp_ratio=2,
                      freq_bands=8, baseline_hidden=32, head="pointer", condition_on_dtau=True)


def test_mixture_velocity_single_gaussian_is_the_closed_form():
    """One component N(μ, σ²): v = (E[X_1 | x_t] − x_t) / (1 − t) with the Gaussian posterior."""
    mu = np.array([0.3, -0.2, 0.05, 0.1], np.float32)
    log_var = np.log(np.array([0.04, 0.01, 1e-4, 4e-4], np.float32))
    x = np.asarray(jax.random.normal(jax.random.key(0), (7, 4)))
    velocity = jax.jit(mixture_velocity)  # one program for every t
    for t in (0.0, 0.3, 0.9):
        v = velocity(np.zeros((1, 1, 7, 1), np.float32), np.broadcast_to(mu, (1, 1, 7, 1, 4)),
                     log_var[None, None, None, None], x[None, None],
                     np.full((1, 1), t, np.float32))
        var0 = np.exp(log_var)
        post_mean = mu + t * var0 / (t**2 * var0 + (1 - t) ** 2) * (x - t * mu)
        np.testing.assert_allclose(v[0, 0], (post_mean - x) / (1 - t), rtol=1e-4, atol=1e-5)


def test_mixture_velocity_transports_noise_to_the_mixture():
    """Integrating the field from N(0, I) lands on the components with their weights."""
    means = jnp.array([[0.2, 0.2, 0.05, 0.05], [0.7, 0.3, 0.05, 0.05], [0.5, 0.8, 0.05, 0.05]])
    weights = jnp.array([0.2, 0.7, 0.1])
    log_var = jnp.log(jnp.full((4,), 1e-4))
    n = 4000

    def fn(x, t):
        return mixture_velocity(jnp.broadcast_to(jnp.log(weights), (1, 1, n, 3)),
                                jnp.broadcast_to(means, (1, 1, n, 3, 4)),
                                log_var[None, None, None, None], x, jnp.full((1, 1), t))

    x0 = jax.random.normal(jax.random.key(1), (1, 1, n, 4))
    x1 = flow.integrate(fn, x0, num_steps=40)[0, 0]
    nearest = jnp.argmin(jnp.linalg.norm(x1[:, None] - means[None], axis=-1), axis=-1)
    dist = jnp.min(jnp.linalg.norm(x1[:, None] - means[None], axis=-1), axis=-1)
    assert float(jnp.mean(dist < 0.05)) > 0.99
    np.testing.assert_allclose(np.bincount(np.asarray(nearest), minlength=3) / n, weights,
                               atol=0.03)


def test_pointer_head_samples_sit_on_map_tokens_from_the_start(small_scenes, flowsim_config):
    """At init (A, B = "centred on the anchor, with the source's size", σ = 0.02) the pointer
    head's flow already centres every sample on a real token, never on the padding, and its
    field is finite at t = 1."""
    from flowmaps_jax.flowsim.scenes import scene_tokens

    params = init_params(jax.random.key(0), POINTER)
    tokens = scene_tokens(small_scenes, np.arange(2), np.array([3, 5]), flowsim_config)
    queries = Queries(descriptor=jnp.array([[0], [1]]), tau_q=jnp.array([[4], [9]]))
    x = Predictor.from_params(params, POINTER).sample(tokens, queries, 200, jax.random.key(1))
    centre = lambda b: b[..., :2] + b[..., 2:] / 2  # noqa: E731
    real = centre(np.asarray(tokens.boxes)[:, :13])  # F + M = 13 real tokens, then padding
    dist = np.linalg.norm(centre(np.asarray(x))[:, 0, :, None] - real[:, None], axis=-1).min(-1)
    # σ = 0.02 per number: median centre distance ~0.03; uniform points would be ~0.14 away
    assert np.median(dist) < 0.05 and np.percentile(dist, 90) < 0.1
    assert np.linalg.norm(centre(np.asarray(x)), axis=-1).min() > 0.05  # none at the padding
    context = encode(params, POINTER, tokens)
    v1 = velocity(params, POINTER, context, x[:, :, :5], jnp.ones((2, 1)), queries)
    assert np.all(np.isfinite(np.asarray(v1)))


def test_dtau_conditioning_changes_the_field_and_paper_config_has_no_dtau_params():
    params = init_params(jax.random.key(0), POINTER)
    assert "dtau_embed" in params
    plain = init_params(jax.random.key(0), dataclasses.replace(POINTER, head="velocity",
                                                               condition_on_dtau=False))
    assert "dtau_embed" not in plain and "readout" not in plain
    with pytest.raises(ValueError, match="head"):
        dataclasses.replace(POINTER, head="pointers")
    with pytest.raises(ValueError, match="condition_on_dtau"):
        dataclasses.replace(POINTER, condition_on_dtau="yes")


def test_routine_diagnostic_scores_the_exact_posterior_and_a_fresh_model(small_scenes,
                                                                          flowsim_config):
    probe = routine.build_probe(small_scenes, flowsim_config, num_envs=6)
    assert np.all(np.asarray(probe.one_step.horizon) == 1)
    exact = route_offset_mass(oracle_slots(probe.one_step.slot_probs),
                              probe.one_step.slot_now, probe.one_step.num_slots)
    np.testing.assert_allclose(np.asarray(exact).mean(axis=(0, 1)), routine.EXACT_ONE_STEP,
                               atol=1e-5)
    predictor = Predictor.from_params(init_params(jax.random.key(0), POINTER), POINTER)
    out = routine.routine_metrics(predictor, probe, num_samples=4)
    mass = [out[f"offset_{k}"] for k in ROUTE_OFFSET_LABELS]
    assert abs(sum(mass) - 1.0) < 1e-5
    assert 0.0 <= out["tv"] <= 1.0 and out["search_cost_ratio"] >= 1.0
    with pytest.raises(ValueError, match="num_envs"):
        routine.build_probe(small_scenes, flowsim_config, num_envs=10_000)


def test_a_history_model_is_probed_with_its_own_maps(small_scenes, flowsim_config):
    """For a model reading H = 2 maps the probe's tokens hold the objects of both maps (ages 0
    and 1, 10 + 3 × 2 real tokens); in the routine world the truth is the same Markov law."""
    probe = routine.build_probe(small_scenes, flowsim_config, num_envs=6, history=2)
    tokens = probe.one_step.tokens
    assert tokens.age is not None and int(np.max(np.asarray(tokens.age))) == 1
    assert np.all(np.asarray(tokens.mask).sum(-1)[np.asarray(probe.one_step.tau) > 0] == 16)
    exact = route_offset_mass(oracle_slots(probe.one_step.slot_probs),
                              probe.one_step.slot_now, probe.one_step.num_slots)
    np.testing.assert_allclose(np.asarray(exact).mean(axis=(0, 1)), routine.EXACT_ONE_STEP,
                               atol=1e-5)


def test_learning_curve_figure_and_missing_records(tmp_path):
    records = [{"kind": "routine", "step": s, **{f"offset_{k}": 0.1 for k in
                                                 ROUTE_OFFSET_LABELS},
                "tv": 0.5, "one_step_tv": 0.4, "search_cost_ratio": 1.1} for s in (0, 100)]
    (tmp_path / "metrics.jsonl").write_text(
        "\n".join(__import__("json").dumps(r) for r in [{"kind": "val", "step": 0}, *records]))
    loaded = routine.read_routine_records(tmp_path)
    assert [r["step"] for r in loaded] == [0, 100]
    fig = routine.plot_learning_curve(loaded)
    assert len(fig.axes) == 2
    with pytest.raises(ValueError, match="records"):
        routine.plot_learning_curve([])
    with pytest.raises(ValueError, match="metrics_path"):
        routine.read_routine_records(tmp_path / "nothing")


def test_short_horizons_are_oversampled(small_scenes, flowsim_config):
    key = jax.random.key(3)
    plain = make_train_batch(key, small_scenes, 64, 8, flowsim_config)
    short = make_train_batch(key, small_scenes, 64, 8, flowsim_config, short_frac=1.0,
                             short_max=2)
    dt = np.asarray(short.queries.tau_q - short.tokens.tau[:, None])
    assert dt.min() >= 1 and dt.max() <= 2
    dt_plain = np.asarray(plain.queries.tau_q - plain.tokens.tau[:, None])
    assert dt_plain.max() > 2
    with pytest.raises(ValueError, match="short_frac"):
        make_train_batch(key, small_scenes, 4, 2, flowsim_config, short_frac=1.5)


def test_target_jitter_has_the_protocol_std():
    box = jnp.array([0.3, 0.4, 0.05, 0.08])
    boxes = jnp.broadcast_to(box, (20000, 4))
    out = flowsim_world.jitter_targets(jax.random.key(0), boxes, 1.0)
    spread = np.asarray(to_centre(out)).std(axis=0)
    expected = np.asarray(gt_mixture_sigma(box[None]))[0]
    np.testing.assert_allclose(spread, expected, rtol=0.05)
    cfg = dataclasses.replace(get_preset("smoke"), target_noise=1.0)
    with pytest.raises(ValueError, match="target_noise"):
        dataclasses.replace(cfg, target_noise=-1.0)
