"""``python -m flowmaps_jax.search``: search episodes driven by a model, baselines and the exact
posterior (the protocol: docs/search.md; homes navigation: docs/flowsim.md, "Navigation").

    python -m flowmaps_jax.search --checkpoint pretrained:flowmaps \\
        --baseline pretrained:mlp pretrained:mlp-learned --out docs/results_search

Writes ``search.json``, ``search.md`` and figures into ``--out`` (default
``<checkpoint>/search``). Models are run or checkpoint directories (best step unless ``--which
latest``) or ``pretrained:NAME``; each one's checkpoint and step are printed and recorded. The
model's world comes from its stored family, and options that do not apply to it are refused.
"""

from __future__ import annotations

import argparse
import dataclasses
import pathlib
import sys
from collections.abc import Sequence

from flowmaps_jax import distributed
from flowmaps_jax.atomic_files import make_output_dir, save_figure
from flowmaps_jax.evaluation.cli import run_for_world
from flowmaps_jax.flowsim import (
    HABIT_WORLDS,
    FlowSimConfig,
    validation_split,
    world_config,
    world_of,
)
from flowmaps_jax.flowsim.habits import default_history
from flowmaps_jax.flowsim.worlds import HABITS_HISTORY
from flowmaps_jax.predictor import PRETRAINED_PREFIX, load_model
from flowmaps_jax.search import episodes as ep
from flowmaps_jax.search import figures as fg
from flowmaps_jax.search import protocol as pr
from flowmaps_jax.search import simulator as sim
from flowmaps_jax.search.report import markdown_table, write_report
from flowmaps_jax.tables import TABLE_METHODS
from flowmaps_jax.validation import (
    check_int,
    check_output_dir,
    check_real,
)
from flowmaps_jax.validation.scalars import ascii_float, ascii_int, int_list

EXIT_USAGE, EXIT_WRITE_FAILED = 2, 74

FIGURES = ("episodes.png", "success_vs_looks.png", "success_vs_distance.png")
REPORT_FILES = ("search.json", "search.md")


def build_parser() -> argparse.ArgumentParser:
    cli = argparse.ArgumentParser(
        prog="python -m flowmaps_jax.search",
        description="Object search with the predicted posterior: look, fail, update, look again; "
                    "every prior scored against the Bayes-optimal searcher (docs/search.md).")
    add = cli.add_argument
    add("--checkpoint", required=True, help="the model's run/checkpoint directory, or "
                                            "pretrained:NAME (flowmaps, mlp, mlp-learned)")
    add("--baseline", nargs="+", action="extend", default=[], metavar="MODEL",
        help="more models as rows (directories or pretrained:NAME), e.g. the MLP baselines")
    add("--out", default=None, help="output directory (default: <checkpoint>/search)")
    add("--num-envs", type=ascii_int, default=pr.DEFAULT_NUM_ENVS, help="validation environments")
    add("--times-per-env", type=ascii_int, default=pr.DEFAULT_TIMES_PER_ENV,
        help="(τ, τ_q) draws per environment; every object is searched for in each")
    add("--horizons", type=int_list, default=None,
        help="instead of random draws: fixed horizons Δτ, e.g. 1,2,4,8 (one row each)")
    add("--world", default=None, metavar="NAME",
        help=f"FlowSim world of the searched scenes ({', '.join(HABIT_WORLDS)}; default: the "
             "world of the first model's config)")
    add("--history", type=ascii_int, default=None, metavar="H",
        help="observations the exact reference posterior is given (default: the largest "
             f"model.history among the models, at least {HABITS_HISTORY} in a world with "
             "habits other than the routine)")
    add("--samples", type=ascii_int, default=pr.DEFAULT_SAMPLES,
        help="samples per query for the model rows' table probabilities")
    add("--table-method", choices=TABLE_METHODS, default="weights",
        help="how FlowMaps' table probabilities are read: the read-out head's mixture weights "
             "(default: no sampling noise, and the shorter searches, docs/results.md), or "
             "counts of --samples samples (the MLP baselines are always sampled)")
    add("--policies", nargs="+", default=list(pr.MAIN_POLICIES), choices=pr.MAIN_POLICIES,
        help="policies every prior is driven by")
    add("--budget", type=ascii_int, default=sim.DEFAULT_BUDGET, help="looks per episode")
    add("--p-miss", type=ascii_float, default=0.0, help="chance a look at the right table misses")
    add("--start", choices=ep.STARTS, default="centre", help="where the robot starts")
    add("--seed", type=ascii_int, default=0, help="seed of the queries, samples and misses")
    add("--which", choices=("best", "latest"), default="best", help="checkpoint to load")
    add("--chunk-rows", type=ascii_int, default=50, help="scene rows per model call")
    add("--devices", type=ascii_int, default=None, metavar="N",
        help="split the model calls over N devices (default: every device JAX sees)")
    add("--queries", type=ascii_int, default=None, metavar="Q",
        help="FlowSim homes: queries (episodes) per home (default 3)")
    add("--regime", default=None,
        help="FlowSim homes: the schedule regime of the homes (preferences, balanced, frequent, "
             "routine or mixed; default mixed)")
    add("--data", default=None, metavar="PATH",
        help="a recorded dataset: navigation of a homes model with the realised receptacle "
             "as the target (default for a run trained with --data: its own data)")
    add("--no-figures", action="store_true", help="skip the PNG figures")
    add("--no-progress", action="store_true", help="no progress bars")
    return cli


def write_figures(results: dict, runs: dict, search_set: ep.SearchSet, config,
                  out: pathlib.Path) -> list[str]:
    """The report's figures into ``out``; returns their file names."""
    policy = "optimal" if "optimal" in results["protocol"]["policies"] \
        else results["protocol"]["policies"][0]
    drawn = {name: (runs[name, policy if name != pr.NEAREST_ROW else "nearest"].episodes,
                    runs[name, policy if name != pr.NEAREST_ROW else "nearest"].outcome)
             for name in results["rows"]}
    exact, nearest = runs[pr.EXACT_ROW, policy].expected, runs[pr.NEAREST_ROW, "nearest"].expected
    gain = None if exact is None else nearest["travel"] - exact["travel"]  # what the prior saves
    picks = fg.pick_episodes(search_set, score=gain)
    figures = {FIGURES[0]: fg.plot_episodes(search_set, drawn, picks, config, policy),
               FIGURES[1]: fg.plot_success_vs_looks(results),
               FIGURES[2]: fg.plot_success_vs_distance(results)}
    for filename, figure in figures.items():
        save_figure(figure, out / filename, name="--out file", dpi=100)
    return list(figures)


def loaded_from(model) -> str:
    """``name (source, step N)``: the checkpoint (a checkpoint directory, or
    ``pretrained:NAME``) and step a model was loaded from, as ``evaluate`` prints it."""
    return f"{model.name} ({model.source}, step {model.step})"


def search_world(models: Sequence, world: str | None = None,
                 history: int | None = None) -> tuple[FlowSimConfig, int]:
    """The search's FlowSim config and reference history for ``models``.

    config: the first model's config in ``world`` (``flowsim.world_config``; None: that config
    as it is), with room for the tokens of the model reading the most maps. history: ``history``
    if given, else the largest ``model.history`` among the models, and at least
    ``HABITS_HISTORY`` when the world has habits other than the routine. ``ValueError`` names
    ``world`` or ``--history``.
    """
    config = models[0].flowsim if world is None else world_config(world, models[0].flowsim)
    reads = max(pr.model_history(m) for m in models)
    needed = config.num_furniture + config.num_objects * reads
    if needed > config.max_tokens:  # a model reading H maps needs F + M·H tokens
        config = dataclasses.replace(config, max_tokens=needed)
    if history is None:
        history = default_history(config, reads)
    check_int("--history", history, maximum=config.num_timesteps)
    return config, int(history)


def main(argv: Sequence[str] | None = None) -> int:
    """CLI entry point; 0 on success, 2 on a bad argument, 74 on a failed write (a full disk);
    one line on stderr. Every argument, ``--out`` and the run's size are checked first. The
    protocol is the one of ``--checkpoint``'s world (its ``search``)."""
    parser = build_parser()
    return run_for_world(parser, parser.parse_args(argv), argv, "search")


def search_flowsim(parser: argparse.ArgumentParser, args: argparse.Namespace,
                   argv: Sequence[str] | None, stored: dict) -> int:
    """The 2-D FlowSim search (:func:`flowmaps_jax.search.protocol.run_search`)."""
    try:  # the options (run_for_world's checked), before any model is loaded
        check_int("--times-per-env", args.times_per_env)
        check_int("--samples", args.samples)
        check_int("--budget", args.budget)
        check_int("--chunk-rows", args.chunk_rows)
        # the chance a look at the right table misses
        check_real("--p-miss", args.p_miss, 0.0, 1.0, high_open=True)
        if args.out is None and args.checkpoint.startswith(PRETRAINED_PREFIX):
            raise ValueError("--out is required when --checkpoint is pretrained:NAME")
        out = pathlib.Path(check_output_dir(
            "--out", args.out or pathlib.Path(args.checkpoint) / "search",
            files=[*REPORT_FILES, *(() if args.no_figures else FIGURES)]))
        models = [load_model(spec, args.which, args.devices)
                  for spec in [args.checkpoint, *args.baseline]]
        config, history = search_world(models, args.world, args.history)
        habits = ep.uses_history(config, history)
        per_env = len(args.horizons) if args.horizons else args.times_per_env
        ep.check_search_size(
            config, args.num_envs * per_env, budget=args.budget, policies=args.policies,
            num_samples=args.samples, chunk_rows=args.chunk_rows, predictors=models,
            what=f"--num-envs {args.num_envs} x " + (f"{per_env} --horizons" if args.horizons
                                                     else f"--times-per-env {per_env}"),
            extra_rows=2 if history > 1 else 0)
        scenes = validation_split(config, num_envs=args.num_envs,
                                  mesh=distributed.local_mesh(args.devices))
        where = (f" of the {world_of(config) or config.habits} world (exact posterior given "
                 f"the last {history} observations)" if habits else "")
        print(f"Search with {', '.join(loaded_from(m) for m in models)} on {args.num_envs} "
              f"validation environments{where} → {out}", flush=True)
        results, runs, search_set = pr.run_search(
            models, scenes, config, seed=args.seed, num_samples=args.samples,
            times_per_env=args.times_per_env, horizons=args.horizons, policies=args.policies,
            budget=args.budget, p_miss=args.p_miss, start=args.start,
            chunk_rows=args.chunk_rows, progress=not args.no_progress,
            table_method=args.table_method, history=history)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_USAGE
    try:
        out = make_output_dir("--out", out)
        if not args.no_figures:
            results["figures"] = write_figures(results, runs, search_set, config, out)
        paths = write_report(results, out)
    except ValueError as err:  # a link planted at an output name while the search ran
        print(f"error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as err:  # a full disk, a quota: one line, not a traceback
        print(f"error: could not write the results into {out}: {err.strerror or err}",
              file=sys.stderr)
        return EXIT_WRITE_FAILED
    print(markdown_table(results).split("\n## By horizon")[0])  # overall (and by habit)
    print(f"wrote {paths['json']}, {paths['markdown']}"
          + "".join(f", {out / f}" for f in results["figures"])
          + f" ({results['seconds']:.0f} s of search)")
    return 0
