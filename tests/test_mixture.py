"""The mixture head (issue 33): explicit table weights and a flow that places the object on a table.

Known answers: a fresh mixture model's placement flow has a zero final projection, so it carries
noise unchanged, z_1 = z_0 ~ N(0, I), in each table's local frame. Its density is then the closed
form Σ_s π_s N(z_s; 0, I) / Π scale, and its samples land on table s with frequency π_s. The
table weights are perturbed away from uniform so that these checks see them.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support import TINY, perturb

from flowmaps_jax.evaluation import protocol as ev
from flowmaps_jax.flowsim.config import FlowSimConfig
from flowmaps_jax.flowsim.scenes import validation_split
from flowmaps_jax.model import init_params, mixture
from flowmaps_jax.model.family import canonical_inputs
from flowmaps_jax.model.flowmaps import encode, object_table_logits, table_logits
from flowmaps_jax.predictor import Predictor
from flowmaps_jax.tables import table_probabilities
from flowmaps_jax.tokens import FURNITURE

SIM = FlowSimConfig()
MIXTURE = dataclasses.replace(TINY, head="mixture", weight_blocks=1)
GEOMETRY = jax.jit(mixture.relative_geometry, static_argnames="angle")  # one program per shape


@pytest.fixture(scope="module")
def evalset():
    return ev.build_eval_queries(validation_split(SIM, num_envs=40), SIM, jax.random.key(5),
                                 kl_draws=16)


@pytest.fixture(scope="module")
def fresh():
    """A mixture model whose table weights are perturbed and whose flow is still zero."""
    params = init_params(jax.random.key(1), MIXTURE)
    weights_only = {k: v for k, v in params.items() if k.startswith(("weight", "encoder"))}
    params = {**params, **perturb(weights_only, jax.random.key(2), 0.5)}
    return Predictor.from_params(params, MIXTURE)


def _closed_form(predictor, part):
    """log Σ_s π_s N(z_s; 0, I) / Π scale over every table (the zero flow's exact density)."""
    return np.asarray(_closed_form_kernel(predictor.params,
                                          *canonical_inputs(part.tokens, part.queries),
                                          part.kl_points))


@jax.jit  # one program, not one per operation
def _closed_form_kernel(params, tokens, queries, x):
    context = encode(params, MIXTURE, tokens)
    log_w = jax.nn.log_softmax(table_logits(params, MIXTURE, context, queries), -1)
    means, scale, _ = mixture.placement_frame(context, queries.descriptor)
    z = (mixture.to_centre(x)[:, :, :, None] - means[:, :, None]) / scale[:, :, None, None]
    log_n = -0.5 * jnp.sum(z ** 2 + jnp.log(2 * jnp.pi), -1) + mixture.local_log_det(scale)[
        ..., None]
    return jax.nn.logsumexp(log_n + log_w[:, :, None], axis=-1)


def test_weights_are_a_distribution_over_the_tables(evalset, fresh):
    w = np.asarray(fresh.table_weights(evalset.tokens, evalset.queries))
    np.testing.assert_allclose(w.sum(-1), 1.0, rtol=1e-5)
    tables = (np.asarray(evalset.tokens.mask) & (np.asarray(evalset.tokens.kind) == FURNITURE))
    off_tables = np.concatenate([~tables, np.ones_like(tables[:, :1])], -1)[:, None]
    assert np.all(w[np.broadcast_to(off_tables, w.shape)] < 1e-6)
    assert np.std(w[..., :SIM.num_furniture]) > 0.01  # perturbed: not uniform


def test_one_pass_gives_every_horizon(evalset, fresh):
    """Column Δτ of the per-object logits is the query's logits at Δτ: one consistent model."""
    part = evalset.take(np.arange(6))
    tokens, queries = canonical_inputs(part.tokens, part.queries)
    context = encode(fresh.params, MIXTURE, tokens)
    per_query = np.asarray(table_logits(fresh.params, MIXTURE, context, queries))
    every = np.asarray(object_table_logits(fresh.params, MIXTURE, context, queries.descriptor))
    dtau = np.asarray(queries.tau_q) - np.asarray(tokens.tau)[:, None]
    np.testing.assert_allclose(np.take_along_axis(every, dtau[..., None, None], -1)[..., 0],
                               per_query, rtol=1e-5, atol=1e-5)


def test_density_is_the_closed_form(evalset, fresh):
    part = evalset.take(np.arange(6))
    want = _closed_form(fresh, part)
    for method, steps in (("midpoint", 10), ("accurate", 24)):
        got = np.asarray(fresh.log_prob(part.tokens, part.queries, part.kl_points,
                                        num_steps=steps, method=method))
        np.testing.assert_allclose(got, want, atol=2e-3, rtol=1e-5)


def test_samples_land_on_the_tables_with_the_weights(evalset, fresh):
    part = evalset.take(np.arange(4))
    n = 2000
    sampled = np.asarray(table_probabilities(fresh, part.tokens, part.queries, n,
                                             jax.random.key(3)))
    weights = np.asarray(fresh.table_weights(part.tokens, part.queries))
    assert np.mean(sampled[..., -1]) < 0.01
    tolerance = 5 * np.sqrt(weights * (1 - weights) / n) + 2e-3
    assert np.all(np.abs(sampled[..., :-1] - weights[..., :-1]) <= tolerance[..., :-1])


def test_sample_with_log_prob_matches_log_prob(evalset, fresh):
    part = evalset.take(np.arange(3))
    boxes, log_p = fresh.sample(part.tokens, part.queries, 8, jax.random.key(4),
                                return_log_prob=True)
    again = fresh.log_prob(part.tokens, part.queries, boxes)
    np.testing.assert_allclose(np.asarray(log_p), np.asarray(again), atol=1e-4)


def test_frame_round_trip_and_start_table(evalset):
    @jax.jit  # one program, not one per operation
    def frames(params, tokens, queries, box, slots):
        context = encode(params, MIXTURE, tokens)
        means, scale, start = mixture.placement_frame(context, queries.descriptor)
        rows = jnp.broadcast_to(start[..., None], box.shape[:3])
        local = mixture.to_local(box, mixture.gather_rows(means, rows), scale)
        back = mixture.from_local(local, mixture.gather_rows(means, rows), scale)
        table, _ = mixture.nearest_tables(slots, context, terms=1)
        z = mixture.to_local(slots, mixture.gather_rows(means, table[..., 0]), scale)
        return back, z, start

    box = np.asarray(evalset.kl_points[:, :, :3])
    slots = np.asarray(evalset.slot_boxes)  # (E, M, F, 4)
    back, z, start = frames(init_params(jax.random.key(0), MIXTURE),
                            *canonical_inputs(evalset.tokens, evalset.queries), box, slots)
    np.testing.assert_allclose(np.asarray(back), box, atol=1e-6)
    # every slot's box sits at the origin of its own table's frame (FlowSim centres objects)
    real = np.asarray(evalset.slot_mask)
    np.testing.assert_allclose(np.asarray(z)[real], 0.0, atol=1e-4)
    assert np.all(np.asarray(start) >= 0)


@pytest.mark.slow  # end to end: pytest -m slow (tests/conftest.py)
def test_default_load_picks_the_lowest_validation_table_cross_entropy(tmp_path):
    """The checkpoint rule (issue 33): a mixture-head run's validation score is the table
    weights' cross-entropy on the fixed validation batches, and the default load (``best``, what
    evaluate, search and export use) is the step where it is lowest."""
    import json

    from flowmaps_jax.predictor import load
    from flowmaps_jax.training import loop, objectives
    from flowmaps_jax.training.config import get_preset
    from flowmaps_jax.worlds import flowsim as data

    base = get_preset("smoke")
    cfg = dataclasses.replace(base, model=dataclasses.replace(base.model, head="mixture",
                                                              weight_blocks=1),
                              pointer_loss=1.0, steps=30, val_every=10, ckpt_every=10,
                              routine_envs=0, lr=3e-3)
    loop.run(cfg, tmp_path, progress=False)
    records = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    val = {r["step"]: r["val_loss"] for r in records if r["kind"] == "val" and r["step"] > 0}
    rule = min(val, key=val.get)
    loaded = load(tmp_path / "checkpoints")
    assert loaded.step == rule
    _, val_scenes = data.load_splits(cfg, log=lambda _: None)
    batches = data.make_val_batches(cfg, val_scenes)
    objective = objectives.objective_for(cfg)
    table_ce = jax.jit(lambda params, batch, key: objective.loss(params, batch, key, False)[1][
        "table_ce"])
    ce = np.mean([float(table_ce(loaded.params, jax.tree.map(lambda x, j=j: x[j], batches),
                                 jax.random.key(j))) for j in range(cfg.val_batches)])
    np.testing.assert_allclose(ce, val[rule], rtol=1e-4)  # the score is the table CE


def test_self_attending_weight_rows_are_a_distribution_at_every_horizon(evalset):
    """``weight_attention="self"``: one object's rows attend to each other; still one pass for
    every horizon, and a distribution over the map's tables that moves with the start table."""
    cfg = dataclasses.replace(MIXTURE, weight_attention="self")
    params = perturb(init_params(jax.random.key(3), cfg), jax.random.key(4), 0.3)
    part = evalset.take(np.arange(6))
    tokens, queries = canonical_inputs(part.tokens, part.queries)
    context = encode(params, cfg, tokens)
    per_query = np.asarray(table_logits(params, cfg, context, queries))
    every = np.asarray(object_table_logits(params, cfg, context, queries.descriptor))
    dtau = np.asarray(queries.tau_q) - np.asarray(tokens.tau)[:, None]
    np.testing.assert_allclose(np.take_along_axis(every, dtau[..., None, None], -1)[..., 0],
                               per_query, rtol=1e-5, atol=1e-5)
    w = np.asarray(Predictor.from_params(params, cfg).table_weights(part.tokens, part.queries))
    np.testing.assert_allclose(w.sum(-1), 1.0, rtol=1e-5)
    assert np.all(w[..., -1] < 1e-6) and np.std(w[..., :SIM.num_furniture]) > 0.01


def test_relative_geometry_is_zero_at_the_start_table_and_feeds_the_rows(evalset):
    """``weight_geometry="relative"``: each row's features are its centre offset from the start
    table and its turn around the map centre; both vanish on the start table itself, and the
    option changes the table weights (the rows read them)."""
    part = evalset.take(np.arange(6))
    tokens, _ = canonical_inputs(part.tokens, part.queries)
    start = np.asarray([[0, 3], [2, 1]] * 3, np.int32)  # (6, 2) token indices
    feats = np.asarray(GEOMETRY(tokens.boxes, start))
    assert feats.shape == (6, 2, tokens.boxes.shape[1], 2 + 4 * len(mixture.GEOMETRY_FREQUENCIES)
                           + 4)
    at_start = np.take_along_axis(feats, start[:, :, None, None], axis=2)[:, :, 0]
    np.testing.assert_allclose(at_start[..., :2], 0.0, atol=1e-7)  # no offset
    np.testing.assert_allclose(at_start[..., -4:],  # no turn
                               np.broadcast_to([0.0, 0.0, 1.0, 1.0], at_start[..., -4:].shape),
                               atol=1e-6)
    cfg = dataclasses.replace(MIXTURE, weight_geometry="relative", weight_attention="self")
    params = perturb(init_params(jax.random.key(3), cfg), jax.random.key(4), 0.3)
    w = np.asarray(Predictor.from_params(params, cfg).table_weights(part.tokens, part.queries))
    np.testing.assert_allclose(w.sum(-1), 1.0, rtol=1e-5)
    flat = dict(params)
    flat["geometry_embed"] = jax.tree.map(np.zeros_like, params["geometry_embed"])
    w0 = np.asarray(Predictor.from_params(flat, cfg).table_weights(part.tokens, part.queries))
    assert np.abs(w - w0).max() > 1e-4
    with pytest.raises(ValueError, match="weight_geometry"):
        dataclasses.replace(MIXTURE, weight_geometry="absolute")


def test_offsets_geometry_has_no_angle_and_moves_with_the_map(evalset):
    """``weight_geometry="offsets"`` (issue 47's world-agnostic rows): the centre features and
    the distance, no angle around the map centre. Shifting every box leaves them unchanged (the
    angle features change), and a model with them gives table weights."""
    part = evalset.take(np.arange(4))
    tokens, _ = canonical_inputs(part.tokens, part.queries)
    start = np.asarray([[0, 3], [2, 1]] * 2, np.int32)
    k = len(mixture.GEOMETRY_FREQUENCIES)
    boxes = np.asarray(tokens.boxes)
    shifted = boxes + np.float32([0.07, -0.05, 0.0, 0.0])  # (y, x, h, w): a translation
    plain = np.asarray(GEOMETRY(boxes, start, angle=False))
    moved = np.asarray(GEOMETRY(shifted, start, angle=False))
    assert plain.shape[-1] == 2 + 4 * k + 1
    np.testing.assert_allclose(moved, plain, atol=1e-5)
    distance = np.linalg.norm(plain[..., :2], axis=-1)
    np.testing.assert_allclose(plain[..., -1], distance, atol=1e-6)
    with_angle = np.asarray(GEOMETRY(boxes, start))
    assert np.abs(np.asarray(GEOMETRY(shifted, start)) - with_angle).max() > 1e-2
    cfg = dataclasses.replace(MIXTURE, weight_geometry="offsets", weight_attention="self")
    params = init_params(jax.random.key(3), cfg)
    w = np.asarray(Predictor.from_params(params, cfg).table_weights(part.tokens, part.queries))
    np.testing.assert_allclose(w.sum(-1), 1.0, rtol=1e-5)
