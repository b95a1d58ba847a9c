"""FlowMaps on FlowSim homes (issue 35, part 2): tokens, history features, the mixture read-out
over receptacles, the placement flow, training, the predictor and the packaged weights.

Tiny sizes: the ``homes-smoke`` preset (4-day homes, a 16-wide model), one set of 8 homes."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from support import perturb, run_python_in_process

from flowmaps_jax.flowsim.homes import context_of, generate_homes, object_boxes
from flowmaps_jax.flowsim.homes import tokens as homes_tokens
from flowmaps_jax.flowsim.homes.queries import HomesQueries
from flowmaps_jax.model import homes_family as homes_model
from flowmaps_jax.predictor import Predictor, load, load_model, load_pretrained
from flowmaps_jax.store import model_spec, pretrained
from flowmaps_jax.training import state as train_state
from flowmaps_jax.training.config import HomesTrainConfig, get_preset
from flowmaps_jax.worlds import homes as homes_world

CFG = get_preset("homes-smoke")
CONFIG, MODEL = CFG.homes, CFG.model
H = MODEL.history


@pytest.fixture(scope="module")
def homes():
    return generate_homes(jax.random.key(3), CONFIG, CFG.chunk_homes)


@pytest.fixture(scope="module")
def queries(homes):
    e = homes.num_homes
    obj = np.argmax(np.asarray(homes.object_valid), axis=1)[:, None].repeat(3, 1)
    valid = np.asarray(homes.object_valid)
    obj[:, 1] = valid.shape[1] - 1 - np.argmax(valid[:, ::-1], axis=1)  # the last valid object
    tau = np.array([[H - 1, 40, 50]] * e, np.int32)
    tau_q = tau + np.array([1, 6, 24], np.int32)
    return HomesQueries(object_index=jnp.asarray(obj, jnp.int32), tau=jnp.asarray(tau),
                        tau_q=jnp.asarray(tau_q))


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A homes-smoke run trained through the train CLI."""
    path = tmp_path_factory.mktemp("homes") / "run"
    code, out = run_python_in_process(
        ["-m", "flowmaps_jax.train", "--preset", "homes-smoke", "--run-dir", str(path),
         "--no-progress"], path.parent)
    assert code == 0, out
    return path


# --------------------------------------------------------------------------- tokens


def test_tokens_have_the_layout_masks_and_normalised_boxes(homes):
    tau = np.arange(homes.num_homes, dtype=np.int32) * 5
    tok = homes_tokens.home_tokens(homes, tau, CONFIG)
    nr, r, m, s = CONFIG.num_rooms, CONFIG.max_receptacles, CONFIG.max_objects, CONFIG.max_tokens
    assert tok.boxes.shape == (homes.num_homes, s, 6) and tok.mask.shape == (homes.num_homes, s)
    mask = np.asarray(tok.mask)
    assert mask[:, :nr].all() and not mask[:, nr + r + m:].any()
    np.testing.assert_array_equal(mask[:, nr:nr + r], homes.receptacle_valid)
    np.testing.assert_array_equal(mask[:, nr + r:nr + r + m], homes.object_valid)
    np.testing.assert_array_equal(np.asarray(tok.kind)[:, :nr + r + m],
                                  np.repeat([0, 1, 2], [nr, r, m])[None].repeat(len(tau), 0))
    _, rec_off, obj_off = CONFIG.descriptor_offsets
    desc = np.asarray(tok.descriptor)
    np.testing.assert_array_equal(desc[:, :nr], homes.room_type)
    valid = np.asarray(homes.object_valid)
    np.testing.assert_array_equal(desc[:, nr + r:nr + r + m][valid],
                                  np.asarray(homes.object_class)[valid] + obj_off)
    assert desc[:, nr:nr + r][np.asarray(homes.receptacle_valid)].min() >= rec_off
    size = np.asarray(homes.home_size)
    scale = np.concatenate([size, np.full((len(tau), 1), homes_tokens.HEIGHT_SCALE)], 1)
    scale = np.concatenate([scale, scale], 1)[:, None]  # (E, 1, 6)
    boxes = np.asarray(tok.boxes)
    np.testing.assert_allclose(boxes[:, nr:nr + r] * scale, homes.receptacle_box, atol=1e-5)
    objects = np.stack([np.asarray(object_boxes(homes, int(t), CONFIG))[i]
                        for i, t in enumerate(tau)])
    np.testing.assert_allclose(boxes[:, nr + r:nr + r + m] * scale, objects, atol=1e-5)
    inside = boxes[mask][:, :2]
    assert inside.min() >= 0 and inside.max() <= 1  # centres within the footprint
    # (E, K) hours give (E, K, S) tokens, one scene per hour
    both = homes_tokens.home_tokens(homes, np.stack([tau, tau + 1], 1), CONFIG)
    np.testing.assert_array_equal(both.boxes[:, 0], tok.boxes)


def test_token_budget_and_tau_are_checked(homes):
    with pytest.raises(ValueError, match="max_tokens"):
        dataclasses.replace(CONFIG, max_tokens=10)
    tight = dataclasses.replace(CONFIG)
    object.__setattr__(tight, "max_tokens", 10)  # a config that skipped its own checks
    with pytest.raises(ValueError, match=r"config.max_tokens=10"):
        homes_tokens.home_tokens(homes, np.zeros(homes.num_homes, np.int32), tight)
    with pytest.raises(ValueError, match="tau"):
        homes_tokens.home_tokens(homes, np.zeros(homes.num_homes + 1, np.int32), CONFIG)
    with pytest.raises(ValueError, match="tau"):
        homes_tokens.home_tokens(homes, np.full(homes.num_homes, 10**6, np.int32), CONFIG)


# --------------------------------------------------------------------------- history features


def _hand_features(homes, e, obj, tau, tau_q, history):
    """The features of one query, computed with loops over the window's hours."""
    traj = np.asarray(homes.receptacle)[e, :, obj]
    allowed = np.asarray(homes.object_allowed)[e, obj]
    cycle = [int(c) for c in np.asarray(homes.cycle)[e, obj] if c >= 0]
    n, cur = len(cycle), traj[tau]
    hours = [t for t in range(tau - history + 1, tau + 1) if t >= 0]
    same = [t for t in hours if context_of(t) == context_of(tau_q)]
    moves = [(t, traj[t + 1]) for t in hours[:-1] if traj[t + 1] != traj[t]]
    steps = [(cycle.index(traj[t + 1]) - cycle.index(traj[t])) % n for t in hours[:-1]]
    out = np.zeros((allowed.size, len(homes_tokens.HISTORY_FEATURES)))
    dist = np.asarray(homes.receptacle_distance)[e, cur]
    for r in range(allowed.size):
        f = dict.fromkeys(homes_tokens.HISTORY_FEATURES, 0.0)
        f["allowed"] = float(allowed[r])
        if allowed[r]:
            k = (cycle.index(r) - cycle.index(cur)) % n
            ctx_moves = [1 for t, s in moves if context_of(t) == context_of(tau_q)]
            f.update(
                occupancy=sum(traj[t] == r for t in hours) / len(hours),
                context_occupancy=sum(traj[t] == r for t in same) / max(len(same), 1),
                at_tau=float(cur == r), distance=dist[r] / homes_tokens.DISTANCE_SCALE,
                near=np.exp(-dist[r] / CONFIG.frequent_length), cycle_0=k == 0, cycle_1=k == 1,
                cycle_2=k == 2, cycle_back=k == n - 1, cycle_fraction=k / n,
                arrivals=sum(s == r for _, s in moves) / max(len(moves), 1),
                context_arrivals=sum(s == r for t, s in moves if context_of(t)
                                     == context_of(tau_q)) / max(len(ctx_moves), 1),
                inverse_allowed=1 / n, move_rate=len(moves) / (len(hours) - 1),
                step_1_rate=steps.count(1) / (len(hours) - 1),
                step_2_rate=steps.count(2) / (len(hours) - 1), coverage=len(hours) / history)
            for name, hour in (("context", tau_q), ("earlier", tau_q - 6), ("next", tau + 1)):
                ctx = [t for t in hours if context_of(t) == context_of(hour)]
                f[f"{name}_arrival_count"] = np.log1p(
                    sum(s == r for t, s in moves if context_of(t) == context_of(hour))
                ) / homes_tokens.COUNT_SCALE
                f[f"{name}_hour_count"] = np.log1p(
                    sum(traj[t] == r for t in ctx)) / homes_tokens.COUNT_SCALE
            days = [t for t in hours if t % 24 == tau_q % 24]
            f["same_hour_occupancy"] = sum(traj[t] == r for t in days) / max(len(days), 1)
        out[r] = [float(f[name]) for name in homes_tokens.HISTORY_FEATURES]
    return out


def test_history_features_match_a_hand_computation(homes, queries):
    got = np.asarray(homes_tokens.history_features(homes, queries, CONFIG, H))
    assert got.shape == (homes.num_homes, 3, CONFIG.max_receptacles,
                         len(homes_tokens.HISTORY_FEATURES))
    for e in range(3):
        for j in range(3):
            args = (int(queries.object_index[e, j]), int(queries.tau[e, j]),
                    int(queries.tau_q[e, j]))
            np.testing.assert_allclose(got[e, j], _hand_features(homes, e, *args, H), atol=1e-6,
                                       err_msg=f"home {e} query {j}")
    # a window reaching before hour 0 counts only the hours inside the rollout
    early = queries.replace(tau=jnp.full_like(queries.tau, 2), tau_q=jnp.full_like(queries.tau, 5))
    got = np.asarray(homes_tokens.history_features(homes, early, CONFIG, H))
    np.testing.assert_allclose(got[0, 0], _hand_features(homes, 0, int(early.object_index[0, 0]),
                                                         2, 5, H), atol=1e-6)


def test_queries_are_checked(homes, queries):
    with pytest.raises(ValueError, match=r"queries.tau"):
        homes_tokens.history_features(homes, queries.replace(tau=queries.tau[:, :2]), CONFIG,
                                      H)
    with pytest.raises(ValueError, match="tau_q"):
        homes_tokens.history_features(homes, queries.replace(tau_q=queries.tau), CONFIG, H)
    with pytest.raises(ValueError, match="history"):
        homes_tokens.history_features(homes, queries, CONFIG, 0)


# --------------------------------------------------------------------------- the model


@pytest.fixture(scope="module")
def params():
    return homes_model.init_params(jax.random.key(0), MODEL, CONFIG)


@pytest.fixture(scope="module")
def batch(homes, queries):
    return homes_tokens.per_query_batch(homes, queries, CONFIG, H)


def test_weights_are_a_distribution_over_the_allowed_receptacles_only(params, batch):
    p0 = np.asarray(homes_model.receptacle_probabilities(params, MODEL, CONFIG, batch))
    allowed = np.asarray(batch.allowed)
    # AdaLN-Zero's zero final projection: uniform over the allowed receptacles at init
    np.testing.assert_allclose(p0, allowed / allowed.sum(-1, keepdims=True), atol=1e-6)
    p = np.asarray(homes_model.receptacle_probabilities(perturb(params, jax.random.key(1)),
                                                        MODEL, CONFIG, batch))
    np.testing.assert_allclose(p.sum(-1), 1.0, atol=1e-5)
    assert np.all(p[~allowed] == 0) and np.all(p[allowed] > 0)
    assert np.abs(p - p0).max() > 1e-3  # the perturbed model is not uniform


def test_rows_without_the_angle_read_offsets_and_distance_only(params, batch):
    """``geometry_angle=False`` (issue 47: nothing that needs a home's centre): the rows' geometry
    loses the angle's four features and gains the distance, and the model still answers a
    distribution; stored models (no such key) keep the angle."""
    flat = dataclasses.replace(MODEL, geometry_angle=False)
    agnostic = homes_model.init_params(jax.random.key(0), flat, CONFIG)
    width = lambda p: p["row_mlp"]["in"]["kernel"].shape[0]  # noqa: E731
    assert width(params) - width(agnostic) == 3
    p = np.asarray(homes_model.receptacle_probabilities(perturb(agnostic, jax.random.key(1)),
                                                        flat, CONFIG, batch))
    np.testing.assert_allclose(p.sum(-1), 1.0, atol=1e-5)
    stored = {k: v for k, v in flat.to_dict().items() if k != "geometry_angle"}
    assert homes_model.HomesModelConfig.from_dict(stored).geometry_angle


def test_placement_velocity_is_zero_at_init(params, batch):
    context, c = homes_model._encode_and_condition(params, MODEL, CONFIG, batch)
    b, q = batch.current.shape
    z = jax.random.normal(jax.random.key(2), (b, q, 3, 6))
    t = jax.random.uniform(jax.random.key(3), (b, q))
    table = jnp.broadcast_to(batch.current[..., None], (b, q, 3))
    v = homes_model.placement_velocity(params, MODEL, CONFIG, context, c, z, t, table)
    assert v.shape == (b, q, 3, 6) and np.all(np.asarray(v) == 0.0)
    noisy = perturb(params, jax.random.key(1))
    context, c = homes_model._encode_and_condition(noisy, MODEL, CONFIG, batch)
    v = homes_model.placement_velocity(noisy, MODEL, CONFIG, context, c, z, t, table)
    assert np.abs(np.asarray(v)).max() > 1e-3


def test_samples_stand_on_a_receptacle_drawn_from_the_weights(params, batch):
    table, boxes = homes_model.sample_placements(params, MODEL, CONFIG, batch,
                                                 jax.random.key(4), 8)
    assert table.shape == (*batch.current.shape, 8) and boxes.shape == (*table.shape, 6)
    assert np.all(np.take_along_axis(np.asarray(batch.allowed), np.asarray(table), -1))
    mean, scale = homes_model.placement_frame(batch.tokens.boxes, batch.object_token, CONFIG)
    mean = np.take_along_axis(np.asarray(mean), np.asarray(table)[..., None], 2)
    scale = np.take_along_axis(np.asarray(scale), np.asarray(table)[..., None], 2)
    z = (np.asarray(boxes) - mean) / scale  # zero velocity at init: the noise itself
    assert np.all(np.abs(z) < 6)


def test_a_few_dozen_steps_lower_the_loss(homes):
    """The loss, its gradients and the run's optimiser on one fixed batch (the train step on
    fresh homes runs in the training CLI's test below)."""
    cfg = dataclasses.replace(CFG, steps=40, lr=3e-3, warmup_steps=2)
    state = train_state.init_state(cfg)
    batch = jax.jit(lambda key: homes_world.draw_batch(key, homes, cfg))(jax.random.key(0))
    tx = train_state.make_optimizer(cfg)

    @jax.jit
    def step(params, opt_state):
        grads, aux = jax.grad(lambda p: homes_model.homes_loss(
            p, MODEL, CONFIG, batch, jax.random.key(1)), has_aux=True)(params)
        updates, opt_state = tx.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, aux

    params, opt_state = state.params, tx.init(state.params)
    _, _, before = step(params, opt_state)
    for _ in range(cfg.steps):
        params, opt_state, aux = step(params, opt_state)
    assert float(aux["ce"]) < 0.5 * float(before["ce"]), (before, aux)
    assert float(aux["cfm"]) < float(before["cfm"]), (before, aux)


# --------------------------------------------------------------------------- training, loading


def test_the_train_cli_trains_the_smoke_preset_and_the_predictor_loads_its_best(run_dir, homes,
                                                                                queries):
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    vals = [r for r in records if r["kind"] == "val"]
    assert [r["step"] for r in vals] == [0, 3, 6] and any(r["kind"] == "train" for r in records)
    config = json.loads((run_dir / "config.json").read_text())
    assert config["model_kind"] == homes_model.FAMILY_NAME
    assert HomesTrainConfig.from_dict(config) == CFG
    predictor = load(run_dir)  # the one Predictor, for every world's models
    assert isinstance(predictor, Predictor) and predictor.family_name == "flowmaps-homes"
    best = min(vals, key=lambda r: r["val_loss"])["step"]
    assert predictor.step == best  # the default load is the best validation CE
    assert load(run_dir / "checkpoints", which="latest").step == 6
    p = np.asarray(predictor.probabilities(homes, queries, CONFIG))
    assert p.shape == (homes.num_homes, 3, CONFIG.max_receptacles)
    np.testing.assert_allclose(p.sum(-1), 1.0, atol=1e-5)
    assert np.all(p[~np.asarray(jax.vmap(lambda a, o: a[o])(homes.object_allowed,
                                                            queries.object_index))] == 0)
    boxes, table = predictor.sample(jax.random.key(0), homes, queries, CONFIG, 4,
                                    return_receptacles=True)
    assert boxes.shape == (homes.num_homes, 3, 4, 6) and table.shape == (homes.num_homes, 3, 4)
    rec = np.take_along_axis(np.asarray(homes.receptacle_box)[:, None],
                             np.asarray(table)[..., None], axis=2)  # (E, Q, N, 6)
    assert np.all(np.abs(np.asarray(boxes)[..., :2] - rec[..., :2]) < rec[..., 3:5] * 1.6)
    assert load_model(str(run_dir)).step == best  # what the CLIs load
    for call in (lambda: predictor.table_weights(None, None),
                 lambda: predictor.log_prob(None, None, None)):
        with pytest.raises(ValueError, match="2-D FlowSim scene tokens"):
            call()  # a 2-D method names the homes methods


def _untimed(path) -> list[dict]:
    """A run's metrics.jsonl records without their timings (steps/s, samples/s)."""
    return [{k: v for k, v in json.loads(line).items() if not k.endswith("_per_sec")}
            for line in path.read_text().splitlines()]


def test_a_homes_run_stopped_and_resumed_writes_the_records_of_one_never_stopped(run_dir,
                                                                                tmp_path):
    """The homes world enters the one training loop: --stop-at, then --resume, continue the
    run exactly (the same data chunks, batches, noise and records as the uninterrupted run)."""
    split = tmp_path / "split"
    args = ["-m", "flowmaps_jax.train", "--run-dir", str(split), "--no-progress"]
    code, out = run_python_in_process([*args, "--preset", "homes-smoke", "--stop-at", "4"],
                                      tmp_path)
    assert code == 0, out
    assert [(r["kind"], r["step"]) for r in _untimed(split / "metrics.jsonl")] == [
        ("val", 0), ("train", 2), ("val", 3), ("train", 4)]
    code, out = run_python_in_process([*args, "--resume"], tmp_path)
    assert code == 0 and "Resumed from" in out, out
    assert _untimed(split / "metrics.jsonl") == _untimed(run_dir / "metrics.jsonl")
    code, out = run_python_in_process([*args, "--resume", "--set", "homes.num_hours=120"],
                                      tmp_path)
    assert code == 2 and "cannot change homes.num_hours" in out, out


def test_export_and_load_by_name_round_trip_with_integrity_checks(run_dir, homes, queries,
                                                                  tmp_path):
    out = tmp_path / "weights"
    code, text = run_python_in_process(
        ["-m", "flowmaps_jax.export", "--checkpoint", str(run_dir / "checkpoints"), "--name",
         "flowmaps-homes", "--out", str(out)], tmp_path)
    assert code == 0, text
    loaded = load_pretrained("flowmaps-homes", out)
    trained = load(run_dir)
    assert loaded.source == "pretrained:flowmaps-homes" and loaded.step == trained.step
    np.testing.assert_array_equal(loaded.probabilities(homes, queries, CONFIG),
                                  trained.probabilities(homes, queries, CONFIG))
    npz = out / "flowmaps-homes.npz"
    data = bytearray(npz.read_bytes())
    data[len(data) // 2] ^= 0xFF
    npz.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"flowmaps-homes.*damaged"):
        load_pretrained("flowmaps-homes", out)


def test_loading_refuses_missing_sources(tmp_path):
    with pytest.raises(ValueError, match=r"does not exist"):
        load(tmp_path / "nothing")
    with pytest.raises(ValueError, match=r"not a checkpoint directory"):
        load(tmp_path)
    with pytest.raises(ValueError, match="which"):
        load(tmp_path, which="first")
    with pytest.raises(ValueError, match="take homes"):  # a 2-D model has no receptacles
        load_pretrained("mlp").probabilities(None, None)


def test_the_predictor_checks_its_inputs(run_dir, homes, queries):
    predictor = load(run_dir)
    with pytest.raises(ValueError, match=r"queries.tau_q"):
        predictor.probabilities(homes, queries.replace(tau_q=queries.tau), CONFIG)
    with pytest.raises(ValueError, match=r"queries.object_index"):
        predictor.probabilities(homes, queries.replace(object_index=queries.object_index[:1]),
                                CONFIG)
    other = dataclasses.replace(CONFIG, max_tokens=CONFIG.max_tokens + 1)
    with pytest.raises(ValueError, match=r"config.max_tokens"):
        predictor.probabilities(homes, queries, other)
    with pytest.raises(ValueError, match="num_samples"):
        predictor.sample(jax.random.key(0), homes, queries, CONFIG, 0)
    with pytest.raises(ValueError, match="num_steps"):  # bounded work, refused up front
        predictor.sample(jax.random.key(0), homes, queries, CONFIG, 2, num_steps=10 ** 7)
    with pytest.raises(ValueError, match="return_receptacles"):
        predictor.sample(jax.random.key(0), homes, queries, CONFIG, 2, return_receptacles=1)


def test_the_store_reads_both_families():
    assert model_spec.HOMES_FAMILY == homes_model.FAMILY_NAME
    assert "flowmaps-homes" in pretrained.NAMES
    spec = model_spec.model_spec(CFG.to_dict())
    assert spec.family_name == homes_model.FAMILY_NAME
    assert spec.model == MODEL and spec.homes == CONFIG
    assert model_spec.model_spec({"model_kind": "flowmaps"}).family_name == "flowmaps"
    with pytest.raises(ValueError, match="'homes' section"):
        model_spec.model_spec({"model_kind": "flowmaps-homes", "model": {}})


def test_the_train_config_round_trips_and_refuses_bad_fields():
    assert HomesTrainConfig.from_dict(CFG.to_dict()) == CFG
    assert HomesTrainConfig.from_dict(
        json.loads(json.dumps(get_preset("homes").to_dict()))) == get_preset("homes")
    with pytest.raises(ValueError, match="max_horizon"):
        dataclasses.replace(CFG, max_horizon=200)
    with pytest.raises(ValueError, match="colour"):
        HomesTrainConfig.from_dict({**CFG.to_dict(), "colour": 1})
    from flowmaps_jax.training.overrides import apply_overrides

    assert apply_overrides(CFG, ["model.dim=8"]).model.dim == 8
    with pytest.raises(ValueError, match=r"unknown config key 'model\.width'"):
        apply_overrides(CFG, ["model.width=8"])


def test_large_requests_run_in_chunks_of_queries_with_the_same_answers(run_dir, homes, queries,
                                                                       monkeypatch):
    from flowmaps_jax.model import homes_inference as homes_predictor

    predictor = load(run_dir)
    whole = np.asarray(predictor.probabilities(homes, queries, CONFIG))
    monkeypatch.setattr(homes_predictor, "ROWS_PER_CALL",
                        homes.num_homes * CONFIG.max_receptacles * 2)  # 2 of the 3 queries
    np.testing.assert_array_equal(predictor.probabilities(homes, queries, CONFIG), whole)
    boxes = predictor.sample(jax.random.key(0), homes, queries, CONFIG, 2)
    assert boxes.shape == (homes.num_homes, 3, 2, 6) and np.all(np.isfinite(boxes))
