"""Trained default models shipped inside the package: ``load_pretrained(name)`` and their export.

The EMA weights of the `cpu`-preset runs documented in docs/results.md ("Shipped weights") live in
``flowmaps_jax/pretrained/<name>.npz`` (float32 parameter arrays keyed by their path in the params
pytree) next to ``<name>.json`` (the run's TrainConfig, model kind, step, source, and the SHA-256
of the .npz, checked on load). A plain ``pip install .`` carries them; nothing is downloaded.

    from flowmaps_jax.sample import load_pretrained
    predictor = load_pretrained("flowmaps")      # or "mlp", "mlp-learned"

:func:`export_pretrained` writes the pair from a checkpoint (atomically: temporary files, then
renames), e.g. ``python -m flowmaps_jax.pretrained --checkpoint runs/X/checkpoints --name mlp``.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import pathlib
import sys
from collections.abc import Sequence

import numpy as np
from flax import traverse_util

PRETRAINED_DIR = pathlib.Path(__file__).resolve().parent / "pretrained"
NAMES = ("flowmaps", "mlp", "mlp-learned")
MAX_BYTES = 10 * 1024 * 1024  # the size budget per model


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
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def export_pretrained(checkpoint_dir: str | pathlib.Path, name: str,
                      directory: str | pathlib.Path = PRETRAINED_DIR,
                      which: str = "latest", note: str = "") -> pathlib.Path:
    """Copy a checkpoint's EMA weights into ``directory`` as ``name`` (.npz + .json).

    which: "latest" (the end of the run, default) or "best". Raises ``ValueError`` if the
    checkpoint is missing, holds a different model kind than the name implies, or is too big.
    Returns the path of the .npz.
    """
    from flowmaps_jax.sample import load
    from flowmaps_jax.training import checkpoint

    name = _check_name(name)
    predictor = load(checkpoint_dir, which=which)
    cfg = checkpoint.load_config(checkpoint.resolve_checkpoint_dir(checkpoint_dir))
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
            "source": str(checkpoint_dir), "note": note,
            "sha256": hashlib.sha256(data).hexdigest(), "config": cfg.to_dict()}
    _write_atomic(root / f"{name}.npz", data)
    _write_atomic(root / f"{name}.json", (json.dumps(meta, indent=2) + "\n").encode())
    return root / f"{name}.npz"


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
    data = npz.read_bytes()
    try:
        meta = json.loads(meta_path.read_text())
        cfg = TrainConfig.from_dict(meta["config"])
    except (ValueError, KeyError, TypeError) as err:
        raise ValueError(f"pretrained {name!r}: unreadable {meta_path.name}: {err}") from None
    if hashlib.sha256(data).hexdigest() != meta.get("sha256"):
        raise ValueError(f"pretrained {name!r}: {npz.name} is damaged (SHA-256 does not match "
                         f"{meta_path.name}); reinstall the package")
    with np.load(io.BytesIO(data)) as arrays:
        params = traverse_util.unflatten_dict({k: jnp.asarray(arrays[k]) for k in arrays.files},
                                              sep="/")
    expected = jax.eval_shape(objective_for(cfg).init, jax.random.key(0))
    got = jax.tree.map(lambda a: (a.shape, a.dtype), params)
    if jax.tree.map(lambda a: (a.shape, a.dtype), expected) != got:
        raise ValueError(f"pretrained {name!r}: the weights do not match the model config in "
                         f"{meta_path.name}")
    return Predictor(params=params, model=cfg.model, kind=cfg.model_kind, flowsim=cfg.flowsim,
                     source=f"pretrained:{name}", step=meta.get("step"))


def main(argv: Sequence[str] | None = None) -> int:
    """CLI: export a checkpoint's EMA weights as a shipped model."""
    parser = argparse.ArgumentParser(prog="python -m flowmaps_jax.pretrained",
                                     description="Export a checkpoint as a shipped model.")
    parser.add_argument("--checkpoint", required=True, help="run or checkpoint directory")
    parser.add_argument("--name", required=True, choices=NAMES)
    parser.add_argument("--which", choices=("latest", "best"), default="latest")
    parser.add_argument("--out", default=str(PRETRAINED_DIR), help="target directory")
    parser.add_argument("--note", default="", help="provenance note stored in the .json")
    args = parser.parse_args(argv)
    try:
        path = export_pretrained(args.checkpoint, args.name, args.out, args.which, args.note)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"wrote {path} ({path.stat().st_size / 2**20:.2f} MB) and {path.with_suffix('.json')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
