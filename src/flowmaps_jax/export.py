"""Export a checkpoint's EMA weights as a shipped model (read by :mod:`flowmaps_jax.shipped`).

:func:`export_pretrained` writes ``<name>.npz`` and ``<name>.json`` (atomically: temporary files,
then renames), e.g. ``python -m flowmaps_jax.export --checkpoint runs/X/checkpoints --name mlp``
(the best-by-validation step, the one evaluate and search load by default: one default path;
``--which latest`` exports the last step instead).
``python -m flowmaps_jax.pretrained`` runs the same command.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import pathlib
import sys
from collections.abc import Sequence

import numpy as np
from flax import traverse_util

from flowmaps_jax.predictor import load
from flowmaps_jax.shipped import MAX_BYTES, NAMES, PRETRAINED_DIR, WHICH, check_name, describe
from flowmaps_jax.training import checkpoint
from flowmaps_jax.validation import (
    check_choice,
    check_no_links,
    check_output_dir,
    make_output_dir,
    write_file,
)

EXIT_USAGE, EXIT_WRITE_FAILED = 2, 74


def _params_bytes(params) -> bytes:
    flat = traverse_util.flatten_dict(params, sep="/")
    buffer = io.BytesIO()
    np.savez(buffer, **{k: np.asarray(v, np.float32) for k, v in sorted(flat.items())})
    return buffer.getvalue()


def _default_why(which: str, step: int, best_step: int | None, latest_step: int | None) -> str:
    """The reason recorded for an export without ``why``: what the step is within its run."""
    if which == "best":
        return (f"step {step}, the run's lowest validation score (the step evaluate and search "
                f"load from a run by default); the run's last step is {latest_step}")
    best = (f"its best validation loss was at step {best_step}" if best_step is not None
            else "it saved no best-by-validation step")
    return f"step {step}, the run's last (the weights at the end of training); {best}"


def export_pretrained(checkpoint_dir: str | pathlib.Path, name: str,
                      directory: str | pathlib.Path = PRETRAINED_DIR,
                      which: str = "best", note: str = "", why: str = "") -> pathlib.Path:
    """Copy a checkpoint's EMA weights into ``directory`` as ``name`` (.npz + .json).

    which: "best" (default: the step evaluate and search load by default, lowest validation
    score; a run without one exports its latest step, and the .json says so) or "latest" (the
    end of the run). The .json records ``which``
    and ``why``: the given reason, or by default what the step is within its run (its last
    step or its best, and the step of the other). Raises ``ValueError`` if the checkpoint is
    missing, holds a different model family than the name implies, or is too big. Returns the
    path of the .npz.
    """
    name = check_name(name)
    which = check_choice("which", which, WHICH)
    if not isinstance(why, str):
        raise ValueError(f"why must be text; got {type(why).__name__}")
    check_output_dir("directory", directory)  # before anything is read or written
    check_no_links("directory", directory, [f"{name}.npz", f"{name}.json"])
    ckpt_root = checkpoint.resolve_checkpoint_dir(checkpoint_dir)
    best_step = next(iter(checkpoint.saved_steps(ckpt_root, checkpoint.BEST)), None)
    latest_step = next(iter(checkpoint.saved_steps(ckpt_root, checkpoint.LATEST)), None)
    fallback = which == "best" and best_step is None
    if fallback:  # as load() does: the latest save
        which = "latest"
    predictor = load(checkpoint_dir, which=which)
    cfg = checkpoint.load_config(ckpt_root, which)
    expected_kind = "mlp" if name.startswith("mlp") else "flowmaps"
    if predictor.kind != expected_kind:
        raise ValueError(f"checkpoint_dir holds a {predictor.kind!r} model; name {name!r} needs "
                         f"a {expected_kind!r} model")
    variant = "learned" if name == "mlp-learned" else "mean"
    if expected_kind == "mlp" and predictor.model.baseline_variance != variant:
        raise ValueError(f"checkpoint_dir holds the MLP with baseline_variance="
                         f"{predictor.model.baseline_variance!r}; name {name!r} needs {variant!r}")
    data = _params_bytes(predictor.params)
    if len(data) > MAX_BYTES:
        raise ValueError(f"{name}: {len(data) / 2**20:.1f} MB of weights, over the "
                         f"{MAX_BYTES / 2**20:.0f} MB budget")
    root = make_output_dir("directory", directory)
    meta = {"name": name, "kind": predictor.kind, "step": predictor.step,
            "source": str(checkpoint_dir), "which": which,
            "why": why or (("--which best, but " if fallback else "")
                           + _default_why(which, predictor.step, best_step, latest_step)),
            "note": note,
            "sha256": hashlib.sha256(data).hexdigest(), "config": cfg.to_dict()}
    text = json.dumps(meta, indent=2) + "\n"
    write_file(root / f"{name}.npz", data, name="directory file")  # a temporary file, a rename
    write_file(root / f"{name}.json", text, name="directory file")
    return root / f"{name}.npz"


def main(argv: Sequence[str] | None = None) -> int:
    """CLI: export a checkpoint's EMA weights as a shipped model."""
    parser = argparse.ArgumentParser(prog="python -m flowmaps_jax.export",
                                     description="Export a checkpoint as a shipped model.")
    parser.add_argument("--checkpoint", required=True, help="run or checkpoint directory")
    parser.add_argument("--name", required=True, choices=NAMES)
    parser.add_argument("--which", choices=WHICH, default="best",
                        help="the run's best-by-validation step (best, default: the step "
                             "evaluate and search load) or its last step (latest)")
    parser.add_argument("--out", default=str(PRETRAINED_DIR), help="target directory")
    parser.add_argument("--note", default="", help="provenance note stored in the .json")
    parser.add_argument("--why", default="",
                        help="why this checkpoint was chosen, stored in the .json (default: "
                             "what the step is within its run)")
    args = parser.parse_args(argv)
    try:
        check_output_dir("--out", args.out)
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
