"""``python -m flowmaps_jax.train``: train a model on a world (examples in the README; the run
directory, ``--resume`` and Ctrl-C: docs/guarantees.md). Exit codes: 0 ok, 1 non-finite loss or
state, 2 bad arguments, 74 a failed write (one line naming it), 130 interrupted."""

from __future__ import annotations

import argparse
import errno
import os
import pathlib
import sys
import time
import typing

from flowmaps_jax import distributed
from flowmaps_jax.training import resume
from flowmaps_jax.training.config import (
    DEFAULT_PRESET,
    TrainConfig,
    get_preset,
    presets,
    recorded_config,
    with_world,
)
from flowmaps_jax.training.loop import run
from flowmaps_jax.training.overrides import replace_fields
from flowmaps_jax.validation import check_output_dir
from flowmaps_jax.validation.scalars import ascii_int
from flowmaps_jax.worlds import families, world

EXIT_OK, EXIT_NAN, EXIT_WRITE_FAILED, EXIT_INTERRUPTED = 0, 1, 74, 130


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m flowmaps_jax.train",
        description="Train FlowMaps (flow matching) or the MLP baseline on FlowSim, or the "
                    "homes model on FlowSim homes (--preset homes).")
    parser.add_argument("--preset", choices=sorted(presets()), default=None,
                        help=f"named configuration (default {DEFAULT_PRESET}; homes and "
                             "homes-smoke train on FlowSim homes)")
    parser.add_argument("--family", "--model", dest="family", choices=families(), default=None,
                        help="the model family: flowmaps (default) or mlp (Gaussian baseline); "
                             "--model is its older spelling")
    parser.add_argument("--run-dir", default=None,
                        help="output directory (default runs/<family>-<preset>-<timestamp>); "
                             "a new run needs an empty or missing one")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --run-dir from its latest checkpoint")
    parser.add_argument("--from-step", type=ascii_int, default=None, metavar="N",
                        help="with --resume: continue from the saved step N instead (e.g. when "
                             "the newest step is damaged); later steps are moved aside")
    parser.add_argument("--overwrite", action="store_true",
                        help="start a new run in a non-empty --run-dir after moving the old run "
                             "to <run-dir>.old-<timestamp>")
    parser.add_argument("--steps", type=ascii_int, default=None, help="total training steps")
    parser.add_argument("--stop-at", type=ascii_int, default=None,
                        help="stop (with a checkpoint) after this step; resume later")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE",
                        help="override any config field, e.g. --set model.dim=64 --set lr=1e-3; "
                             "--set world=NAME puts the run on a FlowSim world (routine, "
                             "preferences, dynamic, mixed)")
    parser.add_argument("--init-from", default=None, metavar="MODEL",
                        help="start from these weights (a run or checkpoint directory, or "
                             "pretrained:NAME) instead of a random init: e.g. a history model "
                             "from the one-map pretrained:flowmaps (same as --set init_from=...)")
    parser.add_argument("--data", default=None, metavar="PATH",
                        help="train the homes network on a recorded dataset (a folder of "
                             "recorded.json, python -m flowmaps_jax.data); --preset smoke or "
                             "homes (default) picks the recipe")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


def default_run_dir(cfg: TrainConfig) -> pathlib.Path:
    """``runs/<family>-<preset>-<YYYYmmdd-HHMMSS>`` under the current directory."""
    return pathlib.Path("runs") / f"{cfg.family}-{cfg.preset}-{time.strftime('%Y%m%d-%H%M%S')}"


def split_world(overrides: typing.Iterable[str]) -> tuple[list[str], str | None]:
    """``--set world=NAME`` (a ``flowsim.HABIT_WORLDS`` name) apart from the field overrides: a
    world names a whole habit mixture, not one field. The last ``world=`` wins."""
    rest, world = [], None
    for text in overrides:
        key, sep, value = text.partition("=")
        if sep and key.strip() == "world":
            world = value.strip()
        else:
            rest.append(text)
    return rest, world


_KEPT = ("cannot change on --resume: a resumed run uses the run's saved config (repeat the "
         "run's own --preset, --family, --data and --set world=..., or leave them out); change "
         "fields with --set")


def _unchanged(cfg: TrainConfig, flag: str, value: str) -> bool:
    """Whether ``flag value`` of the original command, repeated with --resume, is the run's."""
    if flag == "--preset":
        table = world(cfg.world).hook("presets")
        return value in table and table[value]().preset == cfg.preset
    if flag == "--family":
        return value == getattr(cfg, "family", None)
    if flag == "--data":
        return world(cfg.world).reads_files and os.path.abspath(value) == cfg.data
    return with_world(cfg, value) == cfg


def resolve_config(args: argparse.Namespace) -> tuple[TrainConfig, pathlib.Path]:
    """The run's config and directory from parsed arguments (ValueError on bad input). The
    options are checked before any is used."""
    overrides, habits = split_world(args.overrides)
    run_dir = None  # '' is refused, not the default; --resume reads it
    if args.run_dir is not None:
        run_dir = pathlib.Path(check_output_dir("run_dir", args.run_dir))
    if args.resume:
        if run_dir is None:
            raise ValueError("--resume needs --run-dir (the run to continue)")
        if args.overwrite:
            raise ValueError("--overwrite and --resume exclude each other")
        cfg = resume.resume_config(run_dir, args.from_step)
        for flag, value in (("--preset", args.preset), ("--family", args.family),
                            ("--set world=...", habits), ("--data", args.data)):
            if value is not None and not _unchanged(cfg, flag, value):
                raise ValueError(f"{flag} {_KEPT}")
        habits = None  # the run's own, repeated
    elif args.data is not None:
        cfg = recorded_config(args.preset, args.data)
    else:
        cfg = get_preset(args.preset or DEFAULT_PRESET)
    for text in overrides:  # what the run derives from --data itself
        key = text.partition("=")[0].strip()
        if key == "data_digest" or (key == "data" and world(cfg.world).reads_files):
            raise ValueError(f"--set {key}: not a setting; the run stores the path of --data "
                             f"and the digest of its contents itself: give the data with --data")
    if habits is not None:
        cfg = with_world(cfg, habits)
    typed = {name: value for name, value in (("family", args.family), ("steps", args.steps),
                                             ("init_from", args.init_from)) if value is not None}
    cfg = replace_fields(cfg, overrides, typed)
    return cfg, run_dir or default_run_dir(cfg)  # run() checks the default one


def _one_line(err: OSError) -> str:
    """A failed write as one line (the message's own line breaks folded)."""
    return " ".join(str(err).split()) or os.strerror(err.errno or errno.EIO)


def _exit_now(code: int) -> typing.NoReturn:
    """Leave without interpreter teardown: XLA threads still working after a Ctrl-C outside the
    step loop would crash it (SIGSEGV); the run's lock is already released."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit code (module docstring)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        distributed.initialize()  # a multi-host job: connect the processes first
        cfg, run_dir = resolve_config(args)
        result = run(cfg, run_dir, resume=args.resume, overwrite=args.overwrite,
                     from_step=args.from_step, stop_at=args.stop_at,
                     progress=not args.no_progress)
    except ValueError as err:
        parser.error(str(err))
    except OSError as err:  # a full disk or another failed write: one line, not a traceback
        print(f"{parser.prog}: error: {_one_line(err)}", file=sys.stderr)
        if argv is None:  # no teardown: checkpoint threads would print tracebacks after the line
            _exit_now(EXIT_WRITE_FAILED)
        return EXIT_WRITE_FAILED
    except KeyboardInterrupt:  # outside the step loop (data, compilation) or a second Ctrl-C
        print("\nInterrupted; the current state was not saved.", file=sys.stderr)
        if argv is None:  # the real command: see _exit_now
            _exit_now(EXIT_INTERRUPTED)
        return EXIT_INTERRUPTED
    return {"nan": EXIT_NAN, "interrupted": EXIT_INTERRUPTED}.get(result.status, EXIT_OK)


if __name__ == "__main__":
    sys.exit(main())
