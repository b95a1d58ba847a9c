"""Tests for flowmaps_jax.predictor: shapes, keys, validation, exact likelihood, checkpoint loading.

One tiny model config is shared by every test (module fixtures), so each jitted function compiles
once per input shape.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support import TINY, perturb, synthetic_queries, synthetic_tokens

from flowmaps_jax import flow, model
from flowmaps_jax.predictor import Predictor, load, load_pretrained
from flowmaps_jax.tokens import SceneTokens

CFG = TINY
B, S, Q = 2, 20, 3
N = 256  # one sample count for every FlowMaps call, so each function compiles once


def make_inputs(b: int = B, q: int = Q, seed: int = 0):
    """Valid tokens (b, S) with 13 real tokens and queries (b, q) with tau < tau_q."""
    tokens = synthetic_tokens(seed, (13,) * b)
    return tokens, synthetic_queries(tokens, q)


@pytest.fixture(scope="module")
def inputs():
    return make_inputs()


@pytest.fixture(scope="module")
def fresh():
    """FlowMaps at initialisation: zero velocity everywhere (AdaLN-Zero + zero final layer)."""
    return Predictor.from_params(model.init_params(jax.random.key(0), CFG), CFG)


@pytest.fixture(scope="module")
def flowmaps():
    """FlowMaps with a non-trivial velocity field (random, perturbed weights)."""
    params = perturb(model.init_params(jax.random.key(0), CFG), jax.random.key(1), 0.07)
    return Predictor.from_params(params, CFG)


@pytest.fixture(scope="module")
def mlp():
    cfg = dataclasses.replace(CFG, baseline_variance="learned")
    params = perturb(model.init_baseline(jax.random.key(2), cfg), jax.random.key(3), 0.3)
    return Predictor.from_params(params, cfg, family_name="mlp")


# --------------------------------------------------------------------------- sampling


def test_sample_shapes_and_pixels(flowmaps, inputs):
    tokens, queries = inputs
    key = jax.random.key(5)
    boxes = flowmaps.sample(tokens, queries, N, key)
    assert boxes.shape == (B, Q, N, 4)
    assert np.all(np.isfinite(boxes))
    pixels = flowmaps.sample(tokens, queries, N, key, pixels=True)
    scale = flowmaps.flowsim.map_size - 1
    np.testing.assert_allclose(pixels[..., :2], boxes[..., :2] * scale, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(pixels[..., 2:] - pixels[..., :2], boxes[..., 2:] * scale,
                               rtol=1e-5, atol=1e-3)


def test_sample_is_deterministic_by_key(flowmaps, inputs):
    tokens, queries = inputs
    a = flowmaps.sample(tokens, queries, N, jax.random.key(1))
    b = flowmaps.sample(tokens, queries, N, jax.random.key(1))
    c = flowmaps.sample(tokens, queries, N, jax.random.key(2))
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    legacy = flowmaps.sample(tokens, queries, N, jax.random.key(1))  # raw uint32 keys work
    assert legacy.shape == a.shape


def test_trailing_padding_is_dropped_without_changing_results(flowmaps, inputs):
    """The predictor trims empty token slots before the jitted model; results must not change."""
    from flowmaps_jax.model.flowmaps_family import flow_sample
    from flowmaps_jax.predictor import scene_keys

    tokens, queries = inputs
    keys = scene_keys(jax.random.key(4), B)
    untrimmed = flow_sample(flowmaps.params, CFG, jax.tree.map(jnp.asarray, tokens),
                            jax.tree.map(jnp.asarray, queries), keys, 8)
    trimmed = flowmaps.sample(tokens, queries, 8, keys)
    np.testing.assert_allclose(trimmed, untrimmed, atol=1e-4)


def test_per_scene_keys_make_samples_independent_of_the_batch(flowmaps, inputs):
    """With one key per scene, a scene's samples follow its key, wherever it sits in the batch."""
    tokens, queries = inputs
    keys = jax.random.split(jax.random.key(9), B)
    forward = flowmaps.sample(tokens, queries, N, keys)
    flipped = jax.tree_util.tree_map(lambda a: a[::-1], (tokens, queries))
    backward = flowmaps.sample(*flipped, N, keys[::-1])
    np.testing.assert_allclose(forward, backward[::-1], rtol=1e-5, atol=1e-5)
    assert not np.allclose(forward[0], forward[1])


# --------------------------------------------------------------------------- likelihood


def test_zero_velocity_flow_is_the_standard_normal(fresh, inputs):
    """Known case: at initialisation the velocity is 0, so samples are the noise itself and
    the likelihood is exactly N(x; 0, I)."""
    tokens, queries = inputs
    keys = jax.random.split(jax.random.key(3), B)
    samples = fresh.sample(tokens, queries, N, keys)
    noise = jax.vmap(lambda k: jax.random.normal(k, (Q, N, 4)))(keys)
    np.testing.assert_allclose(samples, noise, atol=1e-6)
    log_p = fresh.log_prob(tokens, queries, samples)
    expected = -0.5 * np.sum(np.square(samples), -1) - 2.0 * math.log(2 * math.pi)
    np.testing.assert_allclose(log_p, expected, rtol=1e-5, atol=1e-5)


def test_box_scale_maps_samples_and_densities_between_spaces(flowmaps, inputs):
    """The same weights with box_scale = 4, box_offset = 0.5 sample z/4 + 0.5 from the same noise,
    and their log-density is the identity model's at z = 4 (x − 0.5) plus 4 · log 4."""
    tokens, queries = inputs
    scaled = Predictor.from_params(flowmaps.params,
                                   dataclasses.replace(CFG, box_offset=0.5, box_scale=4.0))
    keys = jax.random.split(jax.random.key(3), B)
    z = np.asarray(flowmaps.sample(tokens, queries, N, keys))
    x = np.asarray(scaled.sample(tokens, queries, N, keys))
    np.testing.assert_allclose(x, z / 4.0 + 0.5, atol=1e-5)
    np.testing.assert_allclose(scaled.log_prob(tokens, queries, x),
                               np.asarray(flowmaps.log_prob(tokens, queries, z)) + 4 * math.log(4),
                               rtol=1e-4, atol=1e-3)
    with pytest.raises(ValueError, match="box_scale"):
        dataclasses.replace(CFG, box_scale=0.0)
    with pytest.raises(ValueError, match="box_offset"):
        dataclasses.replace(CFG, box_offset=float("nan"))


def test_log_prob_is_the_change_of_variables_of_the_sampler(flowmaps, inputs):
    """log p(x1) of a sample x1 = T(x0) equals log N(x0) − log|det ∂T/∂x0|, with the Jacobian of the
    discrete sampler T taken by forward-mode autodiff (rows are independent, so 4 JVPs give every
    row's 4×4 Jacobian). The backward likelihood ODE (flow.log_prob with the model's velocity)
    and the forward sampler agree up to their discretisation error (O(h²); the median error is
    ~0.03 nats on the default 10-point grid for this random field, while a wrong sign or a
    missing divergence term would be off by ~|log det| ≈ 1). ``sample(return_log_prob=True)``
    gives the same samples and, from its one forward solve, densities as close."""
    tokens, queries = inputs
    steps = 10
    keys = jax.random.split(jax.random.key(8), B)
    x1 = flowmaps.sample(tokens, queries, N, keys, num_steps=steps)
    log_p = flowmaps.log_prob(tokens, queries, x1, num_steps=steps)
    x0 = jax.vmap(lambda k: jax.random.normal(k, (Q, N, 4)))(keys)  # the sampler's noise
    context = model.encode(flowmaps.params, CFG, tokens)
    velocity_fn = model.make_velocity_fn(flowmaps.params, CFG, context, queries)

    @jax.jit
    def sampler_jacobian(x0):
        def sampler(x):
            return flow.integrate(velocity_fn, x, steps)
        basis = jnp.broadcast_to(jnp.eye(4)[:, None, None, None, :], (4, *x0.shape))
        columns = jax.vmap(lambda e: jax.jvp(sampler, (x0,), (e,))[1])(basis)
        return sampler(x0), jnp.moveaxis(columns, 0, -1)  # (B, Q, N, 4 out, 4 in)

    mapped, jac = sampler_jacobian(x0)
    np.testing.assert_allclose(mapped, x1, atol=1e-5)
    log_det = jnp.linalg.slogdet(jac)[1]
    expected = -0.5 * jnp.sum(x0**2, -1) - 2.0 * math.log(2 * math.pi) - log_det
    error = np.abs(np.asarray(log_p - expected))
    assert np.median(error) < 0.05
    assert error.max() < 1.5
    assert np.mean(np.abs(log_det)) > 0.5  # the map is far from volume-preserving
    x_fwd, log_p_fwd = flowmaps.sample(tokens, queries, N, keys, num_steps=steps,
                                       return_log_prob=True)
    np.testing.assert_allclose(x_fwd, x1, atol=1e-5)
    assert log_p_fwd.shape == (B, Q, N)
    assert np.median(np.abs(np.asarray(log_p_fwd - expected))) < 0.05


def test_mlp_log_prob_is_its_gaussian_and_samples_follow_it(mlp, inputs):
    tokens, queries = inputs
    mean, log_var = mlp.gaussian(tokens, queries)
    x = jax.random.uniform(jax.random.key(7), (B, Q, 3, 4))
    std = jnp.exp(0.5 * log_var)[:, :, None]
    expected = jnp.sum(-0.5 * ((x - mean[:, :, None]) / std) ** 2 - jnp.log(std)
                       - 0.5 * math.log(2 * math.pi), -1)
    np.testing.assert_allclose(mlp.log_prob(tokens, queries, x), expected, rtol=1e-5, atol=1e-4)
    samples = mlp.sample(tokens, queries, 4000, jax.random.key(8))
    np.testing.assert_allclose(samples.mean(2), mean, atol=0.1 * float(std.max()))
    np.testing.assert_allclose(samples.std(2), std[:, :, 0], rtol=0.1)


# --------------------------------------------------------------------------- validation


def _replace(obj, **fields):
    return dataclasses.replace(obj, **fields)


BAD_INPUTS = {
    "tau_q equal to tau": (lambda t, q: (t, _replace(q, tau_q=np.broadcast_to(
        t.tau[:, None], q.tau_q.shape).copy())), "tau_q"),
    "tau_q beyond the horizon": (lambda t, q: (t, _replace(q, tau_q=q.tau_q + 30)), "tau_q"),
    "unknown query descriptor": (lambda t, q: (t, _replace(q, descriptor=q.descriptor + 9)),
                                 "descriptor"),
    "unknown token descriptor": (lambda t, q: (_replace(t, descriptor=t.descriptor + 9), q),
                                 "descriptor"),
    "token overflow": (lambda t, q: (SceneTokens(
        boxes=np.zeros((B, 25, 4), np.float32), descriptor=np.zeros((B, 25), np.int32),
        kind=np.zeros((B, 25), np.int32), mask=np.ones((B, 25), bool), tau=t.tau), q),
        "max_tokens"),
    "box outside the map": (lambda t, q: (_replace(t, boxes=t.boxes + 2.0), q), "boxes"),
    "queries for another batch": (lambda t, q: (t, jax.tree_util.tree_map(
        lambda a: a[:1], q)), "queries"),
    "queries without a Q axis": (lambda t, q: (t, jax.tree_util.tree_map(
        lambda a: a[:, 0], q)), "queries"),
}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_inputs_raise_value_errors_naming_the_argument(flowmaps, inputs, case):
    make_bad, pattern = BAD_INPUTS[case]
    tokens, queries = make_bad(*inputs)
    with pytest.raises(ValueError, match=pattern):
        flowmaps.sample(tokens, queries, 2, jax.random.key(0))


@pytest.mark.parametrize(("kwargs", "pattern"), [
    ({"num_samples": 0}, "num_samples"),
    ({"num_samples": 2.5}, "num_samples"),
    ({"method": "rk4"}, "method"),
    ({"num_steps": 1}, "num_steps"),
    ({"key": 3}, "key"),
    ({"key": jax.random.split(jax.random.key(0), 5)}, "key"),
])
def test_bad_sampling_arguments(flowmaps, inputs, kwargs, pattern):
    args = {"num_samples": 2, "key": jax.random.key(0), **kwargs}
    with pytest.raises(ValueError, match=pattern):
        flowmaps.sample(*inputs, **args)


def test_bad_log_prob_points(flowmaps, mlp, inputs):
    with pytest.raises(ValueError, match="x must have shape"):
        flowmaps.log_prob(*inputs, np.zeros((B, Q, 4)))
    with pytest.raises(ValueError, match="x contains NaN"):
        flowmaps.log_prob(*inputs, np.full((B, Q, 2, 4), np.nan))
    with pytest.raises(ValueError, match="gaussian"):
        flowmaps.gaussian(*inputs)
    with pytest.raises(ValueError, match="tokens must be a SceneTokens"):
        mlp.sample({"boxes": 0}, inputs[1], 2, jax.random.key(0))
    with pytest.raises(ValueError, match="model family"):
        Predictor.from_params({}, CFG, family_name="diffusion")


# --------------------------------------------------------------------------- loading


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """A FlowMaps and an MLP checkpoint written by the real checkpoint store (no training)."""
    from flowmaps_jax.store.checkpoint_store import CheckpointStore
    from flowmaps_jax.training import state as train_state
    from flowmaps_jax.training.config import get_preset

    root = tmp_path_factory.mktemp("ckpt")
    dirs = {}
    for kind in ("flowmaps", "mlp"):
        net = CFG if kind == "flowmaps" else dataclasses.replace(CFG, baseline_variance="learned")
        cfg = dataclasses.replace(get_preset("smoke"), model=net, family=kind)
        state = train_state.init_state(cfg, jax.random.key(1))
        state = state.replace(ema_params=perturb(state.ema_params, jax.random.key(2), 0.1),
                              step=jnp.asarray(7, jnp.int32))
        with CheckpointStore(root / kind, keep_last=1) as store:
            store.save(state, cfg.to_dict())
        dirs[kind] = (root / kind, state)
    return dirs


def test_load_restores_the_model_family_params_and_step(checkpoints, inputs):
    for kind in ("flowmaps", "mlp"):
        path, state = checkpoints[kind]
        predictor = load(path, which="best")  # no validation yet: falls back to the latest save
        assert predictor.family_name == kind
        assert predictor.step == 7
        same = jax.tree_util.tree_map(np.array_equal, predictor.params, state.ema_params)
        assert all(jax.tree_util.tree_leaves(same))
        raw = load(path, which="latest", use_ema=False)
        same = jax.tree_util.tree_map(np.array_equal, raw.params, state.params)
        assert all(jax.tree_util.tree_leaves(same))
        assert predictor.sample(*inputs, N, jax.random.key(0)).shape == (B, Q, N, 4)


def test_load_errors_are_value_errors(tmp_path, checkpoints):
    with pytest.raises(ValueError, match="does not exist"):
        load(tmp_path / "missing")
    with pytest.raises(ValueError, match="not a checkpoint directory"):
        load(tmp_path)
    with pytest.raises(ValueError, match="which"):
        load(checkpoints["flowmaps"][0], which="first")


def test_exported_weights_load_as_the_same_predictor(tmp_path, checkpoints, inputs):
    from flowmaps_jax.export import export_pretrained

    path, _ = checkpoints["flowmaps"]
    export_pretrained(path, "flowmaps", tmp_path)
    mlp_path, _ = checkpoints["mlp"]
    export_pretrained(mlp_path, "mlp-learned", tmp_path)
    for name, source in (("flowmaps", path), ("mlp-learned", mlp_path)):
        packaged, loaded = load_pretrained(name, tmp_path), load(source, which="latest")
        assert (packaged.family_name, packaged.model, packaged.step) == (loaded.family_name,
                                                                      loaded.model, 7)
        same = jax.tree_util.tree_map(np.array_equal, packaged.params, loaded.params)
        assert all(jax.tree_util.tree_leaves(same))
        key = jax.random.key(3)
        np.testing.assert_array_equal(packaged.sample(*inputs, N, key),
                                      loaded.sample(*inputs, N, key))


def test_export_records_which_checkpoint_and_why(tmp_path, checkpoints, capsys):
    """The .json says which checkpoint of the run it holds ("best" or "latest") and why; the
    CLI exports the best-by-validation step by default (the one evaluate and search load) and
    the last one with --which latest."""
    import json

    from flowmaps_jax import export
    from flowmaps_jax.store import pretrained
    from flowmaps_jax.store.checkpoint_store import CheckpointStore
    from flowmaps_jax.training.resume import load_config

    path, state = checkpoints["flowmaps"]
    run = tmp_path / "run"
    best_state = state.replace(ema_params=perturb(state.ema_params, jax.random.key(5), 0.1),
                               step=jnp.asarray(3, jnp.int32))
    cfg = load_config(path)
    with CheckpointStore(run, keep_last=2) as store:
        assert store.save_if_best(best_state, cfg.to_dict(), 1.5)
        store.save(state, cfg.to_dict())  # the last step, 7
    for which, step in (("latest", 7), ("best", 3)):
        out = tmp_path / which
        args = ["--checkpoint", str(run), "--name", "flowmaps", "--out", str(out)]
        assert export.main(args + ([] if which == "best" else ["--which", "latest"])) == 0
        meta = json.loads((out / "flowmaps.json").read_text())
        assert (meta["which"], meta["step"]) == (which, step)
        assert f"step {step}" in meta["why"]
        assert f"step {step} ({which}: " in capsys.readouterr().out
        assert pretrained.describe("flowmaps", out)["which"] == which
        loaded = load_pretrained("flowmaps", out)
        want = load(run, which=which)
        assert loaded.step == want.step == step
        same = jax.tree_util.tree_map(np.array_equal, loaded.params, want.params)
        assert all(jax.tree_util.tree_leaves(same))
    assert "best validation loss was at step 3" in json.loads(
        (tmp_path / "latest" / "flowmaps.json").read_text())["why"]
    # a given reason is stored as given; a run without a best step exports its last, and says so
    export.export_pretrained(run, "flowmaps", tmp_path / "why", why="the docs use it",
                             which="latest")
    assert pretrained.describe("flowmaps", tmp_path / "why")["why"] == "the docs use it"
    export.export_pretrained(path, "flowmaps", tmp_path / "nobest", which="best")
    info = pretrained.describe("flowmaps", tmp_path / "nobest")
    assert info["which"] == "latest" and "no best" in info["why"]
    with pytest.raises(ValueError, match="which"):
        export.export_pretrained(run, "flowmaps", tmp_path / "bad", which="first")


def test_pretrained_json_without_which_still_loads(tmp_path):
    """The pretrained .json files predate "which": they load, and describe() says "unknown"; a
    .json with another value is refused."""
    import json
    import shutil

    from flowmaps_jax.store import pretrained

    for name in pretrained.available():
        meta = json.loads((pretrained.PRETRAINED_DIR / f"{name}.json").read_text())
        info = pretrained.describe(name)
        assert info["which"] == meta.get("which", "unknown") and info["step"] == meta["step"]
    for name in ("mlp",):
        shutil.copy(pretrained.PRETRAINED_DIR / f"{name}.npz", tmp_path)
        meta = json.loads((pretrained.PRETRAINED_DIR / f"{name}.json").read_text())
        meta.pop("which", None)  # as written before "which" existed (then sealed)
        meta["seal"] = pretrained.seal(meta, (tmp_path / f"{name}.npz").read_bytes())
        (tmp_path / f"{name}.json").write_text(json.dumps(meta))
        assert pretrained.describe(name, tmp_path)["which"] == "unknown"
        assert load_pretrained(name, tmp_path).step == meta["step"]
        (tmp_path / f"{name}.json").write_text(json.dumps({**meta, "which": "first"}))
        with pytest.raises(ValueError, match=r"which must be one of .*got 'first'"):
            load_pretrained(name, tmp_path)
        with pytest.raises(ValueError, match=r"which must be one of .*got 'first'"):
            pretrained.describe(name, tmp_path)


def test_pretrained_errors_are_value_errors(tmp_path, checkpoints):
    from flowmaps_jax.export import export_pretrained

    with pytest.raises(ValueError, match=r"flowmaps.*mlp.*mlp-learned"):
        load_pretrained("flowmap")
    with pytest.raises(ValueError, match="not in"):
        load_pretrained("mlp", tmp_path)
    with pytest.raises(ValueError, match="needs a 'mlp' model"):
        export_pretrained(checkpoints["flowmaps"][0], "mlp", tmp_path)
    with pytest.raises(ValueError, match="baseline_variance"):
        export_pretrained(checkpoints["mlp"][0], "mlp", tmp_path)  # the fixture's MLP is learned
    npz = export_pretrained(checkpoints["flowmaps"][0], "flowmaps", tmp_path)
    data = bytearray(npz.read_bytes())
    data[len(data) // 2] ^= 0xFF
    npz.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="damaged"):
        load_pretrained("flowmaps", tmp_path)
