"""The count-table reference rows (issue 54 item 3): ``evaluation.priors.count_table_prior``,
``stay_prior`` and ``fit_count_table`` on tiny homes with planted laws (two weeks, 4 + 4
homes), and their rows in the recorded scores."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from flowmaps_jax.evaluation import priors as pr
from flowmaps_jax.flowsim.homes import HomesConfig, generate_homes
from flowmaps_jax.flowsim.homes.queries import HomesQueries, draw_queries

CONFIG = HomesConfig(regime="mixed", num_hours=14 * 24, objects_per_home=(4, 6))
HISTORY, HORIZONS = 168, (1, 3, 6, 12, 24)
CLASSES = (len(CONFIG.object_classes), len(CONFIG.receptacle_classes))


def _homes(seed: int):
    return generate_homes(jax.random.key(seed), CONFIG, 4)


def _plant(homes, law):
    """``homes`` whose object m of home e stands on ``law(t, cycle (n,), rng)`` at hour t."""
    rng = np.random.default_rng(0)
    rec = np.asarray(homes.receptacle).copy()
    cycle, num = np.asarray(homes.cycle), np.asarray(homes.num_allowed)
    for e, m in np.argwhere(np.asarray(homes.object_valid)):
        places = cycle[e, m, :num[e, m]]
        rec[e, :, m] = law(np.arange(rec.shape[1]), places, rng)
    return homes.replace(receptacle=jnp.asarray(rec, jnp.int32))


def _half_seen(homes, seed: int = 0):
    seen = np.random.default_rng(seed).random(homes.receptacle.shape) < 0.5
    return pr.seen_only(homes, jnp.asarray(seen))


def _fit_and_score(law, mask=True):
    """(fit on homes 0, {row: mean log score} on homes 1) of homes following ``law``."""
    parts = []
    for seed in (0, 1):
        full = _plant(_homes(seed), law)
        queries = draw_queries(jax.random.key(seed + 7), full, CONFIG, 16, history=HISTORY,
                               horizons=HORIZONS)
        target = pr.receptacle_at(full, queries.tau_q, queries.object_index)
        parts.append((_half_seen(full, seed) if mask else full, queries, target))
    homes, queries, target = parts[0]
    fit = pr.fit_count_table(homes, queries, target, jnp.ones(target.shape, bool), CLASSES,
                             HISTORY)
    homes, queries, target = parts[1]
    rows = {"count": pr.count_table_prior(fit, HISTORY), "stay": pr.stay_prior(fit, HISTORY),
            "frequency": pr.frequency_prior(HISTORY), "uniform": pr.uniform_prior}
    scores = {}
    for name, prior in rows.items():
        p = np.take_along_axis(np.asarray(prior(homes, queries)), np.asarray(target)[..., None],
                               -1)
        scores[name] = float(np.mean(np.log(np.maximum(p, 1e-9))))
    return fit, scores, parts[1]


def _routine(t, places, rng):
    """On its first allowed place at 7–9 h, on its second otherwise."""
    return np.where((t % 24 >= 7) & (t % 24 < 10), places[0], places[min(1, len(places) - 1)])


def test_the_count_table_recovers_an_hour_of_day_routine_and_beats_frequency():
    fit, scores, (homes, _, _) = _fit_and_score(_routine)
    assert float(fit.bandwidth) <= 2.0, fit.summary()
    assert scores["count"] > scores["frequency"] + 0.3, scores
    assert scores["count"] > -0.2, scores  # nearly certain of the realised receptacle
    cycle, num = np.asarray(homes.cycle), np.asarray(homes.num_allowed)
    e, m = (int(v) for v in np.argwhere(np.asarray(homes.object_valid) & (num >= 2))[0])
    tau = 10 * 24 + 5  # a Thursday, 5 h; queried at 8 h and 14 h
    q = HomesQueries(object_index=jnp.full((4, 2), m, jnp.int32),
                     tau=jnp.full((4, 2), tau, jnp.int32),
                     tau_q=jnp.asarray([[tau + 3, tau + 9]] * 4, jnp.int32))
    p = np.asarray(pr.count_table_prior(fit, HISTORY)(homes, q))[e]
    assert p[0].argmax() == cycle[e, m, 0] and p[1].argmax() == cycle[e, m, 1]
    assert p[0].max() > 0.8 and p[1].max() > 0.8


def test_the_stay_probability_is_recovered_from_a_known_stay_rate():
    def markov(t, places, rng, stay=0.9):
        out = np.empty(len(t), np.int64)
        out[0] = rng.choice(places)
        for h in range(1, len(t)):  # stays with 0.9, else a uniform allowed place
            out[h] = out[h - 1] if rng.random() < stay else rng.choice(places)
        return out

    fit, scores, _ = _fit_and_score(markov)
    assert 0.85 - 1e-6 <= float(fit.stay) <= 0.95 + 1e-6, fit.summary()  # the grid near 0.9
    assert scores["stay"] > scores["count"] + 0.1 and scores["stay"] > scores["frequency"]


@pytest.fixture(scope="module")
def mixed():
    homes = _homes(2)
    queries = draw_queries(jax.random.key(3), homes, CONFIG, 8, history=HISTORY,
                           horizons=HORIZONS)
    return _half_seen(homes), queries


def test_rows_are_distributions_on_the_allowed_receptacles(mixed):
    homes, queries = mixed
    target = pr.receptacle_at(homes, queries.tau_q, queries.object_index)
    fit = pr.fit_count_table(homes, queries, jnp.maximum(target, 0), target >= 0, CLASSES,
                             HISTORY)
    assert set(fit.summary()) == {"bandwidth", "alpha", "day_factor", "stay"}
    allowed = np.asarray(pr.allowed_slots(homes, queries))
    for prior in (pr.count_table_prior(fit, HISTORY), pr.stay_prior(fit, HISTORY)):
        p = np.asarray(prior(homes, queries))
        assert p.dtype == np.float32 and np.all(p >= 0) and np.all(p[~allowed] == 0)
        np.testing.assert_allclose(p.sum(-1), 1.0, atol=1e-5)


def test_the_counts_weigh_observed_hours_by_the_kernel_and_ignore_unobserved_ones(mixed):
    homes, queries = mixed
    fit = pr.CountFit(jnp.zeros((*CLASSES[:1], 24, CLASSES[1])), *map(jnp.float32,
                                                                       (2.0, 0.5, 0.2, 0.9)))
    p = np.asarray(pr.count_table_prior(fit, HISTORY)(homes, queries), np.float64)
    unseen = homes.replace(receptacle=jnp.full_like(homes.receptacle, -1))
    backoff = np.asarray(pr.count_table_prior(fit, HISTORY)(unseen, queries), np.float64)
    rec = np.asarray(homes.receptacle)
    obj, taus, taus_q = (np.asarray(a) for a in (queries.object_index, queries.tau,
                                                 queries.tau_q))
    for e, j in np.ndindex(p.shape[:2]):
        i, tau, tau_q = int(obj[e, j]), int(taus[e, j]), int(taus_q[e, j])
        counts = np.zeros(p.shape[-1])
        for h in range(max(0, tau - HISTORY + 1), tau + 1):
            d = abs(h - tau_q) % 24
            w = np.exp(-0.5 * (min(d, 24 - d) / 2.0) ** 2)
            w *= 1.0 if ((h // 24) % 7 >= 5) == ((tau_q // 24) % 7 >= 5) else 0.2
            if rec[e, h, i] >= 0:  # an unobserved hour counts for nothing
                counts[rec[e, h, i]] += w
        expected = counts + 0.5 * backoff[e, j]
        np.testing.assert_allclose(p[e, j], expected / expected.sum(), atol=1e-5)
    stay = np.asarray(pr.stay_prior(fit, HISTORY)(unseen, queries))
    np.testing.assert_allclose(stay, backoff, atol=1e-6)  # never seen: the count table


def test_bad_arguments_name_themselves(mixed):
    homes, queries = mixed
    with pytest.raises(ValueError, match="fit"):
        pr.count_table_prior(0.5)
    with pytest.raises(ValueError, match="history"):
        pr.stay_prior(pr.CountFit(*[jnp.float32(0)] * 5), 0)
    ok = jnp.zeros(queries.tau.shape, bool)
    with pytest.raises(ValueError, match="num_classes"):
        pr.fit_count_table(homes, queries, queries.tau, ok, (3,))
    with pytest.raises(ValueError, match="target"):
        pr.fit_count_table(homes, queries, queries.tau[:, :1], ok, CLASSES)


def test_recorded_rows_ignore_unobserved_and_held_out_hours(mixed):
    """``realised``: the count rows read only the observed hours (whatever the world holds at
    the others), and their fit only the training part's hours before its time cut."""
    from flowmaps_jax.evaluation import realised
    from flowmaps_jax.worlds.recorded import RecordedHomes

    homes, queries = mixed
    full = _homes(2)
    observed = homes.receptacle >= 0
    e, t = observed.shape[:2]
    data = RecordedHomes(homes=full, observed=observed, start=jnp.zeros(e, jnp.int32),
                         stop=jnp.full(e, t // 2, jnp.int32))
    scrambled = full.replace(receptacle=jnp.where(  # other places where nothing was seen
        observed, full.receptacle, jnp.roll(full.receptacle, 5, axis=1)))
    other = data.replace(homes=scrambled)
    fit = realised.fit_counts(data, CONFIG, HISTORY, 24)
    late = jnp.arange(t)[None, :, None] >= t // 2  # after the cut: anything at all
    cut = other.replace(homes=scrambled.replace(receptacle=jnp.where(
        late & (scrambled.receptacle >= 0), scrambled.receptacle[:, ::-1], scrambled.receptacle)))
    assert realised.fit_counts(cut, CONFIG, HISTORY, 24).summary() == fit.summary()
    np.testing.assert_array_equal(realised.fit_counts(cut, CONFIG, HISTORY, 24).classes,
                                  fit.classes)
    rows = realised.reference_rows(data, queries, HISTORY, fit)
    again = realised.reference_rows(other, queries, HISTORY, fit)
    for name in (pr.COUNT_ROW, pr.STAY_ROW):
        np.testing.assert_array_equal(rows[name], again[name])
    shown = realised.reference_rows(data.replace(observed=jnp.ones_like(observed)), queries,
                                    HISTORY, fit)
    assert not np.allclose(shown[pr.COUNT_ROW], rows[pr.COUNT_ROW])  # the mask matters


def test_the_recorded_report_names_the_best_reference_row_per_object_class(mixed):
    """``realised.run_evaluation`` (a stand-in model: uniform) on data the run did not train
    on: the count rows are fitted on the evaluated environments and the report says so; the
    best learned row per object class is named, never the model."""
    from flowmaps_jax.evaluation import realised
    from flowmaps_jax.worlds.recorded import RecordedHomes

    class Uniform:
        homes, model = CONFIG, type("Model", (), {"history": HISTORY})

        def probabilities(self, homes, queries, config, observed=None, not_at=None):
            return pr.uniform_prior(homes, queries)

    homes, _ = mixed
    e, t = homes.receptacle.shape[:2]
    data = RecordedHomes(homes=_homes(2), observed=homes.receptacle >= 0,
                         start=jnp.zeros(e, jnp.int32), stop=jnp.full(e, t, jnp.int32))
    results = realised.run_evaluation(Uniform(), data, num_queries=6, seed=0,
                                      parts=("posterior", "navigation"), progress=False)
    assert results["protocol"]["count_table"]["fitted_on"].startswith("the evaluated")
    posterior = results["posterior"]
    assert list(posterior) == ["FlowMaps", realised.UNIFORM, realised.LAST_SEEN,
                               realised.FREQUENCY, pr.COUNT_ROW, pr.STAY_ROW]
    classes = posterior["FlowMaps"]["metrics"]["log_score"]["by_object_class"]
    for part, metric in (("posterior", "log_score"), ("navigation", "sr@1")):
        best = results["best_reference"][part]
        assert list(best) == ["overall", *classes]
        table = results[part]
        for key, row in best.items():
            scores = {n: (r["metrics"][metric]["overall"] if key == "overall" else
                          r["metrics"][metric]["by_object_class"][key])["mean"]
                      for n, r in table.items() if not n.startswith("FlowMaps")}
            assert row == {"row": max(scores, key=scores.get), metric: max(scores.values())}
    text = realised.markdown(results)
    assert "Best reference row per object class (by log score" in text
    assert "Count rows chosen on the evaluated environments themselves" in text
