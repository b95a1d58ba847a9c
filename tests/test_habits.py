"""Habits in FlowSim (issue 18): the default world is unchanged, the three habits follow their
laws, and the history posterior is exact (against enumeration and an independent NumPy
implementation)."""

from __future__ import annotations

import dataclasses
import hashlib
import itertools

import jax
import numpy as np
import pytest
from support import perturb

from flowmaps_jax.flowsim import (
    FlowSimConfig,
    empirical_frequency,
    exact_posterior,
    generate,
    history_posterior,
    world_config,
)
from flowmaps_jax.flowsim import habits as hb
from flowmaps_jax.flowsim.config import sim_params, sim_shape

# generate(key 0, 256, FlowSimConfig()) before habits existed (commit d98c1fe): the hash of its
# nine arrays. The paper's world must stay bit-identical.
PAPER_WORLD_DIGEST = "c914e009aae5723bc03e8ddcd03820e8f89ecfa1c87ba6a825d05fbd7cdbc0c4"
PAPER_FIELDS = ("furniture_boxes", "furniture_kind", "object_kind", "object_size", "visit_order",
                "num_slots", "slot", "object_boxes", "layout_redraws")


def test_paper_world_is_bit_identical(small_scenes):
    digest = hashlib.sha256()
    for name in PAPER_FIELDS:
        digest.update(np.ascontiguousarray(np.asarray(getattr(small_scenes, name))).tobytes())
    assert digest.hexdigest() == PAPER_WORLD_DIGEST
    assert not np.any(np.asarray(small_scenes.habit))


# ------------------------------------------------- an independent NumPy implementation (float64)


PAPER = FlowSimConfig()


def np_matrix(family: str, k: int, f: int, favourites=(), centres=None, cfg=PAPER):
    """The habit's F x F matrix written from the spec, loop by loop."""
    m = np.zeros((f, f))
    for i in range(k):
        if family == "routine":
            for advance, p in enumerate(cfg.transition_probs):
                m[i, (i + advance) % k] += p
        elif family == "preferences":
            others = [j for j in range(k) if j not in favourites]
            pi = np.zeros(f)
            if others:
                pi[list(favourites)] = cfg.preference_mass / len(favourites)
                pi[others] = (1 - cfg.preference_mass) / len(others)
            else:
                pi[list(favourites)] = 1 / len(favourites)
            m[i, :] = cfg.preference_move * pi
            m[i, i] += 1 - cfg.preference_move
        else:
            w = np.array([0.0 if j == i else np.exp(-np.hypot(*(centres[i] - centres[j]))
                                                      / cfg.dynamic_length) for j in range(k)])
            if w.sum() == 0:
                m[i, i] = 1.0
            else:
                m[i, :k] = (1 - cfg.dynamic_stay) * w / w.sum()
                m[i, i] = cfg.dynamic_stay
    return m


def np_hypotheses(k: int, f: int, centres, habit_probs, cfg=PAPER):
    """(matrices, prior) of every hypothesis that exists for K places."""
    singles = [(i,) for i in range(k)]
    pairs = list(itertools.combinations(range(k), 2))
    mats, prior = [np_matrix("routine", k, f, cfg=cfg)], [habit_probs[0]]
    for fav in singles + pairs:
        mats.append(np_matrix("preferences", k, f, fav, cfg=cfg))
        prior.append(habit_probs[1] / (len(singles) + len(pairs)))
    mats.append(np_matrix("dynamic", k, f, centres=centres, cfg=cfg))
    prior.append(habit_probs[2])
    return np.array(mats), np.array(prior)


def test_matrices_match_numpy_and_are_stochastic():
    cfg = world_config("mixed")
    f = cfg.num_furniture
    rng = np.random.default_rng(0)
    centres = rng.uniform(0, 1, (f, 2)).astype(np.float32)
    params = sim_params(cfg)
    _family, _favourites, needs = hb.hypothesis_table(f)
    both = jax.jit(lambda k: (hb.transition_matrices(k, centres, params),  # one program
                              hb.habit_prior(k, cfg.habit_probs, f)))
    for k in (1, 3, 4):
        got, got_prior = (np.asarray(a) for a in both(np.int32(k)))
        exists = needs <= k
        want, prior = np_hypotheses(k, f, centres.astype(np.float64), cfg.habit_probs, cfg)
        np.testing.assert_allclose(got[exists], want, atol=1e-6)
        np.testing.assert_allclose(got[exists][:, :k].sum(-1), 1.0, atol=1e-6)
        np.testing.assert_allclose(got_prior[exists], prior, atol=1e-7)
        assert not np.any(got_prior[~exists])


# ------------------------------------------------------ the posterior against enumeration

MIXED_ENVS = 4096


@pytest.fixture(scope="module")
def mixed():
    """(config, scenes): 4,096 environments of the mixed world (each habit on about a third of
    the objects), T = 20; one compiled generator for every test here."""
    cfg = world_config("mixed")
    return cfg, generate(jax.random.key(11), MIXED_ENVS, cfg)


def enumerate_posterior(mats, prior, observed: dict[int, int], query_time: int, k: int):
    """Brute force: sum P(h) P(path | h) over every path s_0 = 0, s_1 … s_{query_time}
    that agrees with ``observed`` (time -> slot); return the law of s_{query_time}."""
    paths = np.array([(0, *p) for p in itertools.product(range(k), repeat=query_time)])
    keep = np.all([paths[:, t] == s for t, s in observed.items()], axis=0)
    paths = paths[keep]
    steps = mats[:, paths[:, :-1], paths[:, 1:]]  # (NH, paths, query_time)
    joint = prior @ np.prod(steps, axis=-1)  # (paths,)
    out = np.bincount(paths[:, -1], weights=joint, minlength=mats.shape[-1])
    return out / out.sum()


def test_history_posterior_matches_enumeration(mixed):
    """24 queries with τ + Δτ <= 6 (so every path can be listed), histories of 1 to 5 steps,
    every habit family present: equal to brute-force enumeration to 1e-6."""
    cfg, scenes = mixed
    rng = np.random.default_rng(1)
    env = rng.integers(0, MIXED_ENVS, 24)
    obj = rng.integers(0, 3, 24)
    tau = rng.integers(0, 5, 24)
    horizon = np.minimum(rng.integers(0, 3, 24), 6 - tau)
    hist = np.minimum(rng.integers(1, 6, 24), tau + 1)
    got = np.asarray(history_posterior(scenes, cfg, env, obj, tau, horizon, hist))
    families = hb.hypothesis_table(cfg.num_furniture)[0][np.asarray(scenes.habit)[env, obj]]
    assert set(families) == {0, 1, 2}
    centres = np.asarray(hb.slot_centres(scenes, cfg), np.float64)
    slots = np.asarray(scenes.slot)
    for q in range(24):
        e, o = env[q], obj[q]
        k = int(scenes.num_slots[e, o])
        mats, prior = np_hypotheses(k, cfg.num_furniture, centres[e, o], cfg.habit_probs, cfg)
        seen = {t: int(slots[e, t, o]) for t in range(tau[q] - hist[q] + 1, tau[q] + 1)}
        want = enumerate_posterior(mats, prior, seen, int(tau[q] + horizon[q]), k)
        np.testing.assert_allclose(got[q], want, atol=1e-6)


def test_history_of_one_under_the_routine_is_exact_posterior(small_scenes, flowsim_config):
    rng = np.random.default_rng(2)
    env, obj = rng.integers(0, 256, 24), rng.integers(0, 3, 24)
    tau = rng.integers(0, 19, 24)
    horizon = rng.integers(0, 20 - tau)
    got = history_posterior(small_scenes, flowsim_config, env, obj, tau, horizon, 1)
    want = exact_posterior(np.asarray(small_scenes.num_slots)[env, obj],
                           np.asarray(small_scenes.slot)[env, tau, obj], horizon)
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-6)
    # Under the routine the past adds nothing: the chain is Markov and the habit is known.
    longer = history_posterior(small_scenes, flowsim_config, env, obj, tau, horizon,
                               np.minimum(8, tau + 1))
    np.testing.assert_allclose(np.asarray(longer), np.asarray(want), atol=1e-6)


def test_history_sharpens_the_preferences_posterior(mixed):
    """On objects with favourites, more history puts more mass on where they really are
    (mean log-probability of the true slot 10 steps ahead, 1 -> 8 observations)."""
    cfg, scenes = mixed
    family = hb.hypothesis_table(cfg.num_furniture)[0][np.asarray(scenes.habit)]
    env, obj = np.nonzero(family == 1)
    env, obj = env[:24], obj[:24]
    tau, horizon = np.full(24, 9), np.full(24, 10)
    truth = np.asarray(scenes.slot)[env, 19, obj]
    score = [np.mean(np.log(np.asarray(history_posterior(scenes, cfg, env, obj, tau, horizon, h))
                            [np.arange(24), truth])) for h in (1, 8)]
    assert score[1] > score[0] + 0.05, score


# ------------------------------------------------------- rollouts against the step laws


@pytest.fixture(scope="module")
def own_matrices(mixed):
    """(env, obj, own (N, F, F) float64, family (N,)): the matrix of the habit drawn for each
    of the first three objects of every mixed environment."""
    cfg, scenes = mixed
    env, obj = np.meshgrid(np.arange(scenes.num_envs), np.arange(3), indexing="ij")
    env, obj = env.ravel(), obj.ravel()
    habit = np.asarray(scenes.habit)[env, obj]
    own = jax.jit(lambda s, e, o, h: hb.scene_hypotheses(s, cfg, e, o)[0][np.arange(env.size), h])
    own = np.asarray(own(scenes, env, obj, habit), np.float64)  # (N, F, F); one program
    family = hb.hypothesis_table(cfg.num_furniture)[0][habit]
    return env, obj, own, family


def test_rollouts_follow_their_habit_matrices(mixed, own_matrices):
    """Monte Carlo: every step (slot -> next) of 4,096 mixed-world environments against its
    object's own matrix row: per family, the mean of onehot(next) − P[slot] is zero within 5
    standard errors; habit families are drawn with the config's weights."""
    cfg, scenes = mixed
    f = cfg.num_furniture
    env, obj, own, family = own_matrices
    slots = np.asarray(scenes.slot)[env, :, obj]  # (N, T)
    share = np.bincount(family, minlength=3) / family.size
    # the dynamic habit's matrix is built over SimShape.max_places places: K never exceeds it
    assert int(np.max(np.asarray(scenes.num_slots))) <= sim_shape(cfg).max_places < f
    np.testing.assert_allclose(share, cfg.habit_probs, atol=5 * np.sqrt(0.25 / family.size))
    for fam in range(3):
        rows = family == fam
        now, nxt = slots[rows, :-1], slots[rows, 1:]
        predicted = np.take_along_axis(own[rows], now[..., None], axis=1)  # (n, T-1, F)
        residual = np.eye(f)[nxt] - predicted
        se = np.sqrt(np.mean(predicted * (1 - predicted), axis=(0, 1)) / now.size) + 1e-9
        assert np.all(np.abs(residual.mean(axis=(0, 1))) <= 5 * se + 1e-6), fam


def test_rollouts_reach_the_stationary_law(mixed, own_matrices):
    """Preferences and dynamic objects forget their start within 19 steps: the slot at the last
    timestep follows each object's stationary distribution (left eigenvector of its matrix),
    within 5 binomial standard errors per (family, K); the preferences stationary law is π."""
    cfg, scenes = mixed
    env, obj, own, family = own_matrices
    k = np.asarray(scenes.num_slots)[env, obj]
    own = own / np.maximum(own.sum(-1, keepdims=True), 1e-12)  # float32 rows, renormalised
    stationary = np.stack([np.linalg.matrix_power(m, 256)[0] for m in own])
    pref = np.flatnonzero(family == 1)[:50]  # stationary law of "preferences" is π = P[i] − stay
    pi = (own[pref, 1] - (1 - cfg.preference_move) * np.eye(cfg.num_furniture)[1]) \
        / cfg.preference_move
    np.testing.assert_allclose(stationary[pref], pi, atol=1e-6)
    last = np.eye(cfg.num_furniture)[np.asarray(scenes.slot)[env, -1, obj]]
    for fam in (1, 2):
        for kk in np.unique(k):  # slot index means one place-in-order for one K
            rows = (k == kk) & (family == fam)
            expect, seen = stationary[rows].mean(0), last[rows].mean(0)
            se = np.sqrt(expect * (1 - expect) / rows.sum()) + 1e-9
            assert np.all(np.abs(seen - expect) <= 5 * se), (fam, kk, seen, expect)


# ------------------------------------------------------------------------- bad input


def test_bad_habits_and_histories_are_refused(small_scenes, flowsim_config):
    with pytest.raises(ValueError, match="habit name"):
        FlowSimConfig(habits=(("tidy", 1.0),))
    with pytest.raises(ValueError, match="habits probabilities"):
        FlowSimConfig(habits=(("routine", 0.5), ("dynamic", 0.4)))
    with pytest.raises(ValueError, match="world"):
        world_config("attic")
    one = np.array([0])
    for bad, match in ((0, "history_len"), (21, "history_len"), (5, "longer than the query")):
        with pytest.raises(ValueError, match=match):
            history_posterior(small_scenes, flowsim_config, one, one, np.array([3]), one, bad)


def test_empirical_frequency_counts_the_visible_history():
    history = np.array([[0, 2, 2, 1], [0, 0, 3, 3]])
    valid = np.array([[False, True, True, True], [True, True, True, True]])
    got = np.asarray(empirical_frequency(history, valid, 5))
    np.testing.assert_allclose(got, [[0, 1 / 3, 2 / 3, 0, 0], [0.5, 0, 0, 0.5, 0]], atol=1e-7)


# ------------------------------------------------------------- the model's history tokens


def test_history_tokens_append_the_past_maps_objects(mixed):
    from flowmaps_jax.flowsim.scenes import scene_tokens

    cfg, scenes = mixed
    cfg = dataclasses.replace(cfg, max_tokens=10 + 3 * 4)
    env, tau = np.array([0, 1, 2]), np.array([0, 2, 9])
    one = scene_tokens(scenes, env, tau, cfg)
    four = scene_tokens(scenes, env, tau, cfg, history=4)
    assert one.age is None and four.boxes.shape == (3, 22, 4)
    np.testing.assert_array_equal(np.asarray(four.boxes[:, :13]), np.asarray(one.boxes[:, :13]))
    np.testing.assert_array_equal(np.asarray(four.age[0]), [0] * 13 + [1, 1, 1, 2, 2, 2, 3, 3, 3])
    # maps before t = 0 do not exist: tau = 0 sees one map, tau = 2 three, tau = 9 four
    assert np.asarray(four.mask).sum(1).tolist() == [13, 19, 22]
    px = np.asarray(scenes.object_boxes)[1, 1, 2]  # environment 1, time 1, object 2
    np.testing.assert_allclose(np.asarray(four.boxes[1, 13 + 2]),
                               [px[0] / 255, px[1] / 255, (px[2] - px[0]) / 255,
                                (px[3] - px[1]) / 255], atol=1e-6)
    with pytest.raises(ValueError, match="history=5 needs 25 tokens"):
        scene_tokens(scenes, env, tau, cfg, history=5)


def test_a_history_model_reads_the_past_maps(mixed):
    """ModelConfig.history > 1 adds an age embedding, and the velocity depends on where the
    object was before τ; history 1 has no such parameter (the shipped models load unchanged)."""
    from flowmaps_jax.flowsim.scenes import scene_tokens
    from flowmaps_jax.model import ModelConfig
    from flowmaps_jax.model.families import model_family
    from flowmaps_jax.model.flowmaps import encode, velocity
    from flowmaps_jax.tokens import Queries

    cfg, scenes = mixed
    cfg = dataclasses.replace(cfg, max_tokens=10 + 3 * 3)
    small = dict(dim=16, encoder_layers=1, cdit_blocks=1, heads=2, freq_bands=4, dropout=0.0)
    family = model_family("flowmaps")
    params_1 = family.init(jax.random.key(0), ModelConfig(**small))
    assert "age_embed" not in str(jax.tree_util.tree_structure(params_1))
    model = ModelConfig(**small, history=3)
    params = family.init(jax.random.key(0), model)
    params = perturb(params, jax.random.key(1), scale=0.1)  # leave AdaLN-Zero's zero start
    tokens = scene_tokens(scenes, np.array([5]), np.array([9]), cfg, history=3)
    moved = tokens.replace(boxes=tokens.boxes.at[0, 13:].add(0.05))  # the past objects moved
    queries = Queries(descriptor=np.array([[0]], np.int32), tau_q=np.array([[12]], np.int32))
    x, t = np.zeros((1, 1, 1, 4), np.float32), np.full((1, 1), 0.5, np.float32)
    v = [np.asarray(velocity(params, model, encode(params, model, tk), x, t, queries))
         for tk in (tokens, moved)]
    assert np.all(np.isfinite(v[0])) and not np.allclose(v[0], v[1])


def test_the_habits_preset_reads_eight_maps_of_the_preferences_world():
    from flowmaps_jax.flowsim import world_of
    from flowmaps_jax.model import ModelConfig
    from flowmaps_jax.training.config import get_preset

    cfg = get_preset("habits")
    assert world_of(cfg.flowsim) == "preferences" and cfg.model.history == 8
    assert cfg.flowsim.max_tokens == 10 + 3 * 8
    with pytest.raises(ValueError, match=r"model\.history=9 reads 37 tokens"):
        dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, history=9))
    with pytest.raises(ValueError, match="history"):
        ModelConfig(history=0)


def test_a_file_from_before_habits_loads_with_every_object_on_the_routine(small_scenes,
                                                                         flowsim_config,
                                                                         tmp_path):
    from flowmaps_jax.flowsim import load_scenes, save_scenes

    save_scenes(tmp_path / "new.npz", small_scenes, flowsim_config)
    with np.load(tmp_path / "new.npz") as data:
        old = {k: data[k] for k in data.files if k != "habit"}
    old["format_version"] = np.int64(1)
    np.savez_compressed(tmp_path / "old.npz", **old)
    loaded, _ = load_scenes(tmp_path / "old.npz")
    assert np.asarray(loaded.habit).shape == (256, 3) and not np.any(np.asarray(loaded.habit))
    np.testing.assert_array_equal(np.asarray(loaded.slot), np.asarray(small_scenes.slot))


def test_train_set_world_puts_a_preset_on_a_world_and_refuses_an_unknown_one(tmp_path):
    from flowmaps_jax.flowsim import HABIT_WORLDS, world_of
    from flowmaps_jax.training import cli

    args = cli.build_parser().parse_args(
        ["--preset", "habits", "--set", "world=dynamic", "--set", "lr=1e-3",
         "--run-dir", str(tmp_path / "run")])
    cfg, _ = cli.resolve_config(args)
    assert world_of(cfg.flowsim) == "dynamic" and cfg.flowsim.habits == HABIT_WORLDS["dynamic"]
    assert cfg.lr == 1e-3 and cfg.model.history == 8  # the other fields still apply
    bad = cli.build_parser().parse_args(["--preset", "smoke", "--set", "world=bogus",
                                         "--run-dir", str(tmp_path / "bad")])
    with pytest.raises(ValueError, match="world must be one of"):
        cli.resolve_config(bad)
    resume = cli.build_parser().parse_args(["--resume", "--set", "world=mixed",
                                            "--run-dir", str(tmp_path / "run")])
    # a changed world on an existing run: tests/test_recorded_run_data.py (issue 57, class 5)
    with pytest.raises(ValueError, match="does not exist"):
        cli.resolve_config(resume)
