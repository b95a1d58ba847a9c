"""``python -m flowmaps_jax.export``: a checkpoint's EMA weights as a pretrained model
(:func:`flowmaps_jax.store.pretrained.export_pretrained`), into ``<run>/export/`` or ``--out``.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
from collections.abc import Sequence

from flowmaps_jax.store.checkpoints import WHICH, resolve_checkpoint_dir
from flowmaps_jax.store.pretrained import NAMES, PRETRAINED_DIR, describe, export_pretrained
from flowmaps_jax.validation import check_output_dir

__all__ = ["EXIT_USAGE", "EXIT_WRITE_FAILED", "default_out", "export_pretrained", "main"]

EXIT_USAGE, EXIT_WRITE_FAILED = 2, 74


def default_out(checkpoint: str | pathlib.Path) -> pathlib.Path:
    """The run's own ``export/`` folder next to its ``checkpoints/`` (ValueError if none)."""
    root = resolve_checkpoint_dir(checkpoint)
    return (root.parent if root.name == "checkpoints" else root) / "export"


def main(argv: Sequence[str] | None = None) -> int:
    """CLI: export a checkpoint's EMA weights as a pretrained model."""
    parser = argparse.ArgumentParser(prog="python -m flowmaps_jax.export",
                                     description="Export a checkpoint as a pretrained model.")
    parser.add_argument("--checkpoint", required=True, help="run or checkpoint directory")
    parser.add_argument("--name", required=True, choices=NAMES)
    parser.add_argument("--which", choices=WHICH, default="best",
                        help="the run's best-by-validation step (best, default: the step "
                             "evaluate and search load) or its last step (latest)")
    parser.add_argument("--out", default=None,
                        help="target directory (default: the run's own export/ folder, next "
                             "to its checkpoints/; the packaged weights are replaced only if "
                             f"this names their folder, {PRETRAINED_DIR})")
    parser.add_argument("--note", default="", help="provenance note stored in the .json")
    parser.add_argument("--why", default="",
                        help="why this checkpoint was chosen, stored in the .json (default: "
                             "what the step is within its run)")
    args = parser.parse_args(argv)
    try:
        if args.out is None:
            args.out = str(default_out(args.checkpoint))
        check_output_dir("--out", args.out, files=[f"{args.name}.npz", f"{args.name}.json"])
        path = export_pretrained(args.checkpoint, args.name, args.out, args.which, args.note,
                                 args.why)
        info = describe(args.name, args.out)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as err:  # a full disk: one line, not a traceback
        print(f"error: could not write into {args.out}: {err.strerror or err}", file=sys.stderr)
        return EXIT_WRITE_FAILED
    print(f"wrote {path} ({path.stat().st_size / 2**20:.2f} MB) and {path.with_suffix('.json')}: "
          f"step {info['step']} ({info['which']}: {info['why']})")
    print(f"Load it: flowmaps_jax.predictor.load_pretrained({args.name!r}, "
          f"{str(path.parent)!r})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
