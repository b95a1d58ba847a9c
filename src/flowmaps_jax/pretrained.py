"""Trained default models shipped inside the package: ``load_pretrained(name)`` and their export.

The EMA weights of the `cpu`-preset runs documented in docs/results.md ("Shipped weights") live in
``flowmaps_jax/pretrained/<name>.npz`` (float32 parameter arrays keyed by their path in the params
pytree) next to ``<name>.json`` (the run's TrainConfig, model kind, step, source, which checkpoint
of the run it is, ``"which": "best"`` or ``"latest"``, and why, and the SHA-256 of the .npz,
checked on load). Files written before ``which`` was recorded lack it: :func:`describe` reports
``"unknown"`` for them (the shipped files are the runs' last steps, docs/results.md). A plain
``pip install .`` carries them; nothing is downloaded. Loading trusts neither file: the ``.json``
is size-limited and its fields are checked (a name, a model kind, a step that is a count,
``which`` if present), the ``.npz`` is read only after its SHA-256 matches, with
its members whitelisted (exactly the model's parameters, their declared shapes checked before
anything is decompressed) and every weight finite.

    from flowmaps_jax.sample import load_pretrained
    predictor = load_pretrained("flowmaps")      # or "mlp", "mlp-learned"

:func:`export_pretrained` writes the pair from a checkpoint (atomically: temporary files, then
renames), e.g. ``python -m flowmaps_jax.pretrained --checkpoint runs/X/checkpoints --name mlp``
(the last step; ``--which best`` exports the best-by-validation step instead).
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

PRETRAINED_DIR = pathlib.Path(__file__).resolve().parent / "pretrained"
NAMES = ("flowmaps", "mlp", "mlp-learned")
MAX_BYTES = 10 * 1024 * 1024  # the size budget per model
MAX_META_BYTES = 1024 * 1024  # a .json larger than this is not one export_pretrained wrote
EXIT_USAGE, EXIT_WRITE_FAILED = 2, 74
WHICH = ("latest", "best")  # the checkpoint of a run that an export copies
UNKNOWN = "unknown"  # "which" of a .json written before it was recorded


def _check_name(name) -> str:
    if not isinstance(name, str) or name not in NAMES:
        raise ValueError(f"name must be one of {list(NAMES)}; got {name!r}")
    return name


def available(directory: str | pathlib.Path = PRETRAINED_DIR) -> list[str]:
    """The names whose weights are present in ``directory``."""
    root = pathlib.Path(directory)
    return [n for n in NAMES if (root / f"{n}.npz").is_file() and (root / f"{n}.json").is_file()]


def _params_bytes(params) -> bytes:
    flat = traverse_util.flatten_dict(params, sep="/")
    buffer = io.BytesIO()
    np.savez(buffer, **{k: np.asarray(v, np.float32) for k, v in sorted(flat.items())})
    return buffer.getvalue()


def _write_atomic(path: pathlib.Path, data: bytes) -> None:
    from flowmaps_jax.training.rundir import write_atomic

    write_atomic(path, data)  # a temporary file and a rename; no symbolic link followed


def _check_meta(name: str, meta, file: str) -> dict:
    """The fields of a weights ``.json`` that the loader uses or reports, checked."""
    if not isinstance(meta, dict):
        raise ValueError(f"pretrained {name!r}: {file} is not a JSON object")
    step = meta.get("step")
    if step is not None and (isinstance(step, bool) or not isinstance(step, int) or step < 0):
        raise ValueError(f"pretrained {name!r}: {file} has step {str(step)[:40]!r}; expected a "
                         f"count of training steps")
    which = meta.get("which", UNKNOWN)
    if which not in (*WHICH, UNKNOWN):
        raise ValueError(f"pretrained {name!r}: {file} has which {str(which)[:40]!r}; expected "
                         f"one of {list(WHICH)}")
    if not isinstance(meta.get("why", ""), str):
        raise ValueError(f"pretrained {name!r}: {file} has a why that is not text")
    if meta.get("name", name) != name:
        raise ValueError(f"pretrained {name!r}: {file} is the .json of "
                         f"{str(meta.get('name'))[:40]!r}")
    digest = meta.get("sha256")
    if not (isinstance(digest, str) and len(digest) == 64
            and all(c in "0123456789abcdef" for c in digest)):
        raise ValueError(f"pretrained {name!r}: {file} has no valid sha256 field")
    return meta


def _default_why(which: str, step: int, best_step: int | None, latest_step: int | None) -> str:
    """The reason recorded for an export without ``why``: what the step is within its run."""
    if which == "best":
        return (f"step {step}, the run's lowest validation loss (the step evaluate and search "
                f"load from a run by default); the run's last step is {latest_step}")
    best = (f"its best validation loss was at step {best_step}" if best_step is not None
            else "it saved no best-by-validation step")
    return f"step {step}, the run's last (the weights at the end of training); {best}"


def export_pretrained(checkpoint_dir: str | pathlib.Path, name: str,
                      directory: str | pathlib.Path = PRETRAINED_DIR,
                      which: str = "latest", note: str = "", why: str = "") -> pathlib.Path:
    """Copy a checkpoint's EMA weights into ``directory`` as ``name`` (.npz + .json).

    which: "latest" (the end of the run, default) or "best" (lowest validation loss; a run
    without one exports its latest step, and the .json says so). The .json records ``which``
    and ``why``: the given reason, or by default what the step is within its run (its last
    step or its best, and the step of the other). Raises ``ValueError`` if the checkpoint is
    missing, holds a different model kind than the name implies, or is too big. Returns the
    path of the .npz.
    """
    from flowmaps_jax.sample import load
    from flowmaps_jax.training import checkpoint
    from flowmaps_jax.validation import check_choice, check_output_dir

    name = _check_name(name)
    which = check_choice("which", which, WHICH)
    if not isinstance(why, str):
        raise ValueError(f"why must be text; got {type(why).__name__}")
    check_output_dir("directory", directory)  # before anything is read or written
    ckpt_root = checkpoint.resolve_checkpoint_dir(checkpoint_dir)
    best_step = checkpoint.saved_step(ckpt_root, checkpoint.BEST)
    latest_step = checkpoint.saved_step(ckpt_root, checkpoint.LATEST)
    fallback = which == "best" and best_step is None
    if fallback:  # as load() does: the latest save
        which = "latest"
    predictor = load(checkpoint_dir, which=which)
    cfg = checkpoint.load_config(ckpt_root, which)
    expected_kind = "flowmaps" if name == "flowmaps" else "mlp"
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
    root = pathlib.Path(directory)
    root.mkdir(parents=True, exist_ok=True)
    meta = {"name": name, "kind": predictor.kind, "step": predictor.step,
            "source": str(checkpoint_dir), "which": which,
            "why": why or (("--which best, but " if fallback else "")
                           + _default_why(which, predictor.step, best_step, latest_step)),
            "note": note,
            "sha256": hashlib.sha256(data).hexdigest(), "config": cfg.to_dict()}
    _write_atomic(root / f"{name}.npz", data)
    _write_atomic(root / f"{name}.json", (json.dumps(meta, indent=2) + "\n").encode())
    return root / f"{name}.npz"


def _read_meta(name: str, root: pathlib.Path) -> dict:
    """The checked ``.json`` of the weights ``name`` in ``root`` (size first, then fields)."""
    meta_path = root / f"{name}.json"
    if meta_path.stat().st_size > MAX_META_BYTES:
        raise ValueError(f"pretrained {name!r}: {meta_path.name} holds "
                         f"{meta_path.stat().st_size:,} bytes, more than the "
                         f"{MAX_META_BYTES:,} a shipped model may have")
    try:
        return _check_meta(name, json.loads(meta_path.read_text()), meta_path.name)
    except ValueError as err:
        raise ValueError(f"pretrained {name!r}: unreadable {meta_path.name}: {err}") from None


def describe(name: str, directory: str | pathlib.Path = PRETRAINED_DIR) -> dict:
    """What the shipped model ``name`` is, from its ``.json`` only (no weights are read):
    ``{"name", "kind", "step", "which", "why", "source", "note"}``. ``which`` is "latest" (the
    run's last step), "best" (its best-by-validation step) or "unknown" for a .json written
    before exports recorded it; ``why`` is then "". ValueError when the files are missing or
    the .json is not one :func:`export_pretrained` wrote."""
    name = _check_name(name)
    root = pathlib.Path(directory)
    if name not in available(root):
        raise ValueError(f"pretrained weights {name!r} are not in {root} (present: "
                         f"{available(root) or 'none'})")
    meta = _read_meta(name, root)
    return {"name": name, "kind": meta.get("kind"), "step": meta.get("step"),
            "which": meta.get("which", UNKNOWN), "why": meta.get("why", ""),
            "source": meta.get("source"), "note": meta.get("note", "")}


def load_pretrained(name: str, directory: str | pathlib.Path = PRETRAINED_DIR):
    """The shipped model ``name`` ("flowmaps", "mlp" or "mlp-learned") as a
    :class:`~flowmaps_jax.sample.Predictor`, exactly as ``load(dir)`` of its run would give.

    Raises ``ValueError`` for an unknown name (listing the names), or weights that are missing,
    damaged (SHA-256 mismatch) or do not fit their config.
    """
    import jax
    import jax.numpy as jnp

    from flowmaps_jax.sample import Predictor
    from flowmaps_jax.training.config import TrainConfig
    from flowmaps_jax.training.objectives import objective_for

    name = _check_name(name)
    root = pathlib.Path(directory)
    npz, meta_path = root / f"{name}.npz", root / f"{name}.json"
    if not (npz.is_file() and meta_path.is_file()):
        raise ValueError(f"pretrained weights {name!r} are not in {root} (present: "
                         f"{available(root) or 'none'})")
    from flowmaps_jax.validation import read_npz

    for path, limit in ((meta_path, MAX_META_BYTES), (npz, 2 * MAX_BYTES)):
        if path.stat().st_size > limit:
            raise ValueError(f"pretrained {name!r}: {path.name} holds {path.stat().st_size:,} "
                             f"bytes, more than the {limit:,} a shipped model may have")
    try:
        meta = _check_meta(name, json.loads(meta_path.read_text()), meta_path.name)
        cfg = TrainConfig.from_dict(meta["config"])
    except (ValueError, KeyError, TypeError) as err:
        raise ValueError(f"pretrained {name!r}: unreadable {meta_path.name}: {err}") from None
    if meta.get("kind", cfg.model_kind) != cfg.model_kind:
        raise ValueError(f"pretrained {name!r}: {meta_path.name} names kind "
                         f"{str(meta.get('kind'))[:40]!r} but its config is a "
                         f"{cfg.model_kind!r} model")
    data = npz.read_bytes()
    if hashlib.sha256(data).hexdigest() != meta["sha256"]:
        raise ValueError(f"pretrained {name!r}: {npz.name} is damaged (SHA-256 does not match "
                         f"{meta_path.name}); reinstall the package")
    abstract = jax.eval_shape(objective_for(cfg).init, jax.random.key(0))
    expected = {key: (leaf.shape, leaf.dtype)
                for key, leaf in traverse_util.flatten_dict(abstract, sep="/").items()}
    try:  # members whitelisted and their sizes checked before anything is decompressed
        arrays = read_npz(npz.name, io.BytesIO(data), expected=expected, max_bytes=4 * MAX_BYTES)
    except ValueError as err:
        raise ValueError(f"pretrained {name!r}: the weights do not match the model config in "
                         f"{meta_path.name} ({err})") from None
    bad = sorted(key for key, array in arrays.items() if not np.all(np.isfinite(array)))
    if bad:
        raise ValueError(f"pretrained {name!r}: {npz.name} holds NaN or inf in {bad[0]}"
                         f"{f' and {len(bad) - 1} more' if len(bad) > 1 else ''}; "
                         f"reinstall the package")
    params = traverse_util.unflatten_dict({k: jnp.asarray(a) for k, a in arrays.items()},
                                          sep="/")
    return Predictor(params=params, model=cfg.model, kind=cfg.model_kind, flowsim=cfg.flowsim,
                     source=f"pretrained:{name}", step=meta.get("step"))


def main(argv: Sequence[str] | None = None) -> int:
    """CLI: export a checkpoint's EMA weights as a shipped model."""
    parser = argparse.ArgumentParser(prog="python -m flowmaps_jax.pretrained",
                                     description="Export a checkpoint as a shipped model.")
    parser.add_argument("--checkpoint", required=True, help="run or checkpoint directory")
    parser.add_argument("--name", required=True, choices=NAMES)
    parser.add_argument("--which", choices=WHICH, default="latest",
                        help="the run's last step (latest, default: the shipped weights are the "
                             "runs' last steps) or its best-by-validation step (best)")
    parser.add_argument("--out", default=str(PRETRAINED_DIR), help="target directory")
    parser.add_argument("--note", default="", help="provenance note stored in the .json")
    parser.add_argument("--why", default="",
                        help="why this checkpoint was chosen, stored in the .json (default: "
                             "what the step is within its run)")
    args = parser.parse_args(argv)
    try:
        from flowmaps_jax.validation import check_output_dir

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
