"""``python -m flowmaps_jax.homes.evaluate``: the homes posterior and navigation tables.

    python -m flowmaps_jax.homes.evaluate --out runs/homes-eval [--checkpoint flowmaps-homes]

Evaluation homes are ``generate_homes(jax.random.key(EVAL_SEED), config, --homes)``: a fixed
set, the same for every run, apart from the training homes (which use other seeds). Each home
gets ``--queries`` queries (``homes.draw_queries``: a valid object, a horizon from
``--horizons``, τ leaving ``--history`` hours before it), seeded by ``--seed``. The default
``--regime mixed`` gives every object one of the four regimes; every table is also reported per
regime.

Rows (:mod:`.priors`): the exact posterior given the map and the last ``--history`` hours; the
same given the map alone (H = 1); oracle samples (``--samples`` draws from it); FlowMaps
(``--checkpoint``: its probabilities, and ``--samples`` sampled boxes assigned to receptacles);
the frequency prior; last-seen; uniform. Navigation (:mod:`.navigation`): every prior row
drives the Bayes-optimal-travel planner and most-probable-first, plus nearest first.

Writes ``results.md``, ``results.json`` and the figures ``success_vs_looks.png`` and
``rank_cost_by_horizon.png`` into ``--out``. Exit status 0; 2 on a bad argument (one line
naming it); 74 when the files cannot be written.
"""

from __future__ import annotations

import argparse
import dataclasses
import pathlib
import shlex
import sys
import time
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.flowsim.homes import REGIMES, HomesConfig, generate_homes
from flowmaps_jax.flowsim.homes.rollout import homes_bytes_per_home
from flowmaps_jax.homes import navigation as nav
from flowmaps_jax.homes import priors as pr
from flowmaps_jax.homes.queries import DEFAULT_HORIZONS, check_horizons, draw_queries
from flowmaps_jax.homes.scores import (
    POSTERIOR_METRICS,
    assign_samples,
    group_ids,
    posterior_scores,
    query_groups,
    stats,
    summarise,
)
from flowmaps_jax.validation import (
    check_choice,
    check_int,
    check_output_dir,
    check_request_size,
    check_seed,
    make_output_dir,
    prefix_errors,
)
from flowmaps_jax.validation.scalars import int_list

EVAL_SEED = 35_000_002
"""Seed of the evaluation homes (``jax.random.key(EVAL_SEED)``); training uses other seeds."""
DEFAULT_NUM_HOMES, DEFAULT_QUERIES, DEFAULT_SAMPLES = 200, 3, 100
REGIME_CHOICES = (*REGIMES, "mixed")
REPORT_FILES = ("results.json", "results.md")
FIGURES = ("success_vs_looks.png", "rank_cost_by_horizon.png")
EXACT, NEAREST = "exact posterior", "nearest first"
NAV_POLICIES = ("optimal", "most-probable")
EXIT_USAGE, EXIT_WRITE_FAILED = 2, 74


@dataclasses.dataclass(frozen=True)
class Row:
    """A reference row: ``prior(homes, queries) -> (E, Q, R)``; ``samples``: a histogram (its
    KL is not reported); ``navigate``: also drives the navigation policies."""

    name: str
    prior: pr.Prior
    samples: bool = False
    navigate: bool = True


def evaluation_homes(config: HomesConfig, num_homes: int):
    """The fixed evaluation homes of ``config`` (``EVAL_SEED``)."""
    return generate_homes(jax.random.key(EVAL_SEED), config, num_homes)


def model_rows(model, config: HomesConfig, key, num_samples: int) -> list[Row]:
    """FlowMaps rows of ``model`` (``probabilities(homes, queries, config)`` and, with
    ``num_samples`` > 0 and a ``sample`` method, its sampled boxes assigned to receptacles)."""
    rows = [Row("FlowMaps", lambda h, q: jnp.asarray(model.probabilities(h, q, config)))]
    if num_samples and hasattr(model, "sample"):
        def sampled(h, q):
            return assign_samples(model.sample(key, h, q, config, num_samples), h, q, config)

        rows.append(Row(f"FlowMaps samples (N = {num_samples})", sampled, samples=True,
                        navigate=False))
    return rows


def reference_rows(config: HomesConfig, key, history: int, num_samples: int,
                   model=None) -> list[Row]:
    """The rows in table order (see the module's docstring)."""
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
    rows += [Row(f"frequency prior (H = {history})", pr.frequency_prior(history)),
             Row(f"last-seen (ε = {pr.LAST_SEEN_EPS})", pr.last_seen_prior()),
             Row("uniform over allowed", pr.uniform_prior)]
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


def run_evaluation(config: HomesConfig, *, num_homes: int = DEFAULT_NUM_HOMES,
                   num_queries: int = DEFAULT_QUERIES, seed: int = 0,
                   history: int = pr.DEFAULT_HISTORY, num_samples: int = DEFAULT_SAMPLES,
                   horizons: Sequence[int] = DEFAULT_HORIZONS, budget: int = nav.LOOK_BUDGET,
                   model=None, model_info: str | None = None, progress: bool = False) -> dict:
    """The posterior and navigation results (JSON-able) on the evaluation homes of ``config``;
    ``model``: anything with ``probabilities(homes, queries, config) -> (E, Q, R)`` (and
    optionally ``sample(key, homes, queries, config, n) -> (E, Q, n, 6)``)."""
    from tqdm.auto import tqdm

    t = config.num_hours  # the messages name the command's flags
    num_homes = check_int("--homes", num_homes)
    num_queries = check_int("--queries", num_queries)
    seed = check_seed("--seed", seed)
    history = check_int("--history", history, 1, t - 2)
    num_samples = check_int("--samples", num_samples, 0)
    budget = check_int("--budget", budget, max(nav.SR_LOOKS))
    horizons = check_horizons("--horizons", horizons, t - history)
    per_query = 4 * config.max_receptacles * (history + max(num_samples, 1) + 8 * budget)
    check_request_size(f"--homes {num_homes} x --queries {num_queries}",
                       num_homes * (homes_bytes_per_home(config) + num_queries * per_query))
    begin = time.perf_counter()
    key = jax.random.key(seed)
    rows = reference_rows(config, key, history, num_samples, model)
    navigated = [r for r in rows if r.navigate]
    bar = tqdm(total=2 + len(rows) + len(navigated) * len(NAV_POLICIES) + 1,
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
    _, optimal_travel = nav.optimal_orders(exact, homes, queries, start_distance)
    bar.update(1)
    navigation = {}
    plans = [(f"{r.name}, {policy}", r.name, policy) for r in navigated for policy in
             NAV_POLICIES] + [(NEAREST, None, "nearest")]
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
    return {
        "protocol": {
            "eval_seed": EVAL_SEED, "homes": num_homes, "queries_per_home": num_queries,
            "seed": seed, "regime": config.regime, "history": history, "samples": num_samples,
            "horizons": list(horizons), "budget": budget, "num_hours": config.num_hours,
            "queries_by_regime": counts, "step_length_m": nav.STEP_LENGTH,
            "last_seen_eps": pr.LAST_SEEN_EPS, "start": "centre of room 0",
            "model": model_info},
        "posterior": posterior, "navigation": navigation,
        "bayes_optimal_travel": summarise(np.asarray(optimal_travel, np.float64), groups),
        "num_allowed": stats(np.asarray(allowed).sum(-1)),
        "seconds": round(time.perf_counter() - begin, 1)}


# --------------------------------------------------------------------------- command line


def build_parser() -> argparse.ArgumentParser:
    cli = argparse.ArgumentParser(
        prog="python -m flowmaps_jax.homes.evaluate",
        description="FlowSim homes: every prior against the exact posterior (KL, TV, top-1, "
                    "rank cost) and in object navigation (SR@k, mSR, SPL, steps, E[travel] "
                    "÷ exact), overall, by regime and by horizon.")
    add = cli.add_argument
    add("--out", required=True, help="output directory")
    add("--homes", type=int, default=DEFAULT_NUM_HOMES, help="evaluation homes")
    add("--queries", type=int, default=DEFAULT_QUERIES, help="queries per home")
    add("--regime", default="mixed", help=f"schedule regime: {', '.join(REGIME_CHOICES)}")
    add("--seed", type=int, default=0, help="seed of the queries and the samples")
    add("--checkpoint", default=None, metavar="SOURCE",
        help="a FlowMaps homes model (a run's checkpoints directory or a packaged name)")
    add("--history", type=int, default=pr.DEFAULT_HISTORY,
        help="hours of the object's past the exact posterior and the frequency prior read")
    add("--samples", type=int, default=DEFAULT_SAMPLES,
        help="samples per query of the sample rows (0: none)")
    add("--horizons", type=int_list, default=list(DEFAULT_HORIZONS),
        help="query horizons τ_q − τ in hours, comma-separated")
    add("--budget", type=int, default=nav.LOOK_BUDGET, help="looks per navigation episode")
    add("--no-figures", action="store_true", help="skip the PNG figures")
    add("--no-progress", action="store_true", help="no progress bar")
    return cli


def load_model(source: str):
    """``homes.predictor.HomesPredictor.load(source)``; a missing or unreadable source is a
    ``ValueError`` naming ``--checkpoint``."""
    from flowmaps_jax.homes.predictor import HomesPredictor  # the model only when asked for

    with prefix_errors(f"--checkpoint {source!r}: "):
        return HomesPredictor.load(source)


def main(argv: Sequence[str] | None = None) -> int:
    """CLI entry point (see the module's docstring)."""
    from flowmaps_jax.homes import report

    args = build_parser().parse_args(argv)
    try:
        regime = check_choice("--regime", args.regime, REGIME_CHOICES)
        out = pathlib.Path(check_output_dir(  # and no link at the names it will write
            "--out", args.out, files=[*REPORT_FILES, *(() if args.no_figures else FIGURES)]))
        model = info = None
        config = HomesConfig(regime=regime)
        if args.checkpoint is not None:
            model = load_model(args.checkpoint)
            base = getattr(model, "config", None)
            if isinstance(base, HomesConfig):
                config = dataclasses.replace(base, regime=regime)
            step = getattr(model, "step", None)
            info = args.checkpoint + ("" if step is None else f" (step {step})")
        print(f"Homes evaluation: {args.homes} homes x {args.queries} queries, regime {regime}"
              + (f", FlowMaps {info}" if info else "") + f" -> {out}", flush=True)
        results = run_evaluation(config, num_homes=args.homes, num_queries=args.queries,
                                 seed=args.seed, history=args.history,
                                 num_samples=args.samples, horizons=args.horizons,
                                 budget=args.budget, model=model, model_info=info,
                                 progress=not args.no_progress)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_USAGE
    results["command"] = "python -m flowmaps_jax.homes.evaluate " + shlex.join(
        sys.argv[1:] if argv is None else list(argv))
    try:
        make_output_dir("--out", out)
        results["figures"] = [] if args.no_figures else report.write_figures(results, out)
        paths = report.write_report(results, out)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as err:
        print(f"error: could not write the results into {out}: {err.strerror or err}",
              file=sys.stderr)
        return EXIT_WRITE_FAILED
    print(report.navigation_table(results))
    print(f"wrote {', '.join(str(p) for p in paths)}"
          + "".join(f", {out / f}" for f in results["figures"])
          + f" ({results['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
