"""``python -m flowmaps_jax.data``: recorded worlds from files and simulators, and back
(docs/data.md).

    python -m flowmaps_jax.data import-flowmaps2026 ROOT --out PATH [--overwrite]
    python -m flowmaps_jax.data export-flowmaps2026 PATH --out ROOT [--overwrite]
    python -m flowmaps_jax.data from-homes --homes N [--regime mixed] [--hours T] [--mask 0.3]
        [--seed S] [--names PREFIX] --out PATH [--overwrite]
    python -m flowmaps_jax.data import-log TABLE [--layout FILE] --out PATH [--overwrite]
    python -m flowmaps_jax.data validate PATH

``import-flowmaps2026`` reads every environment folder under ROOT in the authors' 2026 layout
(:mod:`flowmaps_jax.recorded.flowmaps2026`) and writes one recorded world (:mod:`~flowmaps_jax.
recorded.format`) to PATH; ``export-flowmaps2026`` writes a recorded world in that layout;
``from-homes`` generates N FlowSim homes (``generate_homes(jax.random.key(S), config, N)``) and
writes them as a recorded world, about ``--mask`` of the object-hours hidden by whole rooms
(:mod:`~flowmaps_jax.recorded.from_homes`); ``import-log`` reads a CSV or parquet table of
sightings (:mod:`~flowmaps_jax.recorded.import_log`); ``validate`` loads PATH and prints a
summary and the default recipe's split. Every writing command writes its whole ``--out`` folder
aside and renames it into place (:func:`~flowmaps_jax.atomic_files.output_folder`): a link
there is refused, and so is a folder holding anything unless ``--overwrite`` (it is then moved
to ``<out>.old-<time>``). Exit codes: 0 ok, 2 bad arguments or a bad input
file (one line), 74 a failed write (a full disk), 130 interrupted.
"""

from __future__ import annotations

import argparse
import dataclasses
import errno
import os
import sys
from collections.abc import Sequence

from tqdm.auto import tqdm

from flowmaps_jax.atomic_files import output_folder
from flowmaps_jax.flowsim.homes.config import REGIMES, HomesConfig
from flowmaps_jax.recorded import Recorded, from_homes, load_recorded, save_recorded
from flowmaps_jax.recorded.flowmaps2026 import export_flowmaps2026, import_flowmaps2026
from flowmaps_jax.recorded.format import check_environment_name
from flowmaps_jax.resources import check_request_size
from flowmaps_jax.validation import check_int, check_output_dir, check_real, check_seed
from flowmaps_jax.validation.scalars import ascii_float, ascii_int

EXIT_OK, EXIT_USAGE, EXIT_WRITE_FAILED, EXIT_INTERRUPTED = 0, 2, 74, 130
PROG = "python -m flowmaps_jax.data"
HOMES_CHUNK = 64
"""Homes generated per compiled call of ``from-homes`` (one progress step)."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG, description="Recorded worlds: convert the authors' 2026 dataset layout both "
                               "ways, or write FlowSim homes as a recorded world (docs/data.md).")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    imp = commands.add_parser("import-flowmaps2026", help="the authors' 2026 layout -> a "
                                                          "recorded world")
    imp.add_argument("root", metavar="ROOT", help="folder holding environment folders (any "
                                                  "depth) with scan_merged.parquet or "
                                                  "scan_N.parquet")
    imp.add_argument("--out", required=True, metavar="PATH", help="the recorded world's folder")
    exp = commands.add_parser("export-flowmaps2026", help="a recorded world -> the authors' "
                                                          "2026 layout")
    exp.add_argument("path", metavar="PATH", help="a recorded world's folder")
    exp.add_argument("--out", required=True, metavar="ROOT", help="folder to write the "
                                                                   "environment folders into")
    homes = commands.add_parser("from-homes", help="FlowSim homes -> a recorded world")
    homes.add_argument("--homes", type=ascii_int, required=True, metavar="N",
                       help="number of homes")
    homes.add_argument("--regime", choices=(*REGIMES, "mixed"), default="mixed",
                       help="the homes' schedule regime (default mixed)")
    homes.add_argument("--hours", type=ascii_int, default=None, metavar="T",
                       help=f"hours per home (default {HomesConfig().num_hours}, four weeks)")
    homes.add_argument("--mask", type=ascii_float, default=0.0, metavar="FRACTION",
                       help="about this fraction of the object-hours is hidden, by whole rooms "
                            "unvisited for runs of hours (default 0)")
    homes.add_argument("--seed", type=ascii_int, default=0,
                       help="seed of the homes (jax.random.key(seed)) and of the mask")
    homes.add_argument("--names", default="home", metavar="PREFIX",
                       help="environment e is named PREFIX<e> (default home: home0, home1, "
                            "...); a path prefix such as train/env gives train/env0, ...")
    homes.add_argument("--out", required=True, metavar="PATH", help="the recorded world's folder")
    log = commands.add_parser("import-log", help="a table of sightings (CSV or parquet) -> a "
                                                 "recorded world")
    log.add_argument("table", metavar="TABLE", help="a .csv or .parquet table, one row per "
                                                    "sighting or search (docs/data.md)")
    log.add_argument("--layout", metavar="FILE", help="JSON of receptacle boxes, room boxes and "
                                                      "doors per environment (default: none)")
    log.add_argument("--out", required=True, metavar="PATH", help="the recorded world's folder")
    val = commands.add_parser("validate", help="check a recorded world and summarise it")
    val.add_argument("path", metavar="PATH", help="a recorded world's folder")
    for sub in (imp, exp, homes, log):
        sub.add_argument("--no-progress", action="store_true", help="no progress bar")
        sub.add_argument("--overwrite", action="store_true", help="replace a --out folder that "
                         "holds anything (it is moved to <out>.old-<time>)")
    return parser


def describe(recorded: Recorded) -> str:
    """One line: how many environments, their sizes and the share of object-hours observed."""
    envs = recorded.environments

    def span(values) -> str:
        lo, hi = min(values), max(values)
        return str(lo) if lo == hi else f"{lo}-{hi}"

    seen = sum(int(e.observed.sum()) for e in envs)
    total = sum(e.num_hours * e.num_objects for e in envs)
    return (f"{len(envs)} environment{'s' * (len(envs) != 1)}, "
            f"{span([e.num_hours for e in envs])} hours, "
            f"{span([e.num_objects for e in envs])} objects, "
            f"{span([e.num_receptacles for e in envs])} receptacles; "
            f"{100 * seen / max(total, 1):.1f} % of the object-hours observed")


def _bar(args, what: str, unit: str):
    return lambda items: tqdm(items, desc=what, unit=unit, disable=args.no_progress,
                              leave=False)


def _out(args):
    """The ``--out`` folder, checked before any work, written aside (``output_folder``)."""
    check_output_dir("--out", args.out)
    return output_folder("--out", args.out, overwrite=args.overwrite)


def _import(args) -> str:
    with _out(args) as out:
        recorded = import_flowmaps2026(args.root, progress=_bar(args, "reading", "env"))
        save_recorded(recorded, out)
    return f"wrote {args.out}: {describe(recorded)}"


def _export(args) -> str:
    with _out(args) as out:
        recorded = load_recorded(args.path)
        export_flowmaps2026(recorded, out, progress=_bar(args, "writing", "env"))
    return (f"wrote {len(recorded.environments)} environment folders and "
            f"{os.path.join(args.out, 'lookup.json')} ({describe(recorded)})")


def _import_log(args) -> str:
    from flowmaps_jax.recorded.import_log import import_log

    with _out(args) as out:
        recorded = import_log(args.table, args.layout, progress=_bar(args, "reading", "row"))
        save_recorded(recorded, out)
    envs = recorded.environments
    negative = sum(int(e.not_at.any(axis=-1).sum()) for e in envs) / sum(
        e.num_hours * e.num_objects for e in envs)
    return (f"wrote {args.out}: {describe(recorded)}, {100 * negative:.1f} % with negative "
            f"evidence")


def homes_config(args) -> HomesConfig:
    """The HomesConfig of ``from-homes``' options."""
    changes = {"regime": args.regime}
    if args.hours is not None:
        changes["num_hours"] = check_int("--hours", args.hours, 2)
    return HomesConfig(**changes)


def _from_homes(args) -> str:
    from flowmaps_jax.flowsim.homes.rollout import homes_bytes_per_home

    num = check_int("--homes", args.homes, 1)
    mask = check_real("--mask", args.mask, 0.0, 1.0, high_open=True)
    seed = check_seed("--seed", args.seed)
    config = homes_config(args)
    check_environment_name(f"{args.names}0", "--names")
    check_request_size(f"--homes {num}", 2 * num * homes_bytes_per_home(config))
    with _out(args) as out:
        recorded = _generate(args, num, mask, seed, config)
        save_recorded(recorded, out)
    return f"wrote {args.out}: {describe(recorded)}"


def _generate(args, num: int, mask: float, seed: int, config: HomesConfig) -> Recorded:
    import jax
    import numpy as np

    from flowmaps_jax.flowsim.homes.rollout import homes_from_keys

    keys = jax.random.split(jax.random.key(seed), num)  # as generate_homes(key(seed), config, N)
    chunk = min(HOMES_CHUNK, num)
    environments = []
    with tqdm(total=num, desc="homes", unit="home", disable=args.no_progress,
              leave=False) as bar:
        for start in range(0, num, chunk):
            part = keys[start:start + chunk]
            size = part.shape[0]
            if size < chunk:  # the compiled shape: pad with the first key, then drop
                part = jax.numpy.concatenate([part, jax.numpy.repeat(part[:1], chunk - size)])
            homes = jax.tree.map(lambda x, n=size: np.asarray(x)[:n],
                                 homes_from_keys(part, config))
            names = [f"{args.names}{e}" for e in range(start, start + size)]
            environments.extend(from_homes(homes, config, mask_fraction=mask, seed=seed,
                                           names=names, first_home=start).environments)
            bar.update(size)
    generator = {"call": "generate_homes(jax.random.key(seed), config, num_homes)",
                 "seed": seed, "num_homes": num}
    return Recorded(tuple(dataclasses.replace(env, source={**env.source, "generator": generator})
                          for env in environments))


def _validate(args) -> str:
    """The one-screen summary of a dataset that loads (``load_recorded`` refuses a bad one)."""
    from flowmaps_jax.training.config import recorded_homes_preset
    from flowmaps_jax.worlds.recorded import describe_split, split_environments

    recorded = load_recorded(args.path)
    envs, voc, cfg = recorded.environments, recorded.vocabulary(), recorded_homes_preset()

    def some(items, k: int = 8) -> str:
        return ", ".join(items[:k]) + (f", ... ({len(items)} in all)" if len(items) > k else "")

    def share(field: str) -> str:
        n = sum(getattr(e, field) is not None and len(getattr(e, field)) > 0 for e in envs)
        return "all" if n == len(envs) else f"{n} of {len(envs)}"

    def span(values) -> str:
        return f"{min(values)}" + (f"-{max(values)}" if max(values) > min(values) else "")

    spans = [int(e.hours[-1] - e.hours[0]) + 1 for e in envs]
    total = sum(e.num_hours * e.num_objects for e in envs)
    looked = sum(int(e.not_at.any(-1).sum()) for e in envs if e.not_at is not None)
    split = split_environments(recorded.names(), cfg.val_fraction, cfg.test_fraction,
                               cfg.split_seed)
    return "\n".join([
        f"{args.path}: a valid recorded world: {describe(recorded)}",
        f"  environments: {some(recorded.names())}",
        f"  hours spanned (first to last): {span(spans)} ({max(spans) / 24:.1f} days at most)",
        *(f"  {kind[:-1]} classes: {some(voc[kind]) or 'none'}"
          for kind in ("objects", "receptacles", "rooms")),
        f"  rooms per environment: {span([len(e.room_classes) for e in envs])}",
        f"  geometry: receptacle boxes in {share('receptacle_corners')}; rooms in "
        f"{share('room_boxes')}, doors in {share('door_rooms')}, stored walking distances in "
        f"{share('distance')} (else derived), object boxes in {share('object_corners')}"
        + ("" if share("receptacle_corners") == "all" else "; without boxes, walking costs "
           "come from the room graph"),
        f"  negative evidence (not_at) in {share('not_at')}: {100 * looked / total:.1f} % of "
        f"the object-hours hold a look that found the object absent",
        f"  the default recipe's split (val_fraction={cfg.val_fraction}, test_fraction="
        f"{cfg.test_fraction}, split_seed={cfg.split_seed}; docs/protocol.md):",
        describe_split(recorded, split, cfg.time_fraction).replace("  ", "    ")])


COMMANDS = {"import-flowmaps2026": _import, "export-flowmaps2026": _export,
            "from-homes": _from_homes, "import-log": _import_log, "validate": _validate}


def main(argv: Sequence[str] | None = None) -> int:
    """CLI entry point; returns the exit code (0 ok, 2 a bad argument or input file, 74 a
    failed write, 130 interrupted)."""
    args = build_parser().parse_args(argv)
    try:
        print(COMMANDS[args.command](args))
    except ValueError as err:
        print(f"error: {' '.join(str(err).split())}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as err:  # a full disk or another failed write: one line, not a traceback
        text = " ".join(str(err).split()) or os.strerror(err.errno or errno.EIO)
        print(f"error: {text}", file=sys.stderr)
        return EXIT_WRITE_FAILED
    except KeyboardInterrupt:
        print("\nInterrupted; nothing was written unless its line says so.", file=sys.stderr)
        return EXIT_INTERRUPTED
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
