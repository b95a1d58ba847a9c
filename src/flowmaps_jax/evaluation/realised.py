"""Scores without an exact posterior: a homes-network model on a recorded dataset, against the
realised (observed) receptacle of every query (the protocol: docs/protocol.md).

Queries (:func:`realised_queries`): on the held-out part of the data (every environment of a
dataset the run was not trained on), ``num_queries`` per environment, among the observed
(object, hour) pairs at τ_q; the object may be unseen at τ. Rows: the model and the reference
rows of :mod:`flowmaps_jax.evaluation.priors` (count-table parameters from :func:`fit_counts`),
plus the exact rows of :mod:`flowmaps_jax.worlds.recorded_references` when every environment
comes from ``from-homes``. Scores: log score (nats, p floored at ``P_FLOOR``), top-1, top-5,
rank (ties in expectation), reliability in ``BINS`` bins and ECE; the best learned reference
row per object class is named. Navigation (``search``): :mod:`flowmaps_jax.navigation.navigation`
with each row as the belief, from :func:`start_distance`, over the recorded walking distances.
"""

from __future__ import annotations

import argparse
import functools
import json
import pathlib
import shlex
import sys
import time
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.atomic_files import make_output_dir, save_figure, write_file
from flowmaps_jax.evaluation import priors as pr
from flowmaps_jax.evaluation.receptacle_scores import best_lines, best_rows, stats, summarise
from flowmaps_jax.flowsim.homes.queries import DEFAULT_HORIZONS, HomesQueries
from flowmaps_jax.navigation import navigation as nav
from flowmaps_jax.recorded.format import content_digest
from flowmaps_jax.store.pretrained import PREFIX as PRETRAINED_PREFIX
from flowmaps_jax.validation import check_int, check_output_dir, check_seed, prefix_errors
from flowmaps_jax.worlds import recorded as rw
from flowmaps_jax.worlds import recorded_references as references

EXIT_USAGE, EXIT_WRITE_FAILED = 2, 74
START = "the receptacle nearest all the others (smallest sum of walking distances)"
EVAL_SEED = 35_000_047
"""Seed of the evaluation queries (with ``--seed`` folded in)."""
DEFAULT_QUERIES = 32
"""Queries per environment."""
P_FLOOR = 1e-9
BINS = 10
TOP_K = 5
METRICS = ("log_score", "top1", "top5", "rank")
METRIC_NAMES = {"log_score": "log score (nats)", "top1": "top-1", "top5": "top-5",
                "rank": "rank"}
MODEL_ROW, UNIFORM, LAST_SEEN, FREQUENCY = ("FlowMaps", "uniform over allowed", "last seen",
                                            "frequency prior")
RULED_OUT = "Negative evidence: log of the mass off the receptacles ruled out at τ_q"
FIT_SEED, FIT_QUERIES = 35_000_048, 64
"""The count rows' fitting queries: ``FIT_QUERIES`` per environment, seeded apart."""
REPORT = {"posterior": ("results", "reliability.png"),
          "navigation": ("search", "success_vs_looks.png")}


# --------------------------------------------------------------------------- queries


@functools.partial(jax.jit, static_argnames="max_horizon")
def _draw(keys, data, max_horizon):
    """One query per environment for every key, one key at a time (memory: one draw's)."""
    return jax.lax.map(lambda k: rw.draw_queries(k, data, 1, max_horizon, 1.0), keys)


def realised_queries(key, data: rw.RecordedHomes, num_queries: int, max_horizon: int
                     ) -> tuple[HomesQueries, np.ndarray]:
    """(queries (E, Q), valid (E, Q) bool): Q queries per environment, each its own τ (see the
    module docstring); ``valid`` False where an environment had no observed target to draw."""
    keys = jax.random.split(key, num_queries)
    q = _draw(keys, data, max_horizon)  # fields (Q, E, 1)
    queries = jax.tree.map(lambda a: jnp.transpose(a[..., 0]), q)
    ok = np.asarray(rw.target_hours(data))
    e = np.arange(ok.shape[0])[:, None]
    valid = ok[e, np.asarray(queries.tau_q), np.asarray(queries.object_index)]
    return queries, valid


# --------------------------------------------------------------------------- the rows


def model_probabilities(predictor, data: rw.RecordedHomes, queries: HomesQueries) -> np.ndarray:
    """(E, Q, R) the model's receptacle weights: the Predictor's own call, with the data's
    observation mask."""
    return np.asarray(predictor.probabilities(data.homes, queries, predictor.homes,
                                              observed=data.observed, not_at=data.not_at))


def ruled_out_scores(key, predictor, data: rw.RecordedHomes, num_queries: int, max_horizon: int,
                     fit: pr.CountFit | None) -> dict | None:
    """Negative evidence as a realised outcome: Q queries per environment among the (object,
    τ_q) pairs unseen at τ_q but looked for on some allowed receptacles then (drawn as
    :func:`realised_queries` draws the observed ones); per row, the log of the mass the row
    puts off those receptacles (floored at ``P_FLOOR``): {row: stats}, None without such
    pairs."""
    if data.not_at is None:
        return None
    looked = ~data.observed & jnp.any(data.not_at & data.homes.object_allowed[:, None], -1)
    queries, valid = realised_queries(key, data.replace(observed=looked), num_queries,
                                      max_horizon)
    if not valid.any():
        return None
    e = np.arange(valid.shape[0])[:, None]
    ruled = np.asarray(data.not_at)[e, np.asarray(queries.tau_q), np.asarray(queries.object_index)]
    return {name: stats(np.log(np.maximum(1.0 - np.sum(np.where(ruled, p, 0.0), -1),
                                          P_FLOOR))[valid])
            for name, p in row_probabilities(predictor, data, queries, fit).items()}


def row_probabilities(predictor, data: rw.RecordedHomes, queries: HomesQueries,
                      fit: pr.CountFit | None = None) -> dict:
    """{row name: (E, Q, R)} of the model and the reference rows."""
    return {MODEL_ROW: model_probabilities(predictor, data, queries),
            **reference_rows(data, queries, predictor.model.history, fit)}


def fit_counts(data: rw.RecordedHomes, config, history: int, max_horizon: int) -> pr.CountFit:
    """The count rows' parameters chosen on ``data`` (its sightings before ``stop``) with
    ``FIT_QUERIES`` realised queries per environment."""
    queries, valid = realised_queries(jax.random.key(FIT_SEED), data, FIT_QUERIES, max_horizon)
    t = jnp.arange(data.observed.shape[1])[:, None]
    homes = pr.seen_only(data.homes, data.observed & (t < data.stop[:, None, None]))
    target = pr.receptacle_at(homes, queries.tau_q, queries.object_index)
    return pr.fit_count_table(homes, queries, jnp.maximum(target, 0),
                              jnp.asarray(valid) & (target >= 0), (
                                  len(config.object_classes), len(config.receptacle_classes)),
                              history)


def reference_rows(data: rw.RecordedHomes, queries: HomesQueries, history: int,
                   fit: pr.CountFit | None = None) -> dict:
    """{row name: (E, Q, R)} of uniform, last seen, the frequency prior over ``history``
    hours, and with ``fit`` the count table and last seen with a fitted stay. Last seen is
    uniform over the allowed receptacles for an object not yet seen at τ (the world's
    stand-in receptacle for it is no sighting)."""
    seen_only = pr.seen_only(data.homes, data.observed)  # unseen hours count for nothing
    uniform = np.asarray(pr.uniform_prior(data.homes, queries))
    observed = np.asarray(data.observed)  # (E, T, M)
    e = np.arange(observed.shape[0])[:, None]
    seen = np.cumsum(observed, axis=1)[e, np.asarray(queries.tau),
                                       np.asarray(queries.object_index)] > 0  # (E, Q)
    last_seen = np.asarray(pr.last_seen_prior()(data.homes, queries))
    counts = {} if fit is None else {
        pr.COUNT_ROW: np.asarray(pr.count_table_prior(fit, history)(seen_only, queries)),
        pr.STAY_ROW: np.asarray(pr.stay_prior(fit, history)(seen_only, queries))}
    return {UNIFORM: uniform,
            LAST_SEEN: np.where(seen[..., None], last_seen, uniform),
            FREQUENCY: np.asarray(pr.frequency_prior(history)(seen_only, queries)), **counts}


# --------------------------------------------------------------------------- scores


def realised_scores(p, target, allowed) -> dict[str, np.ndarray]:
    """Per query (E, Q): ``METRICS`` of probabilities ``p`` (E, Q, R) against the realised
    receptacle ``target`` (E, Q) among the ``allowed`` (E, Q, R) ones."""
    p = np.where(allowed, np.asarray(p, np.float64), 0.0)
    at = np.take_along_axis(p, target[..., None], -1)[..., 0]
    above = np.sum(allowed & (p > at[..., None]), -1)
    ties = np.sum(allowed & (p == at[..., None]), -1)  # the realised one among them
    # ties broken uniformly at random: its place is above + U{1 … ties}, in expectation
    return {"log_score": np.log(np.maximum(at, P_FLOOR)),
            "top1": np.where(above == 0, 1.0 / ties, 0.0),
            "top5": np.clip((TOP_K - above) / ties, 0.0, 1.0),
            "rank": above + (ties + 1) / 2.0}


def reliability(p, target, allowed, valid, bins: int = BINS) -> dict:
    """The reliability table: per probability bin, the pairs' count, mean probability and the
    frequency of the realised receptacle; ``ece`` the count-weighted mean |gap|."""
    p = np.asarray(p, np.float64)
    hit = np.arange(p.shape[-1]) == target[..., None]
    keep = allowed & valid[..., None]
    prob, outcome = p[keep], hit[keep]
    index = np.minimum((prob * bins).astype(int), bins - 1)
    table = []
    for b in range(bins):
        inside = index == b
        n = int(inside.sum())
        table.append({"low": b / bins, "high": (b + 1) / bins, "count": n,
                      "predicted": float(prob[inside].mean()) if n else None,
                      "realised": float(outcome[inside].mean()) if n else None})
    ece = sum(r["count"] * abs(r["predicted"] - r["realised"]) for r in table if r["count"])
    return {"bins": table, "ece": ece / max(1, len(prob))}


# --------------------------------------------------------------------------- the protocol


def _names(names) -> str:
    return ", ".join(names[:4]) + (f", ... ({len(names)} in all)" if len(names) > 4 else "")


def _trained_on(stored: dict, recorded) -> str:
    """Whether the run trained on any environment of ``recorded`` (by content), in words."""
    path, digest = stored.get("data"), stored.get("data_digest")
    if not stored:
        return "whether the model trained on any of them is not recorded with it"
    if not path:
        return "the run trained on generated FlowSim homes, none of them"
    try:
        original, original_digest = rw.load_data(path)
    except ValueError:
        original_digest = None
    if original_digest != digest:
        return (f"whether the run trained on any of them is not known: its data {path} is gone "
                f"or changed")
    train = rw.split(original, rw.split_of(stored))["environments"]["train"]
    ours = {content_digest(type(recorded)((original.environments[i],))) for i in train}
    seen = [e.name for e in recorded.environments
            if content_digest(type(recorded)((e,))) in ours]
    return (f"the run trained on {len(seen)} of them ({_names(seen)}): not held out"
            if seen else "the run trained on none of them")


def evaluation_part(recorded, config, stored: dict, data_path: str,
                    digest: str | None = None) -> tuple:
    """(RecordedHomes, what it is, its environments, the run's training part or None): the
    test part of the run's own split (:func:`flowmaps_jax.worlds.recorded.split`) when
    ``recorded`` (read from ``data_path``; ``digest``: its content digest) is the dataset the
    run trained on (its ``data_digest``, wherever it sits), else every environment of the data,
    ``what`` naming them and saying whether the run trained on any; the environments in the
    homes' order. ``ValueError`` if the run's own data folder no longer matches its digest."""
    stored_digest = stored.get("data_digest")
    folder = bool(stored.get("data")) and pathlib.Path(stored["data"]).resolve() == \
        pathlib.Path(data_path).resolve()
    digest = digest or (content_digest(recorded) if stored_digest else None)
    same = digest == stored_digest if stored_digest else folder
    if folder and not same:
        raise ValueError(f"{data_path} changed since the run trained on it (it no longer matches "
                         f"data_digest in the run's config.json): its split would now mix "
                         f"training environments into the test part; score a copy of the data "
                         f"the run trained on, or new environments in a folder of their own")
    if not same:
        return (rw.recorded_homes(recorded, config),
                f"all {len(recorded.environments)} environments ({_names(recorded.names())}); "
                f"{_trained_on(stored, recorded)}", tuple(recorded.environments), None)
    cfg_split = rw.split_of(stored)
    parts = rw.split(recorded, cfg_split)
    names = parts["environments"]
    what = (f"the run's held-out test part ({len(names['test'])} environments: "
            f"{_names([recorded.names()[i] for i in names['test']])}"
            + (f", and the last {cfg_split[2] / (1 + (not names['val'])):.0%} of the "
               "training environments' hours" if cfg_split[2] > 0 else "")
            + f"; split_seed={cfg_split[3]})")
    return (rw.part_of(recorded, config, parts, "test"), what,
            tuple(recorded.environments[i] for i in parts["test"][0]),
            rw.part_of(recorded, config, parts, "train"))


def start_distance(homes) -> jax.Array:
    """(E, R) walking distances from the searcher's start: the receptacle with the smallest sum
    of walking distances to the others (sums in mm; ties: the smallest box centre x, then y),
    whatever the order of the data's receptacle list."""
    d = np.asarray(homes.receptacle_distance, np.float64)
    valid = np.asarray(homes.receptacle_valid)
    total = np.where(valid, np.round((d * valid[:, None, :]).sum(-1), 3), np.inf)
    box = np.asarray(homes.receptacle_box)
    start = [np.lexsort((b[:, 1], b[:, 0], t))[0] for t, b in zip(total, box, strict=True)]
    return jnp.asarray(d[np.arange(len(d)), start], jnp.float32)


def run_evaluation(predictor, data: rw.RecordedHomes, *, num_queries: int, seed: int,
                   parts: Sequence[str], budget: int = nav.LOOK_BUDGET,
                   progress: bool = True, environments: Sequence | None = None,
                   train: rw.RecordedHomes | None = None) -> dict:
    """The realised-outcome results (JSON-able) of ``predictor`` on ``data``: ``posterior``
    (the scores and the reliability table of every row) and/or ``navigation``; the count rows
    fitted on ``train`` (None: on ``data`` itself, said in ``protocol["count_table"]``).

    environments: the recorded environments ``data`` was built from, in its order; when they
    are all FlowSim homes written by ``from-homes``, the exact reference rows
    (:mod:`flowmaps_jax.worlds.recorded_references`) are added after the model's, and
    ``protocol["references"]`` says in one line which (or why not)."""
    from tqdm.auto import tqdm

    begin = time.perf_counter()
    longest = int(np.max(np.asarray(data.stop)))  # the data's hours, not the model's
    horizons = [d for d in DEFAULT_HORIZONS if d <= longest - 1] or [1]
    key = jax.random.fold_in(jax.random.key(EVAL_SEED), seed)
    rows_steps = 6 * (("posterior" in parts) + ("navigation" in parts) * len(nav.POLICIES))
    bar = tqdm(total=2 + rows_steps, desc="realised", disable=not progress, leave=False)
    queries, valid = realised_queries(key, data, num_queries, max(horizons))
    if not valid.any():
        raise ValueError("--data: the evaluated environments hold no observed target")
    bar.update(1)
    homes = data.homes
    target = np.asarray(pr.receptacle_at(homes, queries.tau_q, queries.object_index))
    allowed = np.asarray(pr.allowed_slots(homes, queries))
    fit = fit_counts(data if train is None else train, predictor.homes,
                     predictor.model.history, max(horizons))
    beliefs = row_probabilities(predictor, data, queries, fit)
    learned = [name for name in beliefs if name != MODEL_ROW]
    if environments is None:
        exact, note, regime = ({}, "No exact reference rows: the data's environments were not "
                               "given.", None)
    else:
        exact, note, regime = references.reference_rows(environments, data, queries)
    beliefs = {MODEL_ROW: beliefs.pop(MODEL_ROW), **exact, **beliefs}
    bar.total += len(exact) * (rows_steps // 4)
    bar.refresh()
    bar.update(1)
    horizon = np.asarray(queries.horizon)

    groups = {"horizon": horizon[valid]}
    if regime is not None:  # FlowSim homes: their regimes are known
        groups["regime"] = regime[valid]
    classes = np.asarray([c.text for c in predictor.homes.object_classes])
    groups["object_class"] = classes[np.maximum(np.take_along_axis(
        np.asarray(homes.object_class), np.asarray(queries.object_index), 1), 0)][valid]

    def summary(values):
        return summarise(np.asarray(values)[valid], groups)

    results = {"protocol": {
        "eval_seed": EVAL_SEED, "seed": seed, "queries_per_environment": num_queries,
        "queries": int(valid.sum()), "environments": int(homes.num_homes),
        "horizons": horizons, "history": predictor.model.history, "p_floor": P_FLOOR,
        "bins": BINS, "start": START, "budget": budget, "references": note,
        "unseen_at_tau": stats(np.asarray(
            ~np.asarray(data.observed)[np.arange(homes.num_homes)[:, None],
                                       np.asarray(queries.tau),
                                       np.asarray(queries.object_index)])[valid] * 1.0),
        "count_table": {**fit.summary(), "fitted_on": (
            "the evaluated environments themselves (the run did not train on this data)"
            if train is None else f"the run's {train.num_homes} training environments")}},
        "num_allowed": stats(allowed.sum(-1)[valid])}
    best = results["best_reference"] = {}
    if "posterior" in parts:
        posterior = {}
        for name, p in beliefs.items():
            bar.set_postfix_str(name)
            scores = realised_scores(p, target, allowed)
            posterior[name] = {"metrics": {m: summary(scores[m]) for m in METRICS},
                               "reliability": reliability(p, target, allowed, valid)}
            bar.update(1)
        results["posterior"] = posterior
        ruled = ruled_out_scores(jax.random.fold_in(key, 1), predictor, data, num_queries,
                                 max(horizons), fit)
        if ruled:
            results["ruled_out"] = ruled
        best["posterior"] = best_rows(posterior, learned, "log_score", "object_class", True)
    if "navigation" in parts:
        start = start_distance(homes)
        realised = jax.nn.one_hot(target, allowed.shape[-1], dtype=jnp.float32)
        navigation = {}
        for name, p in beliefs.items():
            for policy in nav.POLICIES:
                if policy == "nearest" and name != MODEL_ROW:
                    bar.update(1)
                    continue  # nearest-first ignores the belief: one row
                label = "nearest first" if policy == "nearest" else f"{name}, {policy}"
                bar.set_postfix_str(label)
                orders = nav.visit_orders(policy, jnp.asarray(p, jnp.float32), homes, queries,
                                          start)
                outcome = nav.walk_orders(jnp.asarray(orders), homes, queries, realised, start,
                                          budget)
                metrics = nav.episode_metrics(outcome, budget)
                navigation[label] = {
                    "prior": None if policy == "nearest" else name, "policy": policy,
                    "metrics": {m: summary(metrics[m]) for m in nav.NAVIGATION_METRICS},
                    "success_at": np.round(metrics["success_at"][valid].mean(0), 5).tolist()}
                bar.update(1)
        results["navigation"] = navigation
        best["navigation"] = best_rows(navigation, [n for n, r in navigation.items() if r[
            "prior"] in learned or r["policy"] == "nearest"], "sr@1", "object_class", True)
    bar.close()
    results["seconds"] = round(time.perf_counter() - begin, 1)
    return results


# --------------------------------------------------------------------------- the report


def _pm(stat: dict | None, digits: int = 3) -> str:
    if not stat or stat.get("mean") is None:
        return "-"
    err = stat.get("stderr")
    return f"{stat['mean']:.{digits}f}" + ("" if err is None else f" ± {err:.{digits}f}")


def markdown(results: dict) -> str:
    """results.md / search.md: the realised-outcome tables."""
    p = results["protocol"]
    lines = ["# Realised-outcome scores on recorded data",
             "", f"Data: {results.get('data', '?')}: {results.get('part', '')}. "
             f"{p['queries']} queries ({p['queries_per_environment']} per environment on "
             f"{p['environments']} environments; horizons {p['horizons']} h; history "
             f"{p['history']} h; the object unseen at τ in {_pm(p['unseen_at_tau'], 2)} of "
             f"them), scored against the receptacle where the object was seen at τ_q. Seed "
             f"{p['seed']}.", ""]
    if p.get("references"):
        lines += [p["references"], ""]
    fit, best = p.get("count_table"), results.get("best_reference", {})
    if fit:
        lines += [f"Count rows chosen on {fit['fitted_on']}: bandwidth b = {fit['bandwidth']:g} h, "
                  f"back-off α = {fit['alpha']:g}, other-day-type factor "
                  f"{fit['day_factor']:.2g}, hourly stay s₁ = {fit['stay']:g}.", ""]
    if "posterior" in results:
        lines += ["| row | " + " | ".join(METRIC_NAMES[m] for m in METRICS) + " | ECE |",
                  "|---" * (len(METRICS) + 2) + "|"]
        for name, row in results["posterior"].items():
            lines.append(f"| {name} | " + " | ".join(
                _pm(row["metrics"][m]["overall"]) for m in METRICS)
                + f" | {row['reliability']['ece']:.3f} |")
        if results.get("ruled_out"):
            lines += ["", f"{RULED_OUT} (nats; {next(iter(results['ruled_out'].values()))['count']}"
                      " queries unseen at τ_q, with receptacles looked at and ruled out then):",
                      "", "| row | log mass off the ruled-out receptacles |", "|---|---|",
                      *(f"| {n} | {_pm(v)} |" for n, v in results["ruled_out"].items())]
        if best.get("posterior"):
            lines += ["", *best_lines(best["posterior"], "Best reference row per object class (by "
                                          "log score; the exact rows and the model excluded):",
                                          "log_score")[:-1]]
        lines += ["", "Log score by horizon (nats):", "",
                  "| row | " + " | ".join(f"Δ = {h} h" for h in p["horizons"]) + " |",
                  "|---" * (len(p["horizons"]) + 1) + "|"]
        for name, row in results["posterior"].items():
            by = row["metrics"]["log_score"]["by_horizon"]
            lines.append(f"| {name} | " + " | ".join(_pm(by.get(str(h))) for h in p["horizons"])
                         + " |")
        regimes = list(next(iter(results["posterior"].values()))["metrics"]["log_score"].get(
            "by_regime", {}))
        if regimes:  # FlowSim homes
            lines += ["", "Log score by the object's regime (FlowSim homes; nats):", "",
                      "| row | " + " | ".join(regimes) + " |", "|---" * (len(regimes) + 1) + "|"]
            for name, row in results["posterior"].items():
                by = row["metrics"]["log_score"]["by_regime"]
                lines.append(f"| {name} | " + " | ".join(_pm(by.get(r)) for r in regimes) + " |")
        lines += ["", "## Reliability (predicted probability vs realised frequency)", "",
                  "| bin | " + " | ".join(results["posterior"]) + " |",
                  "|---" * (len(results["posterior"]) + 1) + "|"]
        for b in range(p["bins"]):
            cells = []
            for row in results["posterior"].values():
                r = row["reliability"]["bins"][b]
                cells.append("-" if not r["count"] else
                             f"{r['predicted']:.2f} → {r['realised']:.2f} (n={r['count']})")
            low = results["posterior"][next(iter(results["posterior"]))]["reliability"][
                "bins"][b]
            lines.append(f"| {low['low']:.1f}–{low['high']:.1f} | " + " | ".join(cells) + " |")
    if "navigation" in results:
        cols = nav.NAVIGATION_METRICS
        lines += ["", "## Navigation (target: the realised receptacle)", "",
                  "| row | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
        for name, row in results["navigation"].items():
            lines.append(f"| {name} | " + " | ".join(
                _pm(row["metrics"][m]["overall"], 1 if m == "steps" else 3) for m in cols)
                + " |")
        if best.get("navigation"):
            lines += ["", *best_lines(best["navigation"], "Best reference row per object class (by "
                                          "SR@1; the exact rows and the model excluded):",
                                          "sr@1")[:-1]]
    lines += ["", f"Command: `{results.get('command', '')}`", ""]
    return "\n".join(lines)


def write_figure(results: dict, out: pathlib.Path, part: str) -> str:
    """``reliability.png`` (posterior) or ``success_vs_looks.png`` (navigation), written
    atomically and never through a symbolic link (``atomic_files.save_figure``)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 4.5))
    ax = fig.subplots()
    if part == "posterior":
        ax.plot([0, 1], [0, 1], color="grey", lw=0.8, ls="--")
        for name, row in results["posterior"].items():
            bins = [b for b in row["reliability"]["bins"] if b["count"]]
            ax.plot([b["predicted"] for b in bins], [b["realised"] for b in bins], marker="o",
                    label=f"{name} (ECE {row['reliability']['ece']:.3f})")
        ax.set_xlabel("predicted probability")
        ax.set_ylabel("realised frequency")
        ax.set_title("Reliability on recorded data")
    else:
        for name, row in results["navigation"].items():
            ax.plot(range(1, len(row["success_at"]) + 1), row["success_at"], label=name)
        ax.set_xlabel("looks")
        ax.set_ylabel("success rate")
        ax.set_title("Success vs looks (target: the realised receptacle)")
    ax.legend(fontsize=7)
    name = REPORT[part][1]
    save_figure(fig, out / name, name="--out file", dpi=110, bbox_inches="tight")
    return name


# --------------------------------------------------------------------------- command line


def run_command(part: str, prog: str, parser: argparse.ArgumentParser,
                args: argparse.Namespace, argv: Sequence[str] | None, stored: dict) -> int:
    """``evaluate`` (``part`` "posterior") or ``search`` ("navigation") of ``--checkpoint``
    (``stored``: its run config, {} for a pretrained model) on ``--data`` (default: the data
    the run trained on). Exit 0, 2 on bad input (one line), 74 on a failed write."""
    from flowmaps_jax.predictor import load_model

    stem, figure = REPORT[part]
    try:
        data_path = args.data or stored.get("data")
        if not data_path:
            raise ValueError("--data PATH is required (the recorded dataset to score on)")
        if args.out is None and str(args.checkpoint).startswith(PRETRAINED_PREFIX):
            raise ValueError("--out is required when --checkpoint is pretrained:NAME")
        default = pathlib.Path(args.checkpoint) / ("eval" if part == "posterior" else "search")
        out = pathlib.Path(check_output_dir(
            "--out", default if args.out is None else args.out,
            files=[f"{stem}.json", f"{stem}.md", *(() if args.no_figures else (figure,))]))
        queries = DEFAULT_QUERIES if getattr(args, "queries", None) is None else args.queries
        check_int("--queries", queries, 1)
        check_seed("--seed", args.seed)
        budget = check_int("--budget", getattr(args, "budget", nav.LOOK_BUDGET), 1)
        with prefix_errors(f"--checkpoint {args.checkpoint!r}: "):
            model = load_model(args.checkpoint, args.which)
        with prefix_errors("--data: "):
            recorded, digest = rw.load_data(data_path)
            data, what, environments, train = evaluation_part(recorded, model.homes, stored,
                                                              data_path, digest)
        if args.num_envs != parser.get_default("num_envs") and args.num_envs < data.num_homes:
            data = jax.tree.map(lambda a: a[:args.num_envs], data)
            environments = environments[:args.num_envs]
            what += f", the first {args.num_envs}"
        from flowmaps_jax.evaluation.receptacle_protocol import check_query_size

        check_query_size(model.homes, data.num_homes, queries, model.model.history,
                         budget=budget)  # as FlowSim homes, before XLA tries
        print(f"Recorded {part}: {data_path} ({what}), {queries} queries per environment, "
              f"FlowMaps {args.checkpoint} (step {model.step}) -> {out}", flush=True)
        results = run_evaluation(model, data, num_queries=queries, seed=args.seed,
                                 parts=(part,), budget=budget,
                                 progress=not args.no_progress, environments=environments,
                                 train=train)
    except ValueError as err:
        print(f"error: {' '.join(str(err).split())}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as err:
        print(f"error: --data {args.data}: {err.strerror or err}",
              file=sys.stderr)
        return EXIT_USAGE
    results["data"], results["part"] = str(data_path), what
    results["model"] = f"{args.checkpoint} (step {model.step})"
    results["command"] = f"{prog} " + shlex.join(sys.argv[1:] if argv is None else list(argv))
    try:
        make_output_dir("--out", out)
        results["figures"] = [] if args.no_figures else [write_figure(results, out, part)]
        text = markdown(results)
        paths = [write_file(out / f"{stem}.json", json.dumps(results, indent=1,
                                                             ensure_ascii=False),
                            name="--out file"),
                 write_file(out / f"{stem}.md", text, name="--out file")]
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as err:
        print(f"error: could not write the results into {out}: {err.strerror or err}",
              file=sys.stderr)
        return EXIT_WRITE_FAILED
    print(text.split("\n## Reliability")[0].split("\nCommand:")[0])
    print(f"wrote {', '.join(str(p) for p in paths)}"
          + "".join(f", {out / f}" for f in results["figures"])
          + f" ({results['seconds']:.0f} s)")
    return 0


evaluate = functools.partial(run_command, "posterior", "python -m flowmaps_jax.evaluate")
search = functools.partial(run_command, "navigation", "python -m flowmaps_jax.search")
"""The recorded world's commands (``hook(parser, args, argv, stored)``)."""
