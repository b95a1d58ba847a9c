"""The search protocol in FlowSim worlds with habits (issue 18): ``--world`` / ``--history``.

In a world with habits, or with history H > 1, the search set's exact posterior is the one given
the last H observations, it carries each object's habit and two more reference rows, a model
reading several maps gets their tokens, and the report gains a section per habit. The paper's
world with H = 1 must stay the paper's protocol. Few environments: the mixed world's scenes are
generated once (12 environments × 3 objects = 36 episodes per row).
"""

from __future__ import annotations

import json
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from flowmaps_jax.flowsim import (
    HABIT_WORLDS,
    HABITS,
    FlowSimConfig,
    exact_posterior,
    generate,
    world_config,
)
from flowmaps_jax.flowsim.habits import (
    available_history,
    empirical_frequency,
    habit_family,
    history_posterior,
    observed_history,
)
from flowmaps_jax.flowsim.scenes import scene_tokens
from flowmaps_jax.search import cli, protocol, report
from flowmaps_jax.search import episodes as E
from flowmaps_jax.tokens import OBJECT

H = 8
NUM_ENVS = 12
HISTORY_SAMPLES = 840  # divisible by every observation count 1 … 8: exact visit frequencies
MIXED = world_config("mixed", FlowSimConfig(max_tokens=FlowSimConfig().num_furniture
                                            + FlowSimConfig().num_objects * H))


class Echo:
    """A stand-in model reading ``history`` maps: its samples are the boxes of every token of
    the queried object in the tokens it is given, in equal shares (with the maps of the last
    H observations: their empirical frequency; with one map: last-seen). It keeps the tokens;
    ``flowsim``: the config it was "trained" on (its max_tokens: the token slots it takes)."""

    kind = "echo"

    def __init__(self, history: int, name: str, flowsim: FlowSimConfig = MIXED):
        self.model = types.SimpleNamespace(history=history)
        self.name, self.flowsim = name, flowsim
        self.tokens = []

    def sample(self, tokens, queries, num_samples, key):
        self.tokens.append(tokens)
        boxes = np.asarray(tokens.boxes)
        match = ((np.asarray(queries.descriptor)[:, :, None]
                  == np.asarray(tokens.descriptor)[:, None])
                 & (np.asarray(tokens.kind) == OBJECT)[:, None] & np.asarray(tokens.mask)[:, None])
        out = np.zeros((*match.shape[:2], num_samples, 4), np.float32)
        for b, q in np.ndindex(*match.shape[:2]):
            index = np.flatnonzero(match[b, q])
            out[b, q] = boxes[b, index[np.arange(num_samples) % index.size]]
        return jnp.asarray(out)


@pytest.fixture(scope="module")
def mixed_scenes():
    return generate(jax.random.key(0), NUM_ENVS, MIXED)


@pytest.fixture(scope="module")
def mixed(mixed_scenes):
    """run_search on the mixed world with H = 8: (results, runs, search set, the two echoes)."""
    echoes = [Echo(1, "echo", FlowSimConfig()), Echo(H, "history echo")]  # 20 and 34 slots
    results, runs, search_set = protocol.run_search(
        echoes, mixed_scenes, MIXED, seed=3, num_samples=HISTORY_SAMPLES, times_per_env=1,
        history=H, progress=False)
    return results, runs, search_set, echoes


# --------------------------------------------------------------------------- the paper's world


def test_default_path_is_the_papers_protocol(small_scenes, flowsim_config):
    scenes = jax.tree_util.tree_map(lambda a: a[:NUM_ENVS], small_scenes)
    s = E.build_search_set(scenes, flowsim_config, jax.random.key(3))
    assert s.habit is None and s.extra_slots is None and s.history == 1
    assert not E.uses_history(flowsim_config, 1)
    rows = s.num_rows
    tau = np.broadcast_to(np.asarray(s.tau)[:, None], (rows, flowsim_config.num_objects))
    np.testing.assert_array_equal(  # bit for bit the one-observation posterior, as before
        np.asarray(s.slot_probs),
        np.asarray(exact_posterior(np.asarray(s.num_slots), np.asarray(s.slot_now),
                                   np.asarray(s.horizon), flowsim_config, tau=tau),
                   np.float32))
    assert set(protocol.episode_groups(s, flowsim_config)) == {"category", "horizon"}
    assert list(protocol.reference_priors(s)) == [protocol.EXACT_ROW, protocol.UNIFORM_ROW,
                                                  protocol.LAST_SEEN_ROW]
    results, _, _ = protocol.run_search([], scenes, flowsim_config, seed=3, times_per_env=1,
                                        policies=("greedy",), progress=False)
    assert set(results) == {"protocol", "rows", "figures", "seconds"}
    assert not {"world", "history", "habits"} & set(results["protocol"])
    assert "by_habit" not in results["rows"][protocol.EXACT_ROW]["policies"]["greedy"]["summary"]
    text = report.markdown_table(results)
    assert "By habit" not in text and "World:" not in text


def test_routine_world_with_a_history_is_the_one_observation_posterior(small_scenes,
                                                                        flowsim_config):
    """The routine is Markov: the last H observations say no more than the last one."""
    scenes = jax.tree_util.tree_map(lambda a: a[:NUM_ENVS], small_scenes)
    paper = E.build_search_set(scenes, flowsim_config, jax.random.key(3))
    history = E.build_search_set(scenes, flowsim_config, jax.random.key(3), history=H)
    np.testing.assert_array_equal(np.asarray(history.tau), np.asarray(paper.tau))  # same draws
    np.testing.assert_array_equal(np.asarray(history.tau_q), np.asarray(paper.tau_q))
    np.testing.assert_allclose(history.slot_probs, paper.slot_probs, atol=1e-5)
    assert history.history == H and set(np.asarray(history.habit).ravel()) == {0}
    assert list(history.extra_slots) == [E.EXACT_H1_ROW, E.empirical_row(H)]


# --------------------------------------------------------------------------- a mixed world


def test_mixed_set_is_exact_given_the_history(mixed_scenes, mixed):
    _, _, s, _ = mixed
    m, f = MIXED.num_objects, MIXED.num_furniture
    env = np.repeat(np.asarray(s.env), m)
    obj = np.tile(np.arange(m), s.num_rows)
    tau = np.repeat(np.asarray(s.tau), m)
    horizon = np.asarray(s.horizon).ravel()
    seen = available_history(tau, H)
    assert seen.min() < H  # some queries made before 8 maps exist
    want = history_posterior(mixed_scenes, MIXED, env, obj, tau, horizon, seen)
    np.testing.assert_allclose(np.asarray(s.slot_probs).reshape(-1, f), want, atol=1e-6)
    one = history_posterior(mixed_scenes, MIXED, env, obj, tau, horizon, 1)
    np.testing.assert_allclose(np.asarray(s.extra_slots[E.EXACT_H1_ROW]).reshape(-1, f), one,
                               atol=1e-6)
    observed, valid = observed_history(mixed_scenes, env, obj, tau, seen, max_history=H)
    np.testing.assert_allclose(np.asarray(s.extra_slots[E.empirical_row(H)]).reshape(-1, f),
                               empirical_frequency(observed, valid, f), atol=1e-6)
    assert not np.allclose(np.asarray(s.slot_probs).reshape(-1, f), one, atol=1e-3)
    np.testing.assert_array_equal(np.asarray(s.habit).ravel(), habit_family(mixed_scenes, env,
                                                                             obj))


def test_mixed_report_has_habit_sections_and_the_reference_rows(mixed, tmp_path):
    results, _, s, _ = mixed
    assert list(results["rows"]) == [
        protocol.EXACT_ROW, "echo (H = 1)", f"history echo (H = {H})", E.EXACT_H1_ROW,
        E.empirical_row(H), protocol.UNIFORM_ROW, protocol.LAST_SEEN_ROW, protocol.NEAREST_ROW]
    assert results["protocol"]["world"] == "mixed" and results["protocol"]["history"] == H
    groups = protocol.episode_groups(s, MIXED)
    assert set(np.unique(groups["habit"])) == set(HABITS)  # every habit has episodes here
    sections = results["habits"]
    assert list(sections) == list(HABITS)
    total = results["protocol"]["episodes"]
    assert sum(section["episodes"] for section in sections.values()) == total == 3 * NUM_ENVS
    for habit, section in sections.items():
        assert section["episodes"] == int(np.sum(groups["habit"] == habit))
        assert list(section["rows"]) == list(results["rows"])
        for policy in protocol.MAIN_POLICIES:
            exact = section["rows"][protocol.EXACT_ROW][policy]
            for part in ("ratio", "expected_ratio"):
                for score in ("looks", "travel", "spl"):
                    assert exact[part][score] == pytest.approx(1.0), (habit, policy, part)
            # the Bayes-optimal searcher's expected travel is the least of every row, per habit
            best = section["rows"][protocol.EXACT_ROW]["optimal"]["expected"]["travel"]["mean"]
            for name, parts in section["rows"].items():
                assert parts["optimal"]["expected"]["travel"]["mean"] >= best - 1e-3, name
                assert parts[policy]["summary"]["count"] == section["episodes"]
    text = report.markdown_table(results)
    assert "World: mixed" in text and f"last H = {H} observations" in text
    head, habits = text.split("\n## By habit")
    assert "## optimal expected travel (exact DP)" in head  # the overall tables come first
    habits = habits.split("\n## By horizon")[0]
    for habit, section in sections.items():
        assert f"### habit: {habit} ({section['episodes']} of {total} episodes)" in habits
    for name in results["rows"]:
        assert habits.count(f"| {name} |") == len(HABITS) * len(protocol.MAIN_POLICIES)
    paths = report.write_report(results, tmp_path)
    written = json.loads(paths["json"].read_text())
    assert written["habits"]["dynamic"]["episodes"] == sections["dynamic"]["episodes"]
    # a one-habit world says so instead of repeating its tables under "By habit"
    one = report.markdown_table({**results, "habits": {"dynamic": sections["dynamic"]}})
    assert "Every object follows the dynamic habit" in one and "### habit:" not in one


def test_a_history_model_reads_history_tokens(mixed_scenes, mixed):
    """The H = 8 echo, given the maps of the last 8 observations, is the empirical frequency of
    the last 8; the H = 1 echo, given one map in the 20 token slots it takes (the search's
    tokens have 34), is last-seen first. With one map for both, the history echo would be
    last-seen too, and this test would fail."""
    _, runs, s, (echo, history_echo) = mixed
    got = history_echo.tokens[0]
    want = scene_tokens(mixed_scenes, s.env, s.tau, MIXED, history=H)
    np.testing.assert_array_equal(np.asarray(got.mask), np.asarray(want.mask))
    np.testing.assert_array_equal(np.asarray(got.boxes), np.asarray(want.boxes))
    assert np.asarray(echo.tokens[0].mask).sum() < np.asarray(got.mask).sum()
    assert echo.tokens[0].num_tokens == FlowSimConfig().max_tokens < got.num_tokens == 34

    def belief(name):
        return np.asarray(runs[name, "optimal"].episodes.belief)

    np.testing.assert_allclose(belief(f"history echo (H = {H})"), belief(E.empirical_row(H)),
                               atol=1e-5)
    np.testing.assert_allclose(belief("echo (H = 1)"), belief(protocol.LAST_SEEN_ROW), atol=1e-5)
    assert not np.allclose(belief(E.empirical_row(H)), belief(protocol.LAST_SEEN_ROW), atol=0.1)


# --------------------------------------------------------------------------- the CLI


def _model(flowsim: FlowSimConfig, history: int = 1):
    return types.SimpleNamespace(flowsim=flowsim, model=types.SimpleNamespace(history=history))


def test_search_world_defaults():
    paper = FlowSimConfig()
    config, history = cli.search_world([_model(paper)])
    assert config is paper and history == 1  # the paper's protocol
    config, history = cli.search_world([_model(paper)], "preferences")
    assert config.habits == HABIT_WORLDS["preferences"] and history == 8
    config, history = cli.search_world([_model(paper), _model(MIXED, H)])
    assert config.habits == paper.habits and history == H
    assert config.max_tokens == paper.num_furniture + paper.num_objects * H  # room for its maps
    assert cli.search_world([_model(paper)], "mixed", 3)[1] == 3
    assert cli.search_world([_model(paper)], "routine", 1)[1] == 1
    with pytest.raises(ValueError, match="--history"):
        cli.search_world([_model(paper)], "mixed", paper.num_timesteps + 1)
    with pytest.raises(ValueError, match="world"):
        cli.search_world([_model(paper)], "bogus")


def test_cli_rejects_a_bad_world_or_history_before_loading_models(capsys):
    assert cli.main(["--checkpoint", "pretrained:nothing", "--out", "x", "--world",
                     "bogus"]) == 2
    err = capsys.readouterr().err
    assert "--world" in err and "mixed" in err and "nothing" not in err
    assert cli.main(["--checkpoint", "pretrained:nothing", "--out", "x", "--history", "0"]) == 2
    assert "--history" in capsys.readouterr().err


def test_cli_searches_the_world_it_is_given(capsys, monkeypatch, tmp_path):
    seen = {}

    def stop(models, scenes, config, **kwargs):
        seen.update(config=config, history=kwargs["history"])
        raise ValueError("stopped before the search")

    monkeypatch.setattr(cli, "validation_split", lambda config, **k: seen.update(split=config))
    monkeypatch.setattr(cli.pr, "run_search", stop)
    assert cli.main(["--checkpoint", "pretrained:flowmaps", "--world", "mixed",
                     "--out", str(tmp_path / "search"), "--no-progress"]) == 2
    assert seen["config"].habits == HABIT_WORLDS["mixed"] and seen["split"] is seen["config"]
    assert seen["history"] == 8
    assert "mixed world (exact posterior given the last 8 observations)" in capsys.readouterr().out
