"""FlowSim homes evaluation: the reference priors, the posterior scores, object navigation (the
exact subset DP against brute force, the metrics) and the ``homes.evaluate`` command.

Tiny sizes: the "mixed" config over 8 days (every regime in one compiled program), 6 homes ×
3 queries; one command-line run on 4 default homes × 2 queries."""

from __future__ import annotations

import functools
import itertools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from flowmaps_jax.evaluation import priors as pr
from flowmaps_jax.evaluation import receptacle_protocol as ev
from flowmaps_jax.evaluation.receptacle_scores import (
    assign_samples,
    object_positions,
    posterior_scores,
)
from flowmaps_jax.flowsim.homes import (
    REGIMES,
    HomesConfig,
    generate_homes,
    homes_history_posterior,
    homes_posterior,
)
from flowmaps_jax.flowsim.homes.queries import HomesQueries, draw_queries
from flowmaps_jax.navigation import navigation as nav

CONFIG = HomesConfig(regime="mixed", num_hours=192)
HISTORY = 24
HORIZONS = (1, 6, 24)


@pytest.fixture(scope="module")
def homes():
    return generate_homes(jax.random.key(0), CONFIG, 6)


@pytest.fixture(scope="module")
def queries(homes):
    return draw_queries(jax.random.key(1), homes, CONFIG, 3, history=HISTORY, horizons=HORIZONS)


@pytest.fixture(scope="module")
def exact(homes, queries):
    return np.asarray(pr.exact_prior(CONFIG, HISTORY)(homes, queries))


@pytest.fixture(scope="module")
def geometry(homes):
    return nav.start_points(homes, CONFIG)


class StandIn:
    """A FlowMaps stand-in: the exact posterior as its probabilities, and boxes drawn from it,
    placed where the object would stand, as its samples."""

    def __init__(self, config, history):
        self.exact = pr.exact_prior(config, history)
        self.homes, self.step = config, None

    def probabilities(self, homes, queries, config):
        return self.exact(homes, queries)

    def sample(self, homes, queries, num_samples, key, config=None):
        return _placed(self.exact(homes, queries), homes, queries, key, num_samples, config)


@functools.partial(jax.jit, static_argnums=(4, 5))  # one program, not one per operation
def _placed(p, homes, queries, key, num_samples, config):
    """``num_samples`` boxes per query on receptacles drawn from ``p``, centred on them."""
    draws = jax.random.categorical(key, jnp.log(p)[..., None, :], shape=(*p.shape[:-1],
                                                                         num_samples))
    centre = jnp.take_along_axis(object_positions(homes, queries, config),
                                 draws[..., None], axis=2)  # (E, Q, N, 3)
    return jnp.concatenate([centre, jnp.full(centre.shape, 0.1)], axis=-1)


# --------------------------------------------------------------------------- priors


def test_every_prior_is_a_distribution_on_the_allowed_receptacles(homes, queries):
    allowed = np.asarray(pr.allowed_slots(homes, queries))
    rows = {"exact": pr.exact_prior(CONFIG, HISTORY), "uniform": pr.uniform_prior,
            "last-seen": pr.last_seen_prior(), "frequency": pr.frequency_prior(HISTORY),
            "oracle": pr.oracle_samples_prior(CONFIG, jax.random.key(2), 10, HISTORY)}
    for name, prior in rows.items():
        p = np.asarray(prior(homes, queries))
        assert p.shape == allowed.shape and p.dtype == np.float32, name
        assert np.all(p >= 0) and np.all(p[~allowed] == 0), name
        np.testing.assert_allclose(p.sum(-1), 1.0, atol=1e-5, err_msg=name)
    uniform = np.asarray(pr.uniform_prior(homes, queries))
    np.testing.assert_allclose(uniform[allowed], np.broadcast_to(
        1.0 / allowed.sum(-1, keepdims=True), allowed.shape)[allowed], rtol=1e-6)


def test_the_exact_prior_is_the_history_posterior(homes, queries, exact):
    obj, tau, tau_q = (np.asarray(a) for a in (queries.object_index, queries.tau,
                                                queries.tau_q))
    regime = np.take_along_axis(np.asarray(homes.regime), obj, 1)
    plain = np.asarray(pr.exact_prior(CONFIG, 1)(homes, queries))
    for e, j in itertools.product(range(obj.shape[0]), range(obj.shape[1])):
        home = homes.home(e)
        ref = homes_history_posterior(home, int(obj[e, j]), int(tau[e, j]), int(tau_q[e, j]),
                                      min(HISTORY, int(tau[e, j]) + 1), CONFIG)
        np.testing.assert_allclose(exact[e, j], ref, atol=1e-6)
        if REGIMES[regime[e, j]] != "preferences":  # the history changes nothing
            ref = homes_posterior(home, int(obj[e, j]), int(tau[e, j]), int(tau_q[e, j]),
                                  CONFIG)
            np.testing.assert_allclose(exact[e, j], ref, atol=1e-6)
            np.testing.assert_allclose(plain[e, j], ref, atol=1e-6)


def _object_with(homes, low: int):
    e, m = np.nonzero(np.asarray(homes.object_valid) & (np.asarray(homes.num_allowed) >= low))
    return int(e[0]), int(m[0])


def test_the_frequency_prior_counts_the_window_add_one(homes):
    e, i = _object_with(homes, 3)
    a, b, c = np.nonzero(np.asarray(homes.object_allowed[e, i]))[0][:3]
    n = int(homes.num_allowed[e, i])
    trajectory = np.asarray(homes.receptacle).copy()
    trajectory[e, 6:10, i] = [a, a, b, a]  # hours 6..9; the window of H = 4 at τ = 9
    trajectory[e, 0:2, i] = [c, b]  # hours 0, 1: the window of H = 4 at τ = 1 is clipped
    hand = homes.replace(receptacle=jnp.asarray(trajectory))
    num = homes.num_homes
    for tau, history, counts in ((9, 4, {a: 3, b: 1}), (1, 4, {c: 1, b: 1}),
                                 (9, 1, {a: 1})):
        q = HomesQueries(object_index=jnp.full((num, 1), i, jnp.int32),
                         tau=jnp.full((num, 1), tau, jnp.int32),
                         tau_q=jnp.full((num, 1), tau + 1, jnp.int32))
        p = np.asarray(pr.frequency_prior(history)(hand, q))[e, 0]
        total = min(history, tau + 1) + n
        expected = np.zeros_like(p)
        expected[np.asarray(homes.object_allowed[e, i])] = 1.0 / total
        for r, k in counts.items():
            expected[r] = (k + 1) / total
        np.testing.assert_allclose(p, expected, rtol=1e-6, err_msg=f"tau {tau} H {history}")


def test_last_seen_keeps_all_but_eps_where_the_object_was(homes, queries):
    p = np.asarray(pr.last_seen_prior(0.1)(homes, queries))
    allowed = np.asarray(pr.allowed_slots(homes, queries))
    now = np.asarray(pr.receptacle_at(homes, queries.tau, queries.object_index))
    n = allowed.sum(-1)
    here = np.take_along_axis(p, now[..., None], -1)[..., 0]
    np.testing.assert_allclose(here, np.where(n > 1, 0.9, 1.0), rtol=1e-6)
    others = allowed & (np.arange(p.shape[-1]) != now[..., None])
    spread = np.broadcast_to((0.1 / np.maximum(n - 1, 1))[..., None], p.shape)
    np.testing.assert_allclose(p[others], spread[others], rtol=1e-5)
    with pytest.raises(ValueError, match="eps"):
        pr.last_seen_prior(1.0)


def test_oracle_samples_count_draws_of_the_exact_posterior(homes, queries, exact):
    p = np.asarray(pr.oracle_samples_prior(CONFIG, jax.random.key(3), 20, HISTORY)(homes,
                                                                                  queries))
    np.testing.assert_allclose(p * 20, np.round(p * 20), atol=1e-4)  # multiples of 1/N
    many = np.asarray(pr.oracle_samples_prior(CONFIG, jax.random.key(3), 4000, HISTORY)(
        homes, queries))
    assert 0.5 * np.abs(many - exact).sum(-1).max() < 0.05


# --------------------------------------------------------------------------- scores


def test_posterior_scores_on_hand_cases():
    q = np.array([0.5, 0.3, 0.2, 0.0], np.float32)
    allowed = np.array([True, True, True, False])
    same = posterior_scores(q, q, allowed)
    assert {k: round(float(v), 6) for k, v in same.items()} == {
        "kl": 0.0, "tv": 0.0, "top1": 1.0, "rank_cost": 1.0}
    p = np.array([0.2, 0.3, 0.5, 0.0], np.float32)
    s = posterior_scores(p, q, allowed)
    np.testing.assert_allclose(float(s["kl"]), 0.5 * np.log(2.5) + 0.2 * np.log(0.4),
                               rtol=1e-5)
    np.testing.assert_allclose(float(s["tv"]), 0.3, atol=1e-6)
    assert float(s["top1"]) == 0.0
    np.testing.assert_allclose(float(s["rank_cost"]), 2.3 / 1.7, rtol=1e-6)
    tied = posterior_scores(np.array([1 / 3, 1 / 3, 1 / 3, 0], np.float32), q, allowed)
    np.testing.assert_allclose(float(tied["top1"]), 1 / 3, rtol=1e-6)  # one of three ties
    np.testing.assert_allclose(float(tied["rank_cost"]), 2.0 / 1.7, rtol=1e-6)
    off = posterior_scores(np.array([0.5, 0.3, 0.0, 0.0], np.float32), q, allowed)
    np.testing.assert_allclose(float(off["tv"]), 0.2, atol=1e-6)  # ½·0.2 + ½·0.2 off
    with pytest.raises(ValueError, match="allowed"):
        posterior_scores(p, q, allowed[:3])


def test_samples_are_assigned_to_the_receptacle_they_stand_on(homes, queries, exact):
    positions = np.asarray(object_positions(homes, queries, CONFIG))
    allowed = np.asarray(pr.allowed_slots(homes, queries))
    first = np.argmax(allowed, -1)  # (E, Q)
    centre = np.take_along_axis(positions, first[..., None, None], 2)  # (E, Q, 1, 3)
    far = centre + np.array([0.0, 0.0, 5.0], np.float32)  # 5 m above: off every receptacle
    boxes = np.concatenate([np.concatenate([centre, far, far, centre], 2),
                            np.full((*centre.shape[:2], 4, 3), 0.1, np.float32)], -1)
    p = np.asarray(assign_samples(boxes, homes, queries, CONFIG))
    expected = 0.5 * (np.arange(p.shape[-1]) == first[..., None])
    np.testing.assert_allclose(p, expected, atol=1e-6)
    sampled = StandIn(CONFIG, HISTORY).sample(homes, queries, 50, jax.random.key(0), config=CONFIG)
    hist = np.asarray(assign_samples(sampled, homes, queries, CONFIG))
    np.testing.assert_allclose(hist.sum(-1), 1.0, atol=1e-6)  # on their receptacles, none off
    assert np.all(hist[exact == 0] == 0)


# --------------------------------------------------------------------------- navigation


def _expected_travel(order, q, distance, start):
    total, mass, here = 0.0, 1.0, None
    for r in order:
        total += mass * (start[r] if here is None else distance[here, r])
        mass -= q[r]
        here = r
    return total


def test_the_start_is_room_zero_and_distances_are_geodesic(homes, geometry):
    start, start_distance = (np.asarray(a) for a in geometry)
    box = np.asarray(homes.room_box)[:, 0]
    np.testing.assert_allclose(start, (box[:, :2] + box[:, 2:]) / 2)
    centres = np.asarray(homes.receptacle_box)[..., :2]
    straight = np.linalg.norm(centres - start[:, None], axis=-1)
    valid = np.asarray(homes.receptacle_valid)
    in_room = valid & (np.asarray(homes.receptacle_room) == 0)
    assert np.all(start_distance[valid] >= straight[valid] - 1e-4)
    np.testing.assert_allclose(start_distance[in_room], straight[in_room], rtol=1e-5)
    assert np.any(start_distance[valid & ~in_room] > straight[valid & ~in_room] + 0.1)


def test_the_dynamic_programme_is_brute_force(homes, queries, exact, geometry, monkeypatch):
    _, start_distance = geometry
    orders, values = nav.optimal_orders(exact, homes, queries, start_distance)
    allowed = np.asarray(pr.allowed_slots(homes, queries))
    distance, start = np.asarray(homes.receptacle_distance), np.asarray(start_distance)
    checked = 0
    for e, j in itertools.product(*map(range, allowed.shape[:2])):
        idx = np.nonzero(allowed[e, j])[0]
        order = orders[e, j][orders[e, j] >= 0]
        assert sorted(order.tolist()) == idx.tolist()  # every allowed receptacle, once
        ours = _expected_travel(order, exact[e, j], distance[e], start[e])
        np.testing.assert_allclose(ours, values[e, j], rtol=1e-5)
        if len(idx) <= 7:
            best = min(_expected_travel(p, exact[e, j], distance[e], start[e])
                       for p in itertools.permutations(idx))
            np.testing.assert_allclose(values[e, j], best, rtol=1e-5)
            checked += len(idx) >= 3
    assert checked >= 3
    uniform = np.asarray(pr.uniform_prior(homes, queries))
    for policy in nav.POLICIES:  # no order beats the Bayes-optimal searcher
        o = nav.visit_orders(policy, uniform, homes, queries, start_distance)
        out = nav.walk_orders(jnp.asarray(o), homes, queries, exact, start_distance)
        assert np.all(np.asarray(out["expected_travel"]) >= values * (1 - 1e-5) - 1e-5)
    monkeypatch.setattr(nav, "MAX_OPTIMAL_RECEPTACLES", 2)  # objects here allow 3 or more
    with pytest.raises(ValueError, match="at most 2 allowed receptacles"):
        nav.optimal_orders(uniform, homes, queries, start_distance)


def test_orders_and_walks_by_hand(homes, queries, exact, geometry):
    _, start_distance = geometry
    allowed = np.asarray(pr.allowed_slots(homes, queries))
    start, distance = np.asarray(start_distance), np.asarray(homes.receptacle_distance)
    nearest = np.asarray(nav.visit_orders("nearest", exact, homes, queries, start_distance))
    probable = np.asarray(nav.visit_orders("most-probable", exact, homes, queries,
                                           start_distance))
    target = np.asarray(pr.receptacle_at(homes, queries.tau_q, queries.object_index))
    out = {k: np.asarray(v) for k, v in nav.walk_orders(
        jnp.asarray(probable), homes, queries, exact, start_distance, budget=10).items()}
    for e, j in itertools.product(*map(range, allowed.shape[:2])):
        idx = np.nonzero(allowed[e, j])[0]
        first = nearest[e, j, 0]
        assert start[e, first] == start[e, idx].min()
        order = probable[e, j][probable[e, j] >= 0]
        assert np.all(np.diff(exact[e, j][order]) <= 1e-6)  # decreasing belief
        looks = int(np.nonzero(order == target[e, j])[0][0]) + 1
        legs = [start[e, order[0]]] + [distance[e, a, b] for a, b in itertools.pairwise(order)]
        assert out["looks"][e, j] == looks
        np.testing.assert_allclose(out["travel"][e, j], sum(legs[:looks]), rtol=1e-5)
        np.testing.assert_allclose(out["expected_travel"][e, j], _expected_travel(
            order, exact[e, j], distance[e], start[e]), rtol=1e-5)
        np.testing.assert_allclose(out["shortest"][e, j], start[e, target[e, j]])
    metrics = nav.episode_metrics(out, 10)
    np.testing.assert_array_equal(metrics["sr@1"], out["looks"] == 1)
    np.testing.assert_allclose(metrics["spl@1"], metrics["sr@1"], atol=1e-6)  # geodesic walks
    np.testing.assert_allclose(metrics["steps"], out["travel"] / nav.STEP_LENGTH, rtol=1e-6)
    np.testing.assert_allclose(metrics["msr"], metrics["success_at"].mean(-1))
    assert np.all(np.diff(metrics["success_at"], axis=-1) >= 0)


# --------------------------------------------------------------------------- the evaluation


@pytest.fixture(scope="module")
def results():
    return ev.run_evaluation(CONFIG, num_homes=6, num_queries=3, history=HISTORY,
                             num_samples=10, horizons=HORIZONS, model=StandIn(CONFIG, HISTORY),
                             model_info="stand-in")


def test_the_evaluation_scores_every_row_by_regime_and_horizon(results):
    posterior, navigation = results["posterior"], results["navigation"]
    assert list(posterior)[:3] == [ev.EXACT, "exact, H = 1 (the map alone)",
                                   "oracle samples (N = 10)"]
    assert {"FlowMaps", "FlowMaps samples (N = 10)", "uniform over allowed"} <= set(posterior)
    regimes = [r for r, n in results["protocol"]["queries_by_regime"].items() if n]
    for name, row in posterior.items():
        metrics = row["metrics"]
        assert ("kl" in metrics) == (not row["samples"]), name
        for m, summary in metrics.items():
            assert list(summary["by_regime"]) == regimes, (name, m)
            assert set(summary["by_horizon"]) <= {str(h) for h in HORIZONS}
    for name in (ev.EXACT, "FlowMaps"):  # the stand-in is the exact posterior
        overall = {m: s["overall"]["mean"] for m, s in posterior[name]["metrics"].items()}
        assert overall == pytest.approx({"kl": 0.0, "tv": 0.0, "top1": 1.0, "rank_cost": 1.0},
                                        abs=1e-5)
    assert posterior["last-seen (ε = 0.01)"]["metrics"]["kl"]["overall"]["mean"] > 0.1
    fit = results["protocol"]["count_table"]
    assert fit["bandwidth"] in pr.BANDWIDTHS and fit["stay"] == pytest.approx(
        min(pr.STAYS, key=lambda s: abs(s - fit["stay"])))
    learned = [pr.COUNT_ROW, pr.STAY_ROW, f"frequency prior (H = {HISTORY})",
               "last-seen (ε = 0.01)", "uniform over allowed"]
    assert list(posterior)[-5:] == learned
    best = results["best_reference"]
    assert list(best["posterior"]) == ["overall", *regimes]
    for key, row in best["posterior"].items():  # the least KL among the learned rows
        kl = {n: posterior[n]["metrics"]["kl"]["overall" if key == "overall" else "by_regime"]
              for n in learned}
        kl = {n: v["mean"] if key == "overall" else v[key]["mean"] for n, v in kl.items()}
        assert row == {"row": min(kl, key=kl.get), "kl": min(kl.values())}
    assert set(best["navigation"]) == {"overall", *regimes}
    assert all(b["row"] == ev.NEAREST or b["row"].rsplit(", ", 1)[0] in learned
               for b in best["navigation"].values())
    assert {f"FlowMaps, {p}" for p in ev.NAV_POLICIES} | {ev.NEAREST} <= set(navigation)
    for name, row in navigation.items():
        ratio = row["travel_ratio"]["overall"]
        assert ratio >= 1 - 1e-4, name  # no searcher beats the Bayes-optimal one
        sr = [row["metrics"][f"sr@{k}"]["overall"]["mean"] for k in nav.SR_LOOKS]
        assert sr == sorted(sr) and np.all(np.diff(row["success_at"]) >= 0), name
        assert row["metrics"]["msr"]["overall"]["mean"] == pytest.approx(
            np.mean(row["success_at"]), abs=1e-4)
    for name in (f"{ev.EXACT}, optimal", "FlowMaps, optimal"):
        assert navigation[name]["travel_ratio"]["overall"] == pytest.approx(1.0, abs=1e-4)
        assert all(v == pytest.approx(1.0, abs=1e-4)
                   for v in navigation[name]["travel_ratio"]["by_regime"].values())
    uniform = navigation["uniform over allowed, most-probable"]["metrics"]
    nearest = navigation[ev.NEAREST]["metrics"]
    assert uniform["steps"]["overall"] == nearest["steps"]["overall"]  # ties go to the nearest


@pytest.mark.parametrize("kwargs, named", [
    ({"num_homes": 0}, "--num-envs"), ({"num_queries": 0}, "--queries"),
    ({"horizons": (1, 200)}, "--horizons"), ({"history": 191}, "--history"),
    ({"num_samples": -1}, "--samples"), ({"budget": 5}, "--budget"),
    ({"seed": -1}, "--seed")])
def test_bad_arguments_are_value_errors_naming_them(kwargs, named):
    with pytest.raises(ValueError, match=named):
        ev.run_evaluation(CONFIG, **{"history": HISTORY, "horizons": HORIZONS, **kwargs})


def _homes_cli(monkeypatch):
    """The evaluate and search commands with a stand-in homes model (the exact posterior)."""
    from flowmaps_jax.evaluation import cli as evaluate_cli
    from flowmaps_jax.search import cli as search_cli

    monkeypatch.setattr(evaluate_cli, "stored_run",  # both commands read it through
                        lambda spec, which: ("flowmaps-homes", {}))  # evaluate's run_for_world
    monkeypatch.setattr(ev, "load_model",
                        lambda source, which="best": StandIn(HomesConfig(), 24))
    return evaluate_cli.main, search_cli.main


@pytest.mark.slow  # end to end: pytest -m slow (tests/conftest.py)
def test_evaluate_and_search_run_the_homes_protocol_for_a_homes_model(tmp_path, monkeypatch,
                                                                       capsys):
    """One evaluate and one search command for every world: a homes model gets the homes
    posterior tables from evaluate and the navigation table from search, from the same
    queries."""
    evaluate, search = _homes_cli(monkeypatch)
    out = tmp_path / "eval"
    common = ["--out", str(out), "--num-envs", "4", "--queries", "2", "--history", "24",
              "--horizons", "1,6", "--checkpoint", "stand-in", "--no-progress"]
    assert evaluate([*common, "--samples", "10"]) == 0, capsys.readouterr()
    results = json.loads((out / "results.json").read_text())
    assert results["protocol"]["homes"] == 4 and results["protocol"]["model"] == "stand-in"
    assert "navigation" not in results and "FlowMaps" in results["posterior"]
    md = (out / "results.md").read_text()
    assert "| row | KL (nats) | TV | top-1 | rank cost |" in md and "### routine" in md
    assert "## Navigation" not in md and "### Best reference row per regime (by KL" in md
    assert "Count rows chosen on 32 training homes" in md
    assert (out / "rank_cost_by_horizon.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert search(common) == 0
    printed = capsys.readouterr().out
    found = json.loads((out / "search.json").read_text())
    assert "posterior" not in found and found["protocol"] == {**results["protocol"],
                                                              "samples": 100}
    assert found["navigation"]["FlowMaps, optimal"]["travel_ratio"]["overall"] == \
        pytest.approx(1.0, abs=1e-4)
    md = (out / "search.md").read_text()
    assert "| row | SR@1 | SR@5 | SR@10 | mSR | SPL@1 | mSPL | steps | E[travel] ÷ exact |" in md
    assert (out / "success_vs_looks.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "| nearest first |" in printed


@pytest.mark.parametrize("command, args, named", [
    (0, ["--regime", "weekly"], "--regime"), (0, ["--num-envs", "0"], "--num-envs"),
    (1, ["--horizons", "1,700"], "--horizons"), (0, ["--kl-draws", "8"], "--kl-draws"),
    (1, ["--p-miss", "0.1"], "--p-miss"), (0, ["--samples", "4,8"], "--samples"),
    (0, ["--baseline", "pretrained:mlp"], "--baseline")])
def test_the_homes_commands_name_a_bad_or_foreign_argument(command, args, named, tmp_path,
                                                            monkeypatch, capsys):
    main = _homes_cli(monkeypatch)[command]
    assert main(["--checkpoint", "stand-in", "--out", str(tmp_path / "x"), *args,
                 "--no-progress"]) == 2
    assert named in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


@pytest.mark.slow  # end to end: pytest -m slow (tests/conftest.py)
def test_the_homes_defaults_fit_the_model_and_write_beside_the_run(tmp_path, monkeypatch):
    """A model of 96-hour homes: the default history (at most half the hours) and horizons (those
    that fit after it) are its own, and without --out the files go to <checkpoint>/eval and
    <checkpoint>/search, as for a 2-D model (the end-of-run advice names no --out)."""
    evaluate, search = _homes_cli(monkeypatch)
    short = HomesConfig(num_hours=96)
    monkeypatch.setattr(ev, "load_model", lambda source, which="best": StandIn(short, 24))
    monkeypatch.chdir(tmp_path)
    common = ["--checkpoint", "run", "--num-envs", "2", "--queries", "2", "--no-progress"]
    assert evaluate([*common, "--samples", "4"]) == 0
    assert search(common) == 0
    protocol = json.loads((tmp_path / "run" / "eval" / "results.json").read_text())["protocol"]
    assert protocol["history"] == 48 and protocol["horizons"] == [1, 3, 6, 12, 24]
    assert (tmp_path / "run" / "search" / "search.md").is_file()


def test_a_missing_checkpoint_names_the_flag(tmp_path, capsys):
    from flowmaps_jax.evaluation.cli import main

    code = main(["--out", str(tmp_path / "x"), "--checkpoint", str(tmp_path / "nowhere"),
                 "--no-progress"])
    assert code == 2 and "--checkpoint" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()

