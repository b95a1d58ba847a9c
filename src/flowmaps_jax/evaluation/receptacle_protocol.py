"""The homes protocol: the posterior and navigation tables of a FlowSim homes model
(docs/flowsim.md, "FlowMaps on homes").

The one ``evaluate`` and ``search`` commands run it for a homes model (:func:`run_command`):
``evaluate`` the posterior part, ``search`` the navigation part, from the same queries.
Evaluation homes are ``generate_homes(jax.random.key(EVAL_SEED), config, --homes)``, apart from
every training home; ``--queries`` per home (``homes.draw_queries``), seeded by ``--seed``; the
default ``--regime mixed``; every table also per regime. Rows (:mod:`.priors`): exact given
``--history`` hours, exact H = 1, oracle samples, the model (probabilities and ``--samples``
sampled boxes), the count table and last seen with a fitted stay (fitted on ``FIT_HOMES`` homes
of ``FIT_SEED``, :func:`fitted_counts`), frequency, last-seen, uniform; the best learned
reference row per regime is named. Navigation (:mod:`flowmaps_jax.navigation.navigation`):
every prior by the optimal and most-probable-first policies, plus nearest first. Exit status 0;
2 on a bad argument (one line naming it); 74 when the files cannot be written.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import pathlib
import shlex
import sys
import time
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.atomic_files import make_output_dir
from flowmaps_jax.evaluation import priors as pr
from flowmaps_jax.evaluation.receptacle_scores import (
    POSTERIOR_METRICS,
    assign_samples,
    best_rows,
    group_ids,
    posterior_scores,
    query_groups,
    stats,
    summarise,
)
from flowmaps_jax.flowsim.homes import REGIMES, HomesConfig, generate_homes
from flowmaps_jax.flowsim.homes.queries import DEFAULT_HORIZONS, check_horizons, draw_queries
from flowmaps_jax.flowsim.homes.rollout import homes_bytes_per_home
from flowmaps_jax.navigation import navigation as nav
from flowmaps_jax.resources import check_request_size
from flowmaps_jax.store.pretrained import PREFIX as PRETRAINED_PREFIX
from flowmaps_jax.validation import (
    check_choice,
    check_int,
    check_output_dir,
    check_seed,
    prefix_errors,
)

EVAL_SEED = 35_000_002
"""Seed of the evaluation homes (``jax.random.key(EVAL_SEED)``); training uses other seeds."""
DEFAULT_NUM_HOMES, DEFAULT_QUERIES, DEFAULT_SAMPLES = 200, 3, 100
REGIME_CHOICES = (*REGIMES, "mixed")
PARTS = ("posterior", "navigation")
DEFAULT_OUT = {"posterior": lambda checkpoint: pathlib.Path(checkpoint) / "eval",
               "navigation": lambda checkpoint: pathlib.Path(checkpoint) / "search"}
"""Where each part writes without ``--out`` (as the 2-D commands do): ``<checkpoint>/eval``,
``<checkpoint>/search``."""
REPORT_STEM = {"posterior": "results", "navigation": "search"}
"""The report files of each part: ``<stem>.json`` and ``<stem>.md``."""
FIGURE_OF = {"posterior": "rank_cost_by_horizon.png", "navigation": "success_vs_looks.png"}
EXACT, NEAREST = "exact posterior", "nearest first"
NAV_POLICIES = ("optimal", "most-probable")
EXIT_USAGE, EXIT_WRITE_FAILED = 2, 74
FIT_SEED, FIT_HOMES, FIT_QUERIES = 35_000_003, 32, 16
"""The count rows' training part: ``FIT_HOMES`` homes of ``jax.random.key(FIT_SEED)`` (neither
the evaluation's nor a run's), ``FIT_QUERIES`` queries each."""


@dataclasses.dataclass(frozen=True)
class Row:
    """A reference row: ``prior(homes, queries) -> (E, Q, R)``; ``samples``: a histogram (its
    KL is not reported); ``navigate``: also drives the navigation policies; ``baseline``: a
    reference learned from data (in the running for the best reference row)."""

    name: str
    prior: pr.Prior
    samples: bool = False
    navigate: bool = True
    baseline: bool = False


def evaluation_homes(config: HomesConfig, num_homes: int):
    """The fixed evaluation homes of ``config`` (``EVAL_SEED``)."""
    return generate_homes(jax.random.key(EVAL_SEED), config, num_homes)


def model_rows(model, config: HomesConfig, key, num_samples: int) -> list[Row]:
    """FlowMaps rows of ``model`` (``probabilities(homes, queries, config)`` and, with
    ``num_samples`` > 0, its sampled boxes assigned to receptacles)."""
    rows = [Row("FlowMaps", lambda h, q: jnp.asarray(model.probabilities(h, q, config)))]
    if num_samples:
        def sampled(h, q):
            return assign_samples(model.sample(h, q, num_samples, key, config=config), h, q,
                                  config)

        rows.append(Row(f"FlowMaps samples (N = {num_samples})", sampled, samples=True,
                        navigate=False))
    return rows


def fitted_counts(config: HomesConfig, history: int, horizons) -> pr.CountFit:
    """The count rows' parameters, fitted on the training homes (``FIT_SEED``) against where
    each queried object stands at τ_q."""
    homes = generate_homes(jax.random.key(FIT_SEED), config, FIT_HOMES)
    queries = draw_queries(jax.random.key(FIT_SEED + 1), homes, config, FIT_QUERIES,
                           history=history, horizons=horizons)
    target = pr.receptacle_at(homes, queries.tau_q, queries.object_index)
    return pr.fit_count_table(homes, queries, target, target >= 0, (
        len(config.object_classes), len(config.receptacle_classes)), history)


def reference_rows(config: HomesConfig, key, history: int, num_samples: int,
                   model=None, fit: pr.CountFit | None = None) -> list[Row]:
    """The rows in table order (see the module's docstring); the count rows with ``fit``."""
    rows = [Row(EXACT, pr.exact_prior(config, history))]
    if history > 1:
        rows.append(Row("exact, H = 1 (the map alone)", pr.exact_prior(config, 1),
                        navigate=False))
    if num_samples:
        rows.append(Row(f"oracle samples (N = {num_samples})",
                        pr.oracle_samples_prior(config, jax.random.fold_in(key, 1), num_samples,
                                                history), samples=True, navigate=False))
    if model is not None:
        rows += model_rows(model, config, jax.random.fold_in(key, 2), num_samples)
    if fit is not None:
        rows += [Row(pr.COUNT_ROW, pr.count_table_prior(fit, history), baseline=True),
                 Row(pr.STAY_ROW, pr.stay_prior(fit, history), baseline=True)]
    rows += [Row(f"frequency prior (H = {history})", pr.frequency_prior(history), baseline=True),
             Row(f"last-seen (ε = {pr.LAST_SEEN_EPS})", pr.last_seen_prior(), baseline=True),
             Row("uniform over allowed", pr.uniform_prior, baseline=True)]
    return rows


def _ratio_summary(expected: np.ndarray, optimal: np.ndarray, groups: dict) -> dict:
    """Mean expected travel over the Bayes-optimal searcher's, overall and per group."""
    def ratio(mask):
        return round(float(expected[mask].mean() / optimal[mask].mean()), 5) if mask.any() \
            and optimal[mask].mean() > 0 else None

    out = {"overall": ratio(np.ones(expected.shape, bool))}
    for name, labels in groups.items():
        out[f"by_{name}"] = {str(i): ratio(labels == i) for i in group_ids(name, labels)}
    return out


def check_query_size(config: HomesConfig, num_homes: int, num_queries: int, history: int,
                     num_samples: int = 0, budget: int = nav.LOOK_BUDGET) -> None:
    """``--num-envs`` x ``--queries`` through the memory budget, before any query is drawn:
    the homes, and per query its rows (history, samples, look orders) over the receptacles."""
    per_query = 4 * config.max_receptacles * (history + max(num_samples, 1) + 8 * budget)
    check_request_size(f"--num-envs {num_homes} x --queries {num_queries}",
                       num_homes * (homes_bytes_per_home(config) + num_queries * per_query))


def run_evaluation(config: HomesConfig, *, num_homes: int = DEFAULT_NUM_HOMES,
                   num_queries: int = DEFAULT_QUERIES, seed: int = 0,
                   history: int = pr.DEFAULT_HISTORY, num_samples: int = DEFAULT_SAMPLES,
                   horizons: Sequence[int] = DEFAULT_HORIZONS, budget: int = nav.LOOK_BUDGET,
                   model=None, model_info: str | None = None, progress: bool = False,
                   parts: Sequence[str] = PARTS) -> dict:
    """The posterior and navigation results (JSON-able) on the evaluation homes of ``config``;
    ``model``: anything with ``probabilities(homes, queries, config) -> (E, Q, R)`` (and
    optionally ``sample(key, homes, queries, config, n) -> (E, Q, n, 6)``). ``parts``: which of
    :data:`PARTS` to compute; each part's numbers are the same whether or not the other is
    computed (the queries and every row's key do not depend on it)."""
    from tqdm.auto import tqdm

    t = config.num_hours  # the messages name the command's flags
    num_homes = check_int("--num-envs", num_homes)  # homes
    num_queries = check_int("--queries", num_queries)
    seed = check_seed("--seed", seed)
    history = check_int("--history", history, 1, t - 2)
    num_samples = check_int("--samples", num_samples, 0)
    budget = check_int("--budget", budget, max(nav.SR_LOOKS))
    horizons = check_horizons("--horizons", horizons, t - history)
    check_query_size(config, num_homes, num_queries, history, num_samples, budget)
    begin = time.perf_counter()
    key = jax.random.key(seed)
    fit = fitted_counts(config, history, horizons)
    rows = reference_rows(config, key, history, num_samples, model, fit)
    baselines = [r.name for r in rows if r.baseline]
    navigated = [r for r in rows if r.navigate]
    if "posterior" not in parts:  # navigation alone: only the priors it drives
        rows = navigated
    plans = [(f"{r.name}, {policy}", r.name, policy) for r in navigated for policy in
             NAV_POLICIES] + [(NEAREST, None, "nearest")] if "navigation" in parts else []
    bar = tqdm(total=2 + len(rows) + len(plans),
               disable=not progress, desc="homes evaluation", unit="step")
    homes = evaluation_homes(config, num_homes)
    queries = draw_queries(jax.random.fold_in(key, 0), homes, config, num_queries,
                           history=history, horizons=horizons)
    groups = query_groups(homes, queries)
    allowed = pr.allowed_slots(homes, queries)
    _, start_distance = nav.start_points(homes, config)
    bar.update(1)
    beliefs, posterior = {}, {}
    for row in rows:
        bar.set_postfix_str(row.name)
        p = jax.block_until_ready(row.prior(homes, queries))
        beliefs[row.name] = p
        q = beliefs[EXACT]
        scores = posterior_scores(p, q, allowed)
        posterior[row.name] = {
            "samples": row.samples,
            "metrics": {m: summarise(np.asarray(scores[m]), groups) for m in POSTERIOR_METRICS
                        if not (row.samples and m == "kl")}}
        bar.update(1)
    exact = beliefs[EXACT]
    if plans:
        _, optimal_travel = nav.optimal_orders(exact, homes, queries, start_distance)
    bar.update(1)
    navigation = {}
    for name, prior_name, policy in plans:
        bar.set_postfix_str(name)
        belief = exact if prior_name is None else beliefs[prior_name]
        orders = nav.visit_orders(policy, belief, homes, queries, start_distance)
        outcome = nav.walk_orders(jnp.asarray(orders), homes, queries, exact, start_distance,
                                  budget)
        metrics = nav.episode_metrics(outcome, budget)
        expected = np.asarray(outcome["expected_travel"], np.float64)
        navigation[name] = {
            "prior": prior_name, "policy": policy,
            "metrics": {m: summarise(metrics[m], groups) for m in nav.NAVIGATION_METRICS},
            "expected_travel": summarise(expected, groups),
            "travel_ratio": _ratio_summary(expected, np.asarray(optimal_travel, np.float64),
                                           groups),
            "success_at": np.round(metrics["success_at"].reshape(-1, budget).mean(0),
                                   5).tolist()}
        bar.update(1)
    bar.close()
    counts = {r: int(np.sum(groups["regime"] == r)) for r in REGIMES}
    results = {
        "protocol": {
            "eval_seed": EVAL_SEED, "homes": num_homes, "queries_per_home": num_queries,
            "seed": seed, "regime": config.regime, "history": history, "samples": num_samples,
            "horizons": list(horizons), "budget": budget, "num_hours": config.num_hours,
            "queries_by_regime": counts, "step_length_m": nav.STEP_LENGTH,
            "last_seen_eps": pr.LAST_SEEN_EPS, "start": "centre of room 0",
            "model": model_info, "count_table": {
                **fit.summary(), "fitted_on": f"{FIT_HOMES} training homes (seed {FIT_SEED}) "
                f"x {FIT_QUERIES} queries"}},
        "num_allowed": stats(np.asarray(allowed).sum(-1))}
    best = results["best_reference"] = {}
    if "posterior" in parts:
        results["posterior"] = posterior
        best["posterior"] = best_rows(posterior, baselines, "kl", "regime", higher=False)
    if plans:
        results["navigation"] = navigation
        best["navigation"] = best_rows(navigation, [NEAREST, *(
            n for n, prior, _ in plans if prior in baselines)], "sr@1", "regime", higher=True)
        results["bayes_optimal_travel"] = summarise(np.asarray(optimal_travel, np.float64),
                                                    groups)
    results["seconds"] = round(time.perf_counter() - begin, 1)
    return results


# --------------------------------------------------------------------------- command line


def load_model(source: str, which: str = "best"):
    """The homes model ``source`` names (a run or checkpoint directory, or
    ``pretrained:NAME``) as a :class:`~flowmaps_jax.predictor.Predictor`; a missing or
    unreadable source is a ``ValueError`` naming ``--checkpoint``."""
    from flowmaps_jax.predictor import load_model as load_predictor

    with prefix_errors(f"--checkpoint {source!r}: "):
        return load_predictor(source, which)


def _one_count(samples) -> int:
    """``--samples`` as one count (evaluate parses a list of counts)."""
    counts = tuple(samples) if isinstance(samples, (list, tuple)) else (samples,)
    if len(counts) != 1:
        raise ValueError(f"--samples takes one count for a FlowSim homes model; got "
                         f"{','.join(map(str, counts))}")
    return counts[0]


def run_command(part: str, prog: str, parser: argparse.ArgumentParser,
                args: argparse.Namespace, argv: Sequence[str] | None, stored: dict) -> int:
    """The ``part`` (``"posterior"`` for ``evaluate``, ``"navigation"`` for ``search``) of the
    homes protocol for ``--checkpoint``, from the parsed ``args`` of ``prog``; without ``--out``
    the files go to :data:`DEFAULT_OUT` (a pretrained model needs ``--out``). Returns the exit
    code (0, 2 on a bad argument, 74 on a failed write), one line on stderr."""
    from flowmaps_jax.evaluation import receptacle_report as report

    stem, figure = REPORT_STEM[part], FIGURE_OF[part]
    try:
        if args.out is None and str(args.checkpoint).startswith(PRETRAINED_PREFIX):
            raise ValueError("--out is required when --checkpoint is pretrained:NAME")
        regime = check_choice("--regime", "mixed" if args.regime is None else args.regime,
                              REGIME_CHOICES)
        out = pathlib.Path(check_output_dir(  # and no link at the names it will write
            "--out", DEFAULT_OUT[part](args.checkpoint) if args.out is None else args.out,
            files=[f"{stem}.json", f"{stem}.md", *(() if args.no_figures else (figure,))]))
        samples = args.samples
        num_samples = DEFAULT_SAMPLES if samples == parser.get_default("samples") \
            else _one_count(samples)
        budget = getattr(args, "budget", nav.LOOK_BUDGET)
        model = load_model(args.checkpoint, args.which)
        config = dataclasses.replace(model.homes, regime=regime)
        info = args.checkpoint + ("" if model.step is None else f" (step {model.step})")
        queries = DEFAULT_QUERIES if args.queries is None else args.queries
        print(f"Homes {part}: {args.num_envs} homes x {queries} queries, regime {regime}, "
              f"FlowMaps {info} -> {out}", flush=True)
        # Defaults that fit the model's homes: a week of history (at most half of them), and
        # the default horizons that fit after it (the shipped model's: all of them).
        history = min(pr.DEFAULT_HISTORY, config.num_hours // 2) if args.history is None \
            else args.history
        horizons = args.horizons if args.horizons is not None else [
            d for d in DEFAULT_HORIZONS if d <= config.num_hours - history] or [1]
        results = run_evaluation(
            config, num_homes=args.num_envs, num_queries=queries, seed=args.seed,
            history=history, num_samples=num_samples, horizons=horizons,
            budget=budget, model=model, model_info=info, progress=not args.no_progress,
            parts=(part,))
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_USAGE
    results["command"] = f"{prog} " + shlex.join(sys.argv[1:] if argv is None else list(argv))
    try:
        make_output_dir("--out", out)
        results["figures"] = [] if args.no_figures else report.write_figures(results, out)
        paths = report.write_report(results, out, stem)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as err:
        print(f"error: could not write the results into {out}: {err.strerror or err}",
              file=sys.stderr)
        return EXIT_WRITE_FAILED
    print(report.navigation_table(results) if part == "navigation"
          else report.posterior_table(results))
    print(f"wrote {', '.join(str(p) for p in paths)}"
          + "".join(f", {out / f}" for f in results["figures"])
          + f" ({results['seconds']:.0f} s)")
    return 0


evaluate = functools.partial(run_command, "posterior", "python -m flowmaps_jax.evaluate")
search = functools.partial(run_command, "navigation", "python -m flowmaps_jax.search")
"""The homes world's commands (``hook(parser, args, argv, stored)``)."""


