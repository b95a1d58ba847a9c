"""``python -m flowmaps_jax.evaluate``: evaluate a model and baselines against the exact posterior
(the protocol: docs/protocol.md).

    python -m flowmaps_jax.evaluate --checkpoint runs/flowmaps-cpu-X \\
        --baseline runs/mlp-cpu-Y [--baseline ...] [--out DIR] [--num-envs 200] \\
        [--samples 25,100] [--kl-draws 100] [--seed 0] [--world NAME] [--history H]

Writes ``results.json``, ``results.md`` and figures into ``--out`` (default
``<checkpoint>/eval``). ``--checkpoint`` / ``--baseline``: run or checkpoint directories, or
``pretrained:NAME``. The model's world (:mod:`flowmaps_jax.worlds`; ``--data PATH``: the world
of datasets on disk) evaluates it; options that world does not read are refused.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
from collections.abc import Sequence

import jax

from flowmaps_jax import distributed
from flowmaps_jax.evaluation.protocol import (
    DEFAULT_CHUNK_ENVS,
    DEFAULT_KL_DRAWS,
    DEFAULT_LIKELIHOOD_DRAWS,
    DEFAULT_LIKELIHOOD_STEPS,
    DEFAULT_NUM_ENVS,
    DEFAULT_SAMPLES,
)
from flowmaps_jax.evaluation.report import markdown_table
from flowmaps_jax.evaluation.run import FIGURES, REPORT_FILES, model_token_config, run_evaluation
from flowmaps_jax.flowsim.scenes import load_scenes, validation_split
from flowmaps_jax.flowsim.worlds import HABIT_WORLDS, world_config, world_of
from flowmaps_jax.model.families import model_family
from flowmaps_jax.model.family import DENSITY_FACTOR
from flowmaps_jax.predictor import (
    DEFAULT_NUM_STEPS,
    PRETRAINED_PREFIX,
    SOLVERS,
    load_model,
    stored_run,
)
from flowmaps_jax.resources import check_resources, network_flops, solver_evaluations
from flowmaps_jax.validation import check_choice, check_int, check_output_dir, check_seed
from flowmaps_jax.validation.scalars import ascii_int, int_list
from flowmaps_jax.worlds import world, world_of_family, world_of_files

EXIT_USAGE, EXIT_WRITE_FAILED = 2, 74


def _parse_counts(text: str) -> tuple[int, ...]:
    try:
        counts = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--samples must be comma-separated integers like 25,100; got {text!r}") from None
    if not counts or any(n < 1 for n in counts):
        raise argparse.ArgumentTypeError(f"--samples must be positive integers; got {text!r}")
    return counts


def check_size(models, num_envs: int, config, args: argparse.Namespace) -> None:
    """The evaluation's memory and work, estimated before anything runs (the shared budget,
    :func:`flowmaps_jax.resources.check_resources`): ValueError naming the arguments."""
    e, m, f, d = num_envs, config.num_objects, config.num_furniture, args.kl_draws
    n, chunk = max(args.samples), min(args.chunk_envs, num_envs)
    queries = f"on {e} environments x {m} objects"
    check_resources(f"--kl-draws {d} {queries}", num_bytes=4 * e * m * d * (6 + 4 * f))
    families = [model_family(p.family_name) for p in models]
    sampling = max(fam.request_bytes(p.model, chunk * m * n, False)
                   for fam, p in zip(families, models, strict=True))
    check_resources(f"--samples {n} {queries} ({len(models)} models)",
                    num_bytes=4 * e * m * n * (4 * len(models) + 2 * f + 4) + sampling)
    check_resources(f"--kl-draws {d} x --chunk-envs {chunk}",
                    num_bytes=max(fam.request_bytes(p.model, chunk * m * d, True)
                                  for fam, p in zip(families, models, strict=True)))
    logp_steps = args.num_steps if args.logp_steps is None else args.logp_steps
    flops = 0
    for fam, p in zip(families, models, strict=True):
        # each model reads its own tokens: a history model's last H maps (model_view)
        per_query, per_map = network_flops(p.model, model_token_config(config, p).max_tokens,
                                           fam.gaussian is not None)
        sampled = solver_evaluations(args.num_steps, args.method) if fam.uses_solver else 1
        density = solver_evaluations(logp_steps, args.method) if fam.uses_solver else 1
        accurate = getattr(args, "likelihood_steps", 0) or 0  # RK4 on N and 2N intervals
        density += 12 * accurate if fam.uses_solver else 0
        flops += e * m * (n * sampled + d * density * DENSITY_FACTOR) * per_query + e * per_map
    check_resources(f"--num-steps {args.num_steps} / --logp-steps {logp_steps} / "
                    f"--likelihood-steps {getattr(args, 'likelihood_steps', 0)} with --samples "
                    f"{n} and --kl-draws {d} {queries} ({len(models)} models)", flops=flops)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m flowmaps_jax.evaluate",
        description="Evaluate FlowMaps (and baselines) against FlowSim's exact posterior.")
    parser.add_argument("--checkpoint", required=True,
                        help="run or checkpoint directory of the model to evaluate (FlowMaps), "
                             "or pretrained:NAME for a pretrained model (e.g. pretrained:flowmaps)")
    parser.add_argument("--baseline", action="extend", nargs="+", default=[], metavar="DIR",
                        help="run or checkpoint directories (or pretrained:NAME) of baselines "
                             "(several after one flag, or the flag repeated)")
    parser.add_argument("--out", default=None,
                        help="output directory (default: <checkpoint>/eval)")
    parser.add_argument("--num-envs", type=ascii_int, default=DEFAULT_NUM_ENVS,
                        help="validation environments (3 queries each)")
    parser.add_argument("--samples", type=_parse_counts, default=DEFAULT_SAMPLES,
                        help="sample counts for the slot metrics, e.g. 25,100")
    parser.add_argument("--kl-draws", type=ascii_int, default=DEFAULT_KL_DRAWS,
                        help="draws from q per query for the KL estimate")
    parser.add_argument("--seed", type=ascii_int, default=0,
                        help="seed of times, draws and samples")
    parser.add_argument("--which", choices=("best", "latest"), default="best",
                        help="which checkpoint to load")
    parser.add_argument("--num-steps", type=ascii_int, default=DEFAULT_NUM_STEPS,
                        help="ODE grid points for sampling (10 = 18 midpoint evaluations)")
    parser.add_argument("--logp-steps", type=ascii_int, default=None,
                        help="ODE grid points for the likelihood (default: --num-steps)")
    parser.add_argument("--likelihood-steps", type=ascii_int, default=DEFAULT_LIKELIHOOD_STEPS,
                        help="grid points of the accurate likelihood (RK4 on a grid concentrated "
                             "near t = 1) that FlowMaps' KL uses, with its integration error "
                             "against twice the intervals; 0: only the paper's grid")
    parser.add_argument("--likelihood-draws", type=ascii_int, default=DEFAULT_LIKELIHOOD_DRAWS,
                        help="the accurate likelihood uses the first N of each query's KL draws "
                             "(it costs ~10x the paper grid per point)")
    parser.add_argument("--method", choices=SOLVERS, default="midpoint",
                        help="ODE solver for sampling and the paper's likelihood grid "
                             "(accurate: RK4 on the stiff grid)")
    parser.add_argument("--chunk-envs", type=ascii_int, default=DEFAULT_CHUNK_ENVS,
                        help="environments per compiled batch")
    parser.add_argument("--scenes", default=None,
                        help="evaluate on scenes from an .npz (flowsim.scenes.save_scenes) instead "
                             "of the validation split")
    parser.add_argument("--devices", type=ascii_int, default=None, metavar="N",
                        help="split the environments over N devices (default: every device "
                             "JAX sees); results do not depend on it beyond float "
                             "summation order (about 1e-6 relative in the KL)")
    parser.add_argument("--world", default=None, metavar="NAME",
                        help="FlowSim world of the scenes: routine, preferences, dynamic or "
                             "mixed (default: the world of --checkpoint's config)")
    parser.add_argument("--history", type=ascii_int, default=None, metavar="H",
                        help="observations the exact posterior is given (default: the most maps "
                             "any evaluated model reads, at least 8 in a world with habits "
                             "other than the routine)")
    parser.add_argument("--queries", type=ascii_int, default=None, metavar="Q",
                        help="FlowSim homes: queries per home (default 3)")
    parser.add_argument("--regime", default=None,
                        help="FlowSim homes: the schedule regime of the evaluation homes "
                             "(preferences, balanced, frequent, routine or mixed; default mixed)")
    parser.add_argument("--horizons", type=int_list, default=None,
                        help="FlowSim homes: query horizons in hours, comma-separated (default "
                             "1,3,6,12,24,72,168)")
    parser.add_argument("--data", default=None, metavar="PATH",
                        help="a recorded dataset (python -m flowmaps_jax.data): score a homes "
                             "model against the realised receptacles of its held-out part "
                             "(default for a run trained with --data: its own data)")
    parser.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """CLI entry point; returns the exit code (0 on success, 2 on a bad argument, 74 on a failed
    write). The protocol is the one of ``--checkpoint``'s world (its ``evaluate``)."""
    parser = build_parser()
    return run_for_world(parser, parser.parse_args(argv), argv, "evaluate")


COMMON = ("checkpoint", "out", "num_envs", "seed", "which", "no_figures", "no_progress")
"""The options of evaluate and search that every world reads."""


def run_for_world(parser: argparse.ArgumentParser, args: argparse.Namespace,
                  argv: Sequence[str] | None, command: str) -> int:
    """``command`` (``"evaluate"`` or ``"search"``) of ``--checkpoint``'s world, called as
    ``hook(parser, args, argv, stored)`` with the run config stored with it (read once; {} for
    ``pretrained:NAME``): first the options' values, then the stored model's family
    and world (``--data``: the world that reads files), then any option given that the world
    does not read is refused, before any model is loaded. Exit 2 with one line on a bad
    option."""
    try:
        check_int("--num-envs", args.num_envs, 1)
        check_seed("--seed", args.seed)
        if args.history is not None:
            check_int("--history", args.history, 1)
        if args.world is not None:
            check_choice("--world", args.world, tuple(HABIT_WORLDS))
        if args.out:
            check_output_dir("--out", args.out)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_USAGE
    try:
        family, stored = stored_run(args.checkpoint, args.which)
        plugin = world(stored["world"]) if "world" in stored else world_of_family(family)
    except ValueError as err:
        print(f"error: --checkpoint {args.checkpoint!r}: {err}", file=sys.stderr)
        return EXIT_USAGE
    if args.data is not None:  # a dataset on disk: the world that reads it
        plugin = world_of_files()
        if family not in plugin.families:
            print(f"error: --data needs a model of the {list(plugin.families)} families; "
                  f"{args.checkpoint} is a {family!r} model", file=sys.stderr)
            return EXIT_USAGE
    reads = (*COMMON, *plugin.options[command])
    for name, value in vars(args).items():
        if name not in reads and value != parser.get_default(name):
            print(f"error: --{name.replace('_', '-')} does not apply to {args.checkpoint}, a "
                  f"model of the {plugin.name} world", file=sys.stderr)
            return EXIT_USAGE
    return plugin.hook(command)(parser, args, argv, stored)


def evaluate_flowsim(parser: argparse.ArgumentParser, args: argparse.Namespace,
                     argv: Sequence[str] | None, stored: dict) -> int:
    """The 2-D FlowSim protocol (:func:`flowmaps_jax.evaluation.run.run_evaluation`)."""
    try:  # the options (run_for_world's checked), before any model is loaded
        check_int("--kl-draws", args.kl_draws, 2)
        check_int("--num-steps", args.num_steps, 2)
        check_int("--chunk-envs", args.chunk_envs, 1)
        if args.logp_steps is not None:
            check_int("--logp-steps", args.logp_steps, 2)
        if args.likelihood_steps is not None and args.likelihood_steps != 0:
            check_int("--likelihood-steps", args.likelihood_steps, 3)
        check_int("--likelihood-draws", args.likelihood_draws, 2)
        likelihood_steps = args.likelihood_steps or None  # 0: only the paper's grid
        if args.out:
            out = pathlib.Path(args.out)
        elif args.checkpoint.startswith(PRETRAINED_PREFIX):
            raise ValueError("--out is required when --checkpoint is a pretrained model")
        else:
            out = pathlib.Path(args.checkpoint) / "eval"
        out = pathlib.Path(check_output_dir(  # before the evaluation runs
            "--out", out, files=[*REPORT_FILES, *(() if args.no_figures else FIGURES)]))
        mesh = distributed.local_mesh(args.devices)
        model = load_model(args.checkpoint, args.which, args.devices)
        baselines = [load_model(path, args.which, args.devices) for path in args.baseline]
        config = model.flowsim
        if args.world is not None:
            config = world_config(args.world, config)
        scenes = None
        if args.scenes is not None:
            scenes, config = load_scenes(args.scenes)
            if args.world is not None and world_of(config) != args.world:
                raise ValueError(f"--world {args.world}: the scenes of --scenes {args.scenes} "
                                 f"are of the world {world_of(config) or 'custom'}")
            if args.num_envs < scenes.num_envs:
                scenes = jax.tree_util.tree_map(lambda a: a[: args.num_envs], scenes)
        check_size([*baselines, model], args.num_envs if scenes is None else scenes.num_envs,
                   config, args)  # before the scenes are made
        if scenes is None:
            scenes = validation_split(config, num_envs=args.num_envs, mesh=mesh)
        print(f"Evaluating {model.name} ({model.source}, step {model.step})"
              + "".join(f" vs {b.name} ({b.source}, step {b.step})" for b in baselines)
              + f" on {scenes.num_envs} environments"
              + (f" of the {world_of(config) or 'custom'} world" if config.has_habits
                 or args.world is not None else "")
              + f", {distributed.describe(mesh)} → {out}",
              flush=True)
        results, _, _ = run_evaluation(
            [*baselines, model], scenes, config, out, seed=args.seed, sample_counts=args.samples,
            kl_draws=args.kl_draws, chunk_envs=args.chunk_envs, num_steps=args.num_steps,
            method=args.method, logp_steps=args.logp_steps, likelihood_steps=likelihood_steps,
            likelihood_draws=args.likelihood_draws,
            figures=not args.no_figures,
            progress=not args.no_progress, history=args.history)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as err:  # a full disk while writing the report: one line, not a traceback
        print(f"error: could not write the results into {out}: {err.strerror or err}",
              file=sys.stderr)
        return EXIT_WRITE_FAILED
    print(markdown_table(results).split("\n## KL")[0])
    print(f"wrote {out / 'results.json'}, {out / 'results.md'}"
          + "".join(f", {out / f}" for f in results["figures"])
          + f" in {results['seconds']:.1f} s")
    return 0
