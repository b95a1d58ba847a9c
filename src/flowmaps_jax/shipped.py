"""The trained default models shipped inside the package: which there are, and reading them safely.

The EMA weights of the `cpu`-preset runs documented in docs/results.md ("Shipped weights") live in
the data folder ``flowmaps_jax/pretrained/``: ``<name>.npz`` (float32 parameter arrays keyed by
their path in the params pytree) next to ``<name>.json`` (the run's config, model family, step,
source, which checkpoint of the run it is, ``"which": "best"`` or ``"latest"``, and why, and the
SHA-256 of the .npz, checked on load). Files written before ``which`` was recorded lack it:
:func:`describe` reports ``"unknown"`` for them (the shipped files are the runs' last steps,
docs/results.md). A plain ``pip install .`` carries them; nothing is downloaded. Reading trusts
neither file: the ``.json`` is size-limited and its fields are checked (a name, a model family, a
step that is a count, ``which`` if present), the ``.npz`` is read only after its SHA-256 matches,
with its members whitelisted (exactly the model's parameters, their declared shapes checked
before anything is decompressed) and every weight finite.

    from flowmaps_jax.predictor import load_pretrained
    predictor = load_pretrained("flowmaps")      # or "mlp", "mlp-learned"

:func:`read_weights` is what :func:`flowmaps_jax.predictor.load_pretrained` calls;
:mod:`flowmaps_jax.export` writes the files from a checkpoint
(``python -m flowmaps_jax.export --checkpoint runs/X/checkpoints --name mlp``).
"""

from __future__ import annotations

import hashlib
import io
import json
import pathlib
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np
from flax import traverse_util

from flowmaps_jax.checkpoint_reader import ModelSpec, model_spec
from flowmaps_jax.validation import read_npz

PRETRAINED_DIR = pathlib.Path(__file__).resolve().parent / "pretrained"
NAMES = ("flowmaps", "mlp", "mlp-learned",
         "flowmaps-preferences", "flowmaps-dynamic", "flowmaps-mixed",
         "flowmaps-preferences-h1", "flowmaps-dynamic-h1", "flowmaps-mixed-h1")
"""The shipped models: FlowMaps and the two MLP baselines (the paper's world, ``routine``), and
one FlowMaps per habits world (``flowsim.WORLDS``), trained with ``--preset habits --set
world=NAME``: ``flowmaps-<world>`` reads the last 8 maps, ``flowmaps-<world>-h1`` is the same
recipe reading one map (the "H = 1 model" reference row). A name starting with ``flowmaps``
holds a FlowMaps model, one starting with ``mlp`` the MLP baseline."""
MAX_BYTES = 12 * 1024 * 1024  # size budget per model: issue 8 set 10 MB; issue 33's mixture head
# (two more CDiT blocks for the table weights, 0.66M parameters) needs 11.3 MB
MAX_META_BYTES = 1024 * 1024  # a .json larger than this is not one export_pretrained wrote
WHICH = ("latest", "best")  # the checkpoint of a run that an export copies
UNKNOWN = "unknown"  # "which" of a .json written before it was recorded


def check_name(name) -> str:
    """``name`` if it is one of :data:`NAMES`, else ``ValueError`` listing them."""
    if not isinstance(name, str) or name not in NAMES:
        raise ValueError(f"name must be one of {list(NAMES)}; got {name!r}")
    return name


def available(directory: str | pathlib.Path = PRETRAINED_DIR) -> list[str]:
    """The names whose weights are present in ``directory``."""
    root = pathlib.Path(directory)
    return [n for n in NAMES if (root / f"{n}.npz").is_file() and (root / f"{n}.json").is_file()]


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


def _check_present(name: str, root: pathlib.Path) -> None:
    if name not in available(root):
        raise ValueError(f"pretrained weights {name!r} are not in {root} (present: "
                         f"{available(root) or 'none'})")


def describe(name: str, directory: str | pathlib.Path = PRETRAINED_DIR) -> dict:
    """What the shipped model ``name`` is, from its ``.json`` only (no weights are read):
    ``{"name", "kind", "step", "which", "why", "source", "note"}``. ``which`` is "latest" (the
    run's last step), "best" (its best-by-validation step) or "unknown" for a .json written
    before exports recorded it; ``why`` is then "". ValueError when the files are missing or
    the .json is not one :func:`flowmaps_jax.export.export_pretrained` wrote."""
    name = check_name(name)
    root = pathlib.Path(directory)
    _check_present(name, root)
    meta = _read_meta(name, root)
    return {"name": name, "kind": meta.get("kind"), "step": meta.get("step"),
            "which": meta.get("which", UNKNOWN), "why": meta.get("why", ""),
            "source": meta.get("source"), "note": meta.get("note", "")}


class ShippedWeights(NamedTuple):
    """Verified shipped weights: their ``name``, ``params`` pytree, the model ``spec`` their
    config describes, the training ``step`` and the checked ``.json`` as ``meta``."""

    name: str
    params: Any
    spec: ModelSpec
    step: int | None
    meta: dict


def read_weights(name: str, directory: str | pathlib.Path = PRETRAINED_DIR) -> ShippedWeights:
    """The shipped weights ``name`` ("flowmaps", "mlp" or "mlp-learned") in ``directory``, read
    and checked (see the module doc). Raises ``ValueError`` for an unknown name (listing the
    names), or weights that are missing, damaged (SHA-256 mismatch) or do not fit their
    config."""
    name = check_name(name)
    root = pathlib.Path(directory)
    npz, meta_path = root / f"{name}.npz", root / f"{name}.json"
    _check_present(name, root)
    for path, limit in ((meta_path, MAX_META_BYTES), (npz, 2 * MAX_BYTES)):
        if path.stat().st_size > limit:
            raise ValueError(f"pretrained {name!r}: {path.name} holds {path.stat().st_size:,} "
                             f"bytes, more than the {limit:,} a shipped model may have")
    try:
        meta = _check_meta(name, json.loads(meta_path.read_text()), meta_path.name)
        spec = model_spec(meta["config"])
    except (ValueError, KeyError, TypeError) as err:
        raise ValueError(f"pretrained {name!r}: unreadable {meta_path.name}: {err}") from None
    if meta.get("kind", spec.kind) != spec.kind:
        raise ValueError(f"pretrained {name!r}: {meta_path.name} names kind "
                         f"{str(meta.get('kind'))[:40]!r} but its config is a "
                         f"{spec.kind!r} model")
    data = npz.read_bytes()
    if hashlib.sha256(data).hexdigest() != meta["sha256"]:
        raise ValueError(f"pretrained {name!r}: {npz.name} is damaged (SHA-256 does not match "
                         f"{meta_path.name}); reinstall the package")
    abstract = spec.abstract_params()
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
    return ShippedWeights(name=name, params=params, spec=spec, step=meta.get("step"), meta=meta)
