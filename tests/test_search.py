"""Tests for flowmaps_jax.search: table probabilities, Bayes updates, policies (the exact DP
against brute force and the greedy policies), episodes, metrics and the protocol's report.

Every episode batch here has one shape (48 episodes × 4 tables, budget 10), so the simulator is
compiled twice in all (48 episodes, and 4 × 48 for the expectations over hiding places).
"""

from __future__ import annotations

import itertools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from flowmaps_jax import tables
from flowmaps_jax.flowsim import FlowSimConfig, exact_posterior
from flowmaps_jax.navigation import policies as P
from flowmaps_jax.search import cli, figures, protocol, report
from flowmaps_jax.search import episodes as E
from flowmaps_jax.search import probabilities as T
from flowmaps_jax.search import scores as S
from flowmaps_jax.tokens import OBJECT

NUM_ENVS = 16  # × 3 objects = 48 episodes
N, K = 48, 4
BUDGET = E.DEFAULT_BUDGET


class EchoPredictor:
    """A stand-in model: 3/4 of its samples are the object's box where it was last seen (its
    token at τ), 1/4 far off the map. Its table probabilities are last-seen's, with off mass."""

    name = "echo"
    kind = "echo"

    def __init__(self, flowsim: FlowSimConfig | None = None):
        self.flowsim = flowsim  # the config it was "trained" on: the search's

    def sample(self, tokens, queries, num_samples, key):
        same = np.asarray(queries.descriptor)[:, :, None] == np.asarray(tokens.descriptor)[:, None]
        match = same & (np.asarray(tokens.kind) == OBJECT)[:, None]
        boxes = np.einsum("bqs,bsk->bqk", match.astype(np.float32), np.asarray(tokens.boxes))
        samples = np.repeat(boxes[:, :, None], num_samples, axis=2)
        samples[:, :, 3 * num_samples // 4:, :2] += 3.0  # off the map, near no table
        return jnp.asarray(samples)


@pytest.fixture(scope="module")
def scenes(small_scenes):
    return jax.tree_util.tree_map(lambda a: a[:NUM_ENVS], small_scenes)


@pytest.fixture(scope="module")
def search_set(scenes, flowsim_config):
    s = E.build_search_set(scenes, flowsim_config, jax.random.key(3))
    assert s.num_tables == K and s.obj.size == N
    return s


@pytest.fixture(scope="module")
def exact_episodes(search_set):
    return E.make_episodes(search_set, E.exact_tables(search_set))[0]


def random_episodes(seed: int, concentration: float = 0.7, tables=(2, 3, 4)) -> E.Episodes:
    """48 episodes over 4 padded tables, each with 2, 3 or 4 real ones; Dirichlet beliefs."""
    rng = np.random.default_rng(seed)
    count = rng.choice(tables, N)
    valid = np.arange(K) < count[:, None]
    belief = np.where(valid, rng.dirichlet(np.full(K, concentration), N), 0.0)
    belief = (belief / belief.sum(-1, keepdims=True)).astype(np.float32)
    return E.Episodes(belief=belief, centres=rng.uniform(0, 256, (N, K, 2)).astype(np.float32),
                      valid=valid, start=rng.uniform(0, 256, (N, 2)).astype(np.float32),
                      target=np.zeros(N, np.int32))


def brute_force_travel(belief, centres, start) -> float:
    """The least expected travel over every visiting order of the real tables (numpy)."""
    best = np.inf
    for order in itertools.permutations(range(len(belief))):
        legs = np.linalg.norm(np.diff(np.vstack([start, centres[list(order)]]), axis=0), axis=1)
        unfound = 1.0 - np.concatenate([[0.0], np.cumsum(belief[list(order)])[:-1]])
        best = min(best, float(legs @ unfound))
    return best


def expected(episodes, truth, policy) -> dict:
    return S.expected_scores(*E.expected_outcomes(episodes, truth, policy, BUDGET))


# --------------------------------------------------------------------------- the exact DP


def test_optimal_plan_equals_brute_force_over_orders():
    eps = random_episodes(0)
    values = jax.jit(jax.vmap(P.optimal_expected_travel))(eps.belief, eps.centres, eps.valid,
                                                          eps.start)
    for n in range(N):
        real = np.flatnonzero(eps.valid[n])
        bf = brute_force_travel(eps.belief[n, real], eps.centres[n, real], eps.start[n])
        assert float(values[n]) == pytest.approx(bf, rel=1e-4, abs=1e-3)


@pytest.mark.parametrize("seed,concentration", [(1, 0.7), (2, 3.0)])
def test_dp_policy_travel_is_optimal_and_never_worse_than_the_greedy_policies(seed,
                                                                              concentration):
    """When the object hides where the belief says, the DP policy's expected travel (re-planned
    after every look) is the brute-force optimum, and no other policy does better."""
    eps = random_episodes(seed, concentration)
    travel = {p: expected(eps, eps.belief, p)["travel"] for p in P.POLICIES}
    for n in range(N):
        real = np.flatnonzero(eps.valid[n])
        bf = brute_force_travel(eps.belief[n, real], eps.centres[n, real], eps.start[n])
        assert travel["optimal"][n] == pytest.approx(bf, rel=1e-4, abs=1e-3)
    for policy in ("most-probable", "greedy", "nearest"):
        assert np.all(travel["optimal"] <= travel[policy] + 1e-3 * (1 + travel[policy]))
    assert np.any(travel["optimal"] < travel["most-probable"] - 1.0)  # it is not a tie


def test_optimal_refuses_more_than_seven_tables_and_says_why():
    eps = E.Episodes(belief=np.full((1, 8), 1 / 8, np.float32), centres=np.zeros((1, 8, 2)),
                     valid=np.ones((1, 8), bool), start=np.zeros((1, 2)),
                     target=np.zeros(1, np.int32))
    with pytest.raises(ValueError, match=r"at most 7 candidate tables.*2\^K"):
        E.run_episodes(eps, "optimal")


# --------------------------------------------------------------------------- Bayes


def test_bayes_update_matches_hand_computation():
    b = np.array([0.5, 0.3, 0.2], np.float32)
    np.testing.assert_allclose(E.bayes_update(b, np.int32(0), 0.2),
                               np.array([0.1, 0.3, 0.2]) / 0.6, rtol=1e-6)
    np.testing.assert_allclose(E.bayes_update(b, np.int32(1), 0.0), [0.5 / 0.7, 0.0, 0.2 / 0.7],
                               rtol=1e-6)
    # nothing left (the prior ruled the rest out): uniform over the tables not looked at
    np.testing.assert_allclose(E.bayes_update(np.array([0.0, 1.0, 0.0]), np.int32(1)),
                               [0.5, 0.0, 0.5])


def test_p_miss_zero_is_zero_and_renormalise():
    eps = random_episodes(3)
    looked = np.asarray(eps.target) + 1  # table 1 always exists
    plain = np.where(np.arange(K) == looked[:, None], 0.0, eps.belief)
    plain = plain / plain.sum(-1, keepdims=True)
    got = E.bayes_update(eps.belief, looked, 0.0, valid=eps.valid)
    np.testing.assert_allclose(got, np.where(np.isfinite(plain), plain, got), atol=1e-6)


# --------------------------------------------------------------------------- episodes


def test_exact_posterior_most_probable_first_expected_looks_is_sum_rank_q(search_set,
                                                                           exact_episodes):
    q = np.asarray(E.truth_probs(search_set), np.float64)
    rank = np.argsort(np.argsort(-q, axis=1, kind="stable"), axis=1) + 1
    looks = expected(exact_episodes, q, "most-probable")["looks"]
    np.testing.assert_allclose(looks, np.sum(rank * q, axis=1), atol=1e-5)


def test_all_mass_on_the_true_table_is_found_in_one_look(exact_episodes):
    truth = np.asarray(exact_episodes.target)
    sure = exact_episodes.replace(belief=jax.nn.one_hot(truth, K) * exact_episodes.valid)
    for policy in ("most-probable", "greedy", "optimal"):
        out = E.run_episodes(sure, policy)
        s = S.episode_scores(out)
        assert np.all(s["sr@1"] == 1.0) and np.all(out.path[:, 1] == -1)
        np.testing.assert_allclose(out.travel, out.shortest, rtol=1e-5)
        np.testing.assert_allclose(s["spl"], 1.0, rtol=1e-5)


def test_rollout_is_the_every_target_run_at_the_true_table(exact_episodes, search_set):
    every, weights = E.expected_outcomes(exact_episodes, E.truth_probs(search_set), "optimal")
    single = E.run_episodes(exact_episodes, "optimal")
    picked = E.at_targets(every, exact_episodes.target)
    for a, b in zip(jax.tree_util.tree_leaves(single), jax.tree_util.tree_leaves(picked),
                    strict=True):
        np.testing.assert_array_equal(a, b)
    assert np.all(single.found) and np.all(single.looks <= exact_episodes.valid.sum(-1))
    np.testing.assert_allclose(np.sum(weights, axis=0), 1.0, atol=1e-5)


def test_imperfect_detector_is_seeded_and_costs_looks(exact_episodes):
    key = jax.random.key(7)
    a = E.run_episodes(exact_episodes, "greedy", key, p_miss=0.5)
    b = E.run_episodes(exact_episodes, "greedy", key, p_miss=0.5)
    perfect = E.run_episodes(exact_episodes, "greedy", key)
    np.testing.assert_array_equal(a.path, b.path)
    assert a.looks.mean() > perfect.looks.mean()
    path = np.asarray(a.path)
    assert not np.any((path[:, 1:] == path[:, :-1]) & (path[:, 1:] >= 0))  # never twice in a row


# --------------------------------------------------------------------------- table probabilities


def test_exact_table_probabilities_are_the_exact_posterior_on_the_route(search_set,
                                                                        flowsim_config):
    probs = np.asarray(E.exact_tables(search_set))
    q = exact_posterior(np.asarray(search_set.num_slots), np.asarray(search_set.slot_now),
                        np.asarray(search_set.horizon), flowsim_config)
    order = np.asarray(search_set.visit_order)
    expected_probs = np.zeros_like(probs)
    r, m, k = np.nonzero(order >= 0)
    expected_probs[r, m, order[r, m, k]] = np.asarray(q)[r, m, k]
    np.testing.assert_allclose(probs, expected_probs, atol=1e-7)
    furniture = flowsim_config.num_furniture
    assert np.all(probs[..., furniture:] == 0.0)  # object tokens, padding and the off bin


def test_sampled_table_probabilities_and_their_dict_form(search_set):
    tokens = jax.tree_util.tree_map(lambda a: a[:4], search_set.tokens)
    queries = jax.tree_util.tree_map(lambda a: a[:4], search_set.queries)
    probs = np.asarray(tables.table_probabilities(EchoPredictor(), tokens, queries, 8,
                                             jax.random.key(0)))
    seen = np.asarray(search_set.visit_order)[np.arange(4)[:, None], np.arange(3),
                                              np.asarray(search_set.slot_now)[:4]]
    assert probs.shape == (4, 3, tokens.num_tokens + 1)
    np.testing.assert_allclose(probs[np.arange(4)[:, None], np.arange(3), seen], 0.75)
    np.testing.assert_allclose(probs[..., -1], 0.25)
    as_dict = T.table_dict(probs, tokens)
    for b, q in itertools.product(range(4), range(3)):
        entry = as_dict[b][q]
        assert set(entry) == {*range(10), T.OFF}
        assert all(isinstance(k, int) and isinstance(v, float) for k, v in entry.items()
                   if k != T.OFF)
        np.testing.assert_allclose([entry[s] for s in range(10)], probs[b, q, :10])
        assert entry[T.OFF] == pytest.approx(probs[b, q, -1])


# --------------------------------------------------------------------------- protocol and report


@pytest.fixture(scope="module")
def results(scenes, flowsim_config):
    return protocol.run_search([EchoPredictor(flowsim_config)], scenes, flowsim_config, seed=3,
                               num_samples=8, times_per_env=1, progress=False)


def test_protocol_rows_ratios_and_monotone_success(results):
    table, runs, _ = results
    rows = table["rows"]
    assert list(rows) == [protocol.EXACT_ROW, "echo", protocol.UNIFORM_ROW,
                          protocol.LAST_SEEN_ROW, protocol.NEAREST_ROW]
    for policy in protocol.MAIN_POLICIES:
        exact = rows[protocol.EXACT_ROW]["policies"][policy]
        for part in ("ratio", "expected_ratio"):
            for name in ("looks", "travel", "spl", "sr@1"):
                assert exact[part]["overall"][name] == pytest.approx(1.0)
                assert all(v[name] in (None, pytest.approx(1.0))
                           for v in exact[part]["by_horizon"].values())
        for entry in rows.values():
            o = entry["policies"][policy]["summary"]["overall"]
            assert o["sr@1"]["mean"] <= o["sr@2"]["mean"] <= o["sr@3"]["mean"] <= 1.0
            curve = entry["policies"][policy]["curves"]
            assert np.all(np.diff(curve["looks"]) >= 0)
            assert np.all(np.diff(curve["distance"]["success"]) >= 0)
            assert o["found"]["mean"] == 1.0  # perfect detector, budget ≥ K
        # the Bayes-optimal searcher has the least expected travel of every row
        best = rows[protocol.EXACT_ROW]["policies"]["optimal"]["expected"]["overall"]["travel"]
        for entry in rows.values():
            assert entry["policies"][policy]["expected"]["overall"]["travel"]["mean"] \
                >= best["mean"] - 1e-3
    # the echo model's belief is last-seen's: the same episodes, and a quarter of its mass off
    echo, last = runs["echo", "optimal"], runs[protocol.LAST_SEEN_ROW, "optimal"]
    np.testing.assert_array_equal(echo.outcome.path, last.outcome.path)
    assert rows["echo"]["kind_mass"]["mean"] == pytest.approx(0.75)
    assert set(rows["echo"]["policies"]["greedy"]["summary"]["by_category"]) \
        == {"fork", "bottle", "remote"}


def test_report_and_figures_are_written(results, flowsim_config, tmp_path):
    table, runs, search_set = results
    names = cli.write_figures(table, runs, search_set, flowsim_config, tmp_path)
    table = {**table, "figures": names}
    paths = report.write_report(table, tmp_path)
    assert json.loads(paths["json"].read_text())["protocol"]["episodes"] == N
    text = paths["markdown"].read_text()
    for row in table["rows"]:
        assert text.count(f"| {row} |") >= 3 * 5  # 3 policy tables, 4 group tables each + mass
    assert "## optimal expected travel (exact DP)" in text and "SR@1 by horizon Δτ" in text
    # why flat priors can beat the exact searcher under most-probable first: once, under its table
    assert text.count(report.FLAT_PRIOR_NOTE) == 1
    assert text.index("## most-probable first") < text.index(report.FLAT_PRIOR_NOTE) \
        < text.index("## greedy probability per pixel")
    for name in names:
        assert (tmp_path / name).read_bytes().startswith(b"\x89PNG")
    assert len(figures.pick_episodes(search_set, count=3)) == 3


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("field,value,match", [
    ("belief", np.full((N, K), -0.25), "negative"),
    ("belief", np.full((N, K), np.nan), "NaN"),
    ("belief", np.full((N, K), 0.3), "sum to 1"),
    ("belief", np.full((N, 3), 1 / 3), "shape"),
    ("target", np.full(N, 9), "real table"),
])
def test_bad_episodes_name_the_field(field, value, match):
    eps = random_episodes(4, tables=(4,)).replace(**{field: value})
    with pytest.raises(ValueError, match=f"episodes.{field}.*{match}"):
        E.run_episodes(eps, "greedy")


@pytest.mark.parametrize("kwargs,name", [
    ({"policy": "random"}, "policy"), ({"p_miss": 1.0}, "p_miss"), ({"p_miss": -0.1}, "p_miss"),
    ({"budget": 0}, "budget"), ({"key": 3}, "key")])
def test_bad_arguments_name_themselves(kwargs, name):
    args = {"episodes": random_episodes(5), "policy": "greedy", **kwargs}
    with pytest.raises(ValueError, match=name):
        E.run_episodes(**args)


def test_other_bad_inputs(search_set):
    with pytest.raises(ValueError, match="belief"):
        E.bayes_update(np.array([0.5, 0.6]), np.int32(0))
    with pytest.raises(ValueError, match="start"):
        E.make_episodes(search_set, E.exact_tables(search_set), start="door")
    with pytest.raises(ValueError, match="table_probs"):
        E.make_episodes(search_set, np.zeros((2, 3, 4)))
    queries = search_set.queries.replace(descriptor=search_set.queries.descriptor + 3)
    with pytest.raises(ValueError, match=r"queries.descriptor\[0, 0\]"):
        tables.table_boxes(search_set.tokens, queries)
    with pytest.raises(ValueError, match="num_samples"):
        tables.table_probabilities(EchoPredictor(), search_set.tokens, search_set.queries, 0,
                              jax.random.key(0))
    with pytest.raises(ValueError, match="nearest"):
        protocol.score_priors(search_set, {}, None, policies=("nearest",))


def test_cli_rejects_bad_arguments_before_loading_models(capsys):
    assert cli.main(["--checkpoint", "pretrained:flowmaps", "--out", "x", "--p-miss", "1"]) == 2
    assert "--p-miss" in capsys.readouterr().err
    assert cli.main(["--checkpoint", "pretrained:flowmaps", "--budget", "0"]) == 2
    assert "--budget" in capsys.readouterr().err
    assert cli.main(["--checkpoint", "pretrained:flowmaps"]) == 2  # --out needed
    assert "--out" in capsys.readouterr().err


def test_cli_prints_the_checkpoint_and_step_of_each_model(capsys, monkeypatch, tmp_path):
    """Before searching, the CLI names every model with where it was loaded from and its step,
    as evaluate does."""
    from flowmaps_jax.predictor import load_pretrained

    def stop(*args, **kwargs):
        raise ValueError("stopped after the models were loaded")

    monkeypatch.setattr(cli, "validation_split", lambda *a, **k: None)
    monkeypatch.setattr(cli.pr, "run_search", stop)
    code = cli.main(["--checkpoint", "pretrained:flowmaps", "--baseline", "pretrained:mlp",
                     "--out", str(tmp_path / "search"), "--no-progress"])
    assert code == 2
    out = capsys.readouterr().out
    for name in ("flowmaps", "mlp"):
        model = load_pretrained(name)
        assert cli.loaded_from(model) == f"{model.name} (pretrained:{name}, step {model.step})"
        assert cli.loaded_from(model) in out
