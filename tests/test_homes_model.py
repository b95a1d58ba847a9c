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

from flowmaps_jax.flowsim.homes import generate_homes, object_boxes
from flowmaps_jax.flowsim.homes.queries import HomesQueries
from flowmaps_jax.model import homes_family as homes_model
from flowmaps_jax.model import homes_inputs
from flowmaps_jax.model.homes_inference import home_tokens
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
def run_dir(homes_runs):
    """A homes-smoke run trained through the train CLI (the session's, tests/conftest.py)."""
    return homes_runs.straight


# --------------------------------------------------------------------------- tokens


def test_tokens_have_the_layout_masks_and_normalised_boxes(homes):
    tau = np.arange(homes.num_homes, dtype=np.int32) * 5
    tok = home_tokens(homes, tau, CONFIG)
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
    scale = np.concatenate([size, np.full((len(tau), 1), homes_inputs.HEIGHT_SCALE)], 1)
    scale = np.concatenate([scale, scale], 1)[:, None]  # (E, 1, 6)
    boxes = np.asarray(tok.boxes)
    np.testing.assert_allclose(boxes[:, nr:nr + r] * scale, homes.receptacle_box, atol=1e-5)
    at_hour = jax.jit(object_boxes, static_argnums=2)  # one program for every hour
    objects = np.stack([np.asarray(at_hour(homes, np.int32(t), CONFIG))[i]
                        for i, t in enumerate(tau)])
    np.testing.assert_allclose(boxes[:, nr + r:nr + r + m] * scale, objects, atol=1e-5)
    inside = boxes[mask][:, :2]
    assert inside.min() >= 0 and inside.max() <= 1  # centres within the footprint
    # (E, K) hours give (E, K, S) tokens, one scene per hour
    both = home_tokens(homes, np.stack([tau, tau + 1], 1), CONFIG)
    np.testing.assert_array_equal(both.boxes[:, 0], tok.boxes)


def test_token_budget_and_tau_are_checked(homes):
    with pytest.raises(ValueError, match="max_tokens"):
        dataclasses.replace(CONFIG, max_tokens=10)
    tight = dataclasses.replace(CONFIG)
    object.__setattr__(tight, "max_tokens", 10)  # a config that skipped its own checks
    with pytest.raises(ValueError, match=r"config.max_tokens=10"):
        home_tokens(homes, np.zeros(homes.num_homes, np.int32), tight)
    with pytest.raises(ValueError, match="tau"):
        home_tokens(homes, np.zeros(homes.num_homes + 1, np.int32), CONFIG)
    with pytest.raises(ValueError, match="tau"):
        home_tokens(homes, np.full(homes.num_homes, 10**6, np.int32), CONFIG)


# --------------------------------------------------------------------------- history inputs


def _hand_rows(homes, e, obj, tau, tau_q, history):
    """The events and row features of one query, with loops over the window's hours."""
    traj = np.asarray(homes.receptacle)[e, :, obj]
    allowed = np.asarray(homes.object_allowed)[e, obj]
    r_all = allowed.size
    hours = list(range(tau - history + 1, tau + 1))
    events = [int(traj[t]) if t >= 0 else -1 for t in hours]
    seen = [t for t in hours if t >= 0]
    counts = np.zeros((r_all, r_all))
    for t in seen[:-1]:
        counts[traj[t], traj[t + 1]] += 1
    counts += homes_inputs.STAY_PRIOR * np.diag(allowed)
    counts *= np.outer(allowed, allowed)
    chain = counts / np.maximum(counts.sum(1, keepdims=True), 1e-9)
    cur = traj[tau]
    pushed = np.linalg.matrix_power(chain, tau_q - tau)[cur]
    moves = sum(traj[t + 1] != traj[t] for t in seen[:-1])
    dist = np.asarray(homes.receptacle_distance)[e, cur]
    out = np.zeros((r_all, len(homes_inputs.ROW_FEATURES)))
    for r in range(r_all):
        f = dict.fromkeys(homes_inputs.ROW_FEATURES, 0.0)
        f["allowed"] = float(allowed[r])
        if allowed[r]:
            f.update(last_seen=float(cur == r), distance=dist[r] / homes_inputs.DISTANCE_SCALE,
                     occupancy=sum(traj[t] == r for t in seen) / len(seen),
                     one_step=chain[cur, r], pushed=pushed[r],
                     pushed_log=np.log(pushed[r] + 1e-3) / -np.log(1e-3),
                     inverse_allowed=1 / allowed.sum(), coverage=len(seen) / history,
                     moves=moves / max(len(seen) - 1, 1))
        out[r] = [float(f[name]) for name in homes_inputs.ROW_FEATURES]
    return np.asarray(events), out


@jax.jit
def _events_and_rows(homes, queries, observed=None):
    """``history_events`` and ``row_features`` as numpy, in one compiled program."""
    events = homes_inputs.history_events(homes, queries, H, observed)
    return events, homes_inputs.row_features(homes, queries, CONFIG, events, observed)


def test_history_inputs_match_a_hand_computation(homes, queries):
    events, rows = (np.asarray(a) for a in _events_and_rows(homes, queries))
    assert rows.shape == (homes.num_homes, 3, CONFIG.max_receptacles,
                          len(homes_inputs.ROW_FEATURES))
    early = queries.replace(tau=np.full(queries.tau.shape, 2, np.int32),
                            tau_q=np.full(queries.tau.shape, 5, np.int32))
    early_events, early_rows = (np.asarray(a) for a in _events_and_rows(homes, early))
    for qs, ev, got in ((queries, events, rows), (early, early_events, early_rows)):
        for e in range(3):
            for j in range(3):
                want_ev, want = _hand_rows(homes, e, int(qs.object_index[e, j]),
                                           int(qs.tau[e, j]), int(qs.tau_q[e, j]), H)
                np.testing.assert_array_equal(ev[e, j], want_ev)
                np.testing.assert_allclose(got[e, j], want, atol=1e-5,
                                           err_msg=f"home {e} query {j}")


def test_unobserved_hours_are_events_of_nothing(homes, queries):
    observed = np.ones(homes.receptacle.shape, bool)
    observed[:, 30:41] = False  # hours 30 … 40 unseen: τ = 40 is unseen too
    events, rows = (np.asarray(a) for a in _events_and_rows(homes, queries, observed))
    hours = np.asarray(queries.tau)[..., None] - H + 1 + np.arange(H)
    assert (events[(hours >= 30) & (hours <= 40)] == -1).all()
    assert (events[(hours >= 0) & ((hours < 30) | (hours > 40))] >= 0).all()
    unseen = rows[..., homes_inputs.ROW_FEATURES.index("unseen_at_tau")].max(-1)
    np.testing.assert_array_equal(unseen[:, 1], 1.0)  # the query at τ = 40
    np.testing.assert_array_equal(unseen[:, 2], 0.0)  # τ = 50 was seen


def test_the_model_inputs_read_nothing_of_a_simulators_law():
    """Issue 54: the network's inputs are what any log has; the rhythms are learned."""
    import ast
    import inspect

    from flowmaps_jax.model import homes_inputs as inputs

    for module in (inputs, homes_model):
        tree = ast.parse(inspect.getsource(module))
        imported = [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
        imported += [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
        law = [m for m in imported if m.startswith("flowmaps_jax.flowsim")
               and m != "flowmaps_jax.flowsim.homes.config"]  # the stored spec's config class
        assert not law, (module.__name__, law)
        names = {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)}
        names |= {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
        told = names & {"context_of", "cycle", "frequent_length", "regime", "favourite",
                        "routine_probs", "preference_mass", "num_allowed", "NUM_CONTEXTS"}
        assert not told, (module.__name__, told)
    assert not [m for m in ast.walk(ast.parse(inspect.getsource(inputs)))
                if isinstance(m, ast.ImportFrom) and (m.module or "").startswith("flowmaps_jax")]


def test_queries_are_checked(homes, queries):
    from flowmaps_jax.model.homes_inference import check

    predictor = Predictor(params=homes_model.init_params(jax.random.key(0), MODEL, CONFIG),
                          model=MODEL, family_name=homes_model.FAMILY_NAME, homes=CONFIG)
    with pytest.raises(ValueError, match=r"queries.tau"):
        check(predictor, homes, queries.replace(tau=queries.tau[:, :2]), CONFIG)
    with pytest.raises(ValueError, match="tau_q"):
        check(predictor, homes, queries.replace(tau_q=queries.tau), CONFIG)
    with pytest.raises(ValueError, match="observed"):
        check(predictor, homes, queries, CONFIG, observed=np.ones((1, 2, 3), bool))


def test_a_model_trained_on_partial_logs_refuses_a_query_without_the_mask(homes, queries):
    model = dataclasses.replace(MODEL, history_observed=True)
    predictor = Predictor(params=homes_model.init_params(jax.random.key(0), model, CONFIG),
                          model=model, family_name=homes_model.FAMILY_NAME, homes=CONFIG)
    with pytest.raises(ValueError, match="observed is required"):
        predictor.probabilities(homes, queries, CONFIG)
    observed = np.ones(homes.receptacle.shape, bool)
    p = np.asarray(predictor.probabilities(homes, queries, CONFIG, observed=observed))
    np.testing.assert_allclose(p.sum(-1), 1.0, atol=1e-5)


def test_models_with_the_told_features_are_refused_with_a_clear_line():
    old = {**MODEL.to_dict(), "history_counts": True}
    with pytest.raises(ValueError, match="generator-told history features"):
        homes_model.HomesModelConfig.from_dict(old)


# --------------------------------------------------------------------------- the model


@pytest.fixture(scope="module")
def params():
    return homes_model.init_params(jax.random.key(0), MODEL, CONFIG)


@pytest.fixture(scope="module")
def batch(homes, queries):
    return jax.jit(homes_inputs.per_query_batch, static_argnums=(2, 3))(homes, queries, CONFIG, H)


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
    """``geometry_angle=False`` (the default: nothing that needs a home's centre): the rows'
    geometry has no angle's four features but the distance; ``True`` adds the angle, and both
    answer a distribution."""
    angled = dataclasses.replace(MODEL, geometry_angle=True)
    with_angle = homes_model.init_params(jax.random.key(0), angled, CONFIG)
    width = lambda p: p["row_mlp"]["in"]["kernel"].shape[0]  # noqa: E731
    assert not MODEL.geometry_angle and width(with_angle) - width(params) == 3
    p = np.asarray(homes_model.receptacle_probabilities(perturb(with_angle, jax.random.key(1)),
                                                        angled, CONFIG, batch))
    np.testing.assert_allclose(p.sum(-1), 1.0, atol=1e-5)


def test_placement_velocity_is_zero_at_init(params, batch):
    @jax.jit  # one program for both parameter sets
    def velocity(p, batch):
        context, c = homes_model._encode_and_condition(p, MODEL, CONFIG, batch)
        b, q = batch.current.shape
        z = jax.random.normal(jax.random.key(2), (b, q, 3, 6))
        t = jax.random.uniform(jax.random.key(3), (b, q))
        table = jnp.broadcast_to(batch.current[..., None], (b, q, 3))
        return homes_model.placement_velocity(p, MODEL, CONFIG, context, c, z, t, table)

    v = np.asarray(velocity(params, batch))
    assert v.shape == (*batch.current.shape, 3, 6) and np.all(v == 0.0)
    assert np.abs(np.asarray(velocity(perturb(params, jax.random.key(1)), batch))).max() > 1e-3


def test_samples_stand_on_a_receptacle_drawn_from_the_weights(params, batch):
    table, boxes = homes_model.sample_placements(params, MODEL, CONFIG, batch,
                                                 jax.random.key(4), 8)
    assert table.shape == (*batch.current.shape, 8) and boxes.shape == (*table.shape, 6)
    assert np.all(np.take_along_axis(np.asarray(batch.allowed), np.asarray(table), -1))
    mean, scale = jax.jit(homes_model.placement_frame, static_argnums=2)(
        batch.tokens.boxes, batch.object_token, CONFIG)
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

    # committed to the device as step's outputs are: one compiled step, not a second for them
    params, opt_state = jax.device_put((state.params, state.opt_state), jax.devices()[0])
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
    boxes, table = predictor.sample(homes, queries, 4, jax.random.key(0), config=CONFIG,
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
        predictor.sample(homes, queries, 0, jax.random.key(0), config=CONFIG)
    with pytest.raises(ValueError, match="num_steps"):  # bounded work, refused up front
        predictor.sample(homes, queries, 2, jax.random.key(0), num_steps=10 ** 7, config=CONFIG)
    with pytest.raises(ValueError, match="return_receptacles"):
        predictor.sample(homes, queries, 2, jax.random.key(0), config=CONFIG,
                         return_receptacles=1)


def test_the_store_reads_both_families():
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
    boxes = predictor.sample(homes, queries, 2, jax.random.key(0), config=CONFIG)
    assert boxes.shape == (homes.num_homes, 3, 2, 6) and np.all(np.isfinite(boxes))


def test_the_history_read_out_is_sized_before_a_run_starts():
    """model.history_heads is a size: the run's estimate counts the read-out and refuses it."""
    from flowmaps_jax.training.config import apply_overrides, check_run_resources

    cfg = get_preset("homes")
    check_run_resources(cfg)
    with pytest.raises(ValueError, match=r"model.history_heads=60000\) would need about"):
        check_run_resources(apply_overrides(cfg, ["model.history_heads=60000"]))
