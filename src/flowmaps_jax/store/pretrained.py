"""The pretrained models packaged with flowmaps-jax: which there are, reading them safely, and
writing them from a checkpoint (docs/results.md, "Shipped weights").

In ``flowmaps_jax/pretrained/``: ``<name>.npz`` (float32 parameters keyed by their path in the
params pytree) and ``<name>.json`` (config, family, step, source, ``which`` and why, the
``.npz``'s SHA-256, and its ``seal``: one SHA-256 over the canonical ``.json`` and the ``.npz``
bytes, :func:`seal`). Reading trusts neither file: the ``.json`` is size-limited and checked,
nothing is used before the seal matches, then the ``.npz`` is read with its members
whitelisted (shapes checked before decompression) and every weight finite
(:func:`read_weights`, what :func:`flowmaps_jax.predictor.load_pretrained` calls).
:func:`export_pretrained` writes the files (``python -m flowmaps_jax.export``).
"""

from __future__ import annotations

import hashlib
import io
import json
import pathlib
import re
from typing import Any, NamedTuple

import jax
import numpy as np
from flax import traverse_util

from flowmaps_jax.atomic_files import make_output_dir, write_files
from flowmaps_jax.store import checkpoints
from flowmaps_jax.store.checkpoints import WHICH
from flowmaps_jax.store.model_spec import ModelSpec, model_spec
from flowmaps_jax.untrusted_files import parse_json, read_npz
from flowmaps_jax.validation import (
    check_choice,
    check_instance,
    check_int,
    check_keys,
    check_output_dir,
    prefix_errors,
)

PRETRAINED_DIR = pathlib.Path(__file__).resolve().parents[1] / "pretrained"
PREFIX = "pretrained:"
"""A model spec starting with this names pretrained weights (``pretrained:flowmaps``)."""
"""The package data folder holding the pretrained weights."""
NAMES = ("flowmaps", "mlp", "mlp-learned",
         "flowmaps-preferences", "flowmaps-dynamic", "flowmaps-mixed",
         "flowmaps-preferences-h1", "flowmaps-dynamic-h1", "flowmaps-mixed-h1",
         "flowmaps-homes")
"""The pretrained models: FlowMaps and the two MLP baselines (the paper's world, ``routine``),
and one FlowMaps per habits world (``flowsim.HABIT_WORLDS``), trained with ``--preset habits --set
world=NAME``: ``flowmaps-<world>`` reads the last 8 maps, ``flowmaps-<world>-h1`` is the same
recipe reading one map (the "H = 1 model" reference row); ``flowmaps-homes`` is the FlowSim
homes model (``--preset homes``, :class:`flowmaps_jax.predictor.Predictor`). A name
starting with ``mlp`` holds the MLP baseline, ``flowmaps-homes`` the homes model, any other
starting with ``flowmaps`` a FlowMaps model."""
MAX_BYTES = 12 * 1024 * 1024  # size budget per model: issue 8 set 10 MB; issue 33's mixture head
# (two more CDiT blocks for the table weights, 0.66M parameters) needs 11.3 MB
MAX_META_BYTES = 1024 * 1024  # a .json larger than this is not one export_pretrained wrote
UNKNOWN = "unknown"  # "which" of a .json written before it was recorded
SEAL_FORMAT = 1
"""The version of the ``seal`` field (:func:`seal`) this code writes and reads."""


HOLDS = {**{name: ("flowmaps", None) for name in NAMES}, "mlp": ("mlp", "mean"),
         "mlp-learned": ("mlp", "learned"), "flowmaps-homes": ("flowmaps-homes", None)}
"""What each pretrained name holds: (its model family, the MLP's ``baseline_variance`` or
None)."""


def available(directory: str | pathlib.Path = PRETRAINED_DIR) -> list[str]:
    """The names whose weights are present in ``directory``."""
    root = pathlib.Path(directory)
    return [n for n in NAMES if (root / f"{n}.npz").is_file() and (root / f"{n}.json").is_file()]


# --------------------------------------------------------------------------------------------
# Reading


def seal(meta: dict, npz_bytes: bytes) -> dict:
    """The ``seal`` field of a weights ``.json`` whose other fields are ``meta`` and whose
    ``.npz`` holds ``npz_bytes``: ``{"format": SEAL_FORMAT, "sha256": ...}``, the SHA-256 of
    the canonical JSON of ``meta`` (sorted keys, no spaces, ASCII; a ``seal`` in it is
    ignored) followed by the ``.npz`` bytes. Any change to a field's value, name or type, or to
    a weight byte, changes it."""
    fields = {key: value for key, value in meta.items() if key != "seal"}
    canonical = json.dumps(fields, sort_keys=True, separators=(",", ":"), ensure_ascii=True,
                           allow_nan=False)
    digest = hashlib.sha256(f"flowmaps-jax pretrained seal {SEAL_FORMAT}\n".encode())
    digest.update(canonical.encode() + b"\n")
    digest.update(npz_bytes)
    return {"format": SEAL_FORMAT, "sha256": digest.hexdigest()}


def check_seal(name: str, meta: dict, npz_bytes: bytes) -> None:
    """``ValueError`` unless ``meta`` (a weights ``.json``) carries the :func:`seal` of itself
    and ``npz_bytes``: a ``.json`` or ``.npz`` changed after the export is refused, naming the
    file that changed (the ``.npz`` when its own SHA-256 no longer matches)."""
    held = meta.get("seal")
    if held is None:
        raise ValueError(f"pretrained {name!r}: {name}.json is not sealed (written before its "
                         f"config was sealed with its weights); re-seal it once with python -m "
                         f"flowmaps_jax.store.reseal DIRECTORY (or export it again)")
    if not isinstance(held, dict) or held.get("format") != SEAL_FORMAT:
        raise ValueError(f"pretrained {name!r}: {name}.json has a seal of an unknown format "
                         f"({str(held)[:60]}); this code reads format {SEAL_FORMAT}")
    if held != seal(meta, npz_bytes):
        damaged = f"{name}.npz" if hashlib.sha256(npz_bytes).hexdigest() != meta["sha256"] \
            else f"{name}.json"
        raise ValueError(f"pretrained {name!r}: {damaged} is damaged (the seal over the "
                         f"config and the weights does not match); reinstall the package")


def _read_limited(name: str, path: pathlib.Path, limit: int) -> bytes:
    """The bytes of the file ``path`` of the pretrained model ``name``, if it holds at most
    ``limit`` bytes (a larger one is not one :func:`export_pretrained` wrote)."""
    if path.stat().st_size > limit:
        raise ValueError(f"pretrained {name!r}: {path.name} holds {path.stat().st_size:,} "
                         f"bytes, more than the {limit:,} a pretrained model may have")
    return path.read_bytes()


def _read_meta(name: str, root: pathlib.Path) -> dict:
    """The checked ``.json`` of the weights ``name`` in ``root``: both files present, its size
    first, then the fields the loader uses or reports (``name`` must be the model's own)."""
    if name not in available(root):
        raise ValueError(f"pretrained weights {name!r} are not in {root} (present: "
                         f"{available(root) or 'none'})")
    file = f"{name}.json"
    text = _read_limited(name, root / file, MAX_META_BYTES)
    meta = parse_json(f"pretrained {name!r}: {file}", text)  # its depth bounded
    check_keys(f"pretrained {name!r}: {file}", meta)  # a JSON object
    where = f"pretrained {name!r}: {file} "
    if meta.get("step") is not None:
        check_int(where + "step", meta["step"], 0)
    check_choice(where + "which", meta.get("which", UNKNOWN), (*WHICH, UNKNOWN))
    check_instance(where + "why", meta.get("why", ""), str)
    digest = meta.get("sha256")
    if not (isinstance(digest, str) and re.fullmatch("[0-9a-f]{64}", digest)):
        raise ValueError(f"{where}sha256 must be a SHA-256 hex digest; got {str(digest)[:40]!r}")
    check_instance(where + "config", meta.get("config"), dict)
    if meta.get("seal") is not None:
        check_instance(where + "seal", meta["seal"], dict)
    check_choice(where + "name", meta.get("name", name), (name,))
    return meta


def describe(name: str, directory: str | pathlib.Path = PRETRAINED_DIR) -> dict:
    """What the pretrained model ``name`` is, from its ``.json`` only (no weights are read):
    ``{"name", "kind", "step", "which", "why", "source", "note"}``. ``which`` is "latest" (the
    run's last step), "best" (its best-by-validation step) or "unknown" for a .json written
    before exports recorded it; ``why`` is then "". ValueError when the files are missing or
    the .json is not one :func:`export_pretrained` wrote."""
    check_choice("name", name, NAMES)
    meta = _read_meta(name, pathlib.Path(directory))
    return {"name": name, "kind": meta.get("kind"), "step": meta.get("step"),
            "which": meta.get("which", UNKNOWN), "why": meta.get("why", ""),
            "source": meta.get("source"), "note": meta.get("note", "")}


class PretrainedWeights(NamedTuple):
    """Verified pretrained weights: their ``name``, ``params`` pytree, the model ``spec`` their
    config describes, the training ``step`` and the checked ``.json`` as ``meta``."""

    name: str
    params: Any
    spec: ModelSpec
    step: int | None
    meta: dict


def read_weights(name: str, directory: str | pathlib.Path = PRETRAINED_DIR) -> PretrainedWeights:
    """The pretrained weights ``name`` (one of :data:`NAMES`) in ``directory``, read and checked
    (see the module doc). Raises ``ValueError`` for an unknown name (listing the names), or
    weights that are missing, damaged (the seal over the .json and the .npz does not match) or
    do not fit their config."""
    check_choice("name", name, NAMES)
    root = pathlib.Path(directory)
    npz, meta_path = root / f"{name}.npz", root / f"{name}.json"
    meta = _read_meta(name, root)
    data = _read_limited(name, npz, 2 * MAX_BYTES)
    check_seal(name, meta, data)  # the config is trusted from here on, as the weights are
    with prefix_errors(f"pretrained {name!r}: unreadable {meta_path.name}: ",
                       also=(KeyError, TypeError)):
        spec = model_spec(meta["config"])
    if meta.get("kind", spec.family_name) != spec.family_name:  # "kind": the family's name
        raise ValueError(f"pretrained {name!r}: {meta_path.name} names kind "
                         f"{str(meta.get('kind'))[:40]!r} but its config is a "
                         f"{spec.family_name!r} model")
    abstract = spec.abstract_params()
    expected = {key: (leaf.shape, leaf.dtype)
                for key, leaf in traverse_util.flatten_dict(abstract, sep="/").items()}
    # members whitelisted and their sizes checked before anything is decompressed
    with prefix_errors(f"pretrained {name!r}: the weights do not match the model config in "
                       f"{meta_path.name}: "):
        arrays = read_npz(npz.name, io.BytesIO(data), expected=expected, max_bytes=4 * MAX_BYTES)
    bad = sorted(key for key, array in arrays.items() if not np.all(np.isfinite(array)))
    if bad:
        raise ValueError(f"pretrained {name!r}: {npz.name} holds NaN or inf in {bad[0]}"
                         f"{f' and {len(bad) - 1} more' if len(bad) > 1 else ''}; "
                         f"reinstall the package")
    params = traverse_util.unflatten_dict({k: jax.device_put(a) for k, a in arrays.items()},
                                          sep="/")
    return PretrainedWeights(name=name, params=params, spec=spec, step=meta.get("step"),
                             meta=meta)


# --------------------------------------------------------------------------------------------
# Writing


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
                      directory: str | pathlib.Path,
                      which: str = "best", note: str = "", why: str = "") -> pathlib.Path:
    """Copy a checkpoint's EMA weights into ``directory`` as ``name`` (.npz + .json, both
    written to temporary files, then renamed: never one without the other). ``directory`` has
    no default: the package's own :data:`PRETRAINED_DIR` is written only when it is named.

    which: "best" (default: the step evaluate and search load by default, lowest validation
    score; a run without one exports its latest step, and the .json says so) or "latest" (the
    end of the run). The .json records ``which`` and ``why``: the given reason, or by default
    what the step is within its run (its last step or its best, and the step of the other),
    and the run's config as the checkpoint stored it. Raises ``ValueError`` if the checkpoint
    is missing, holds a different model family than the name implies, or is too big. Returns
    the path of the .npz.
    """
    # before anything is read or written
    check_choice("name", name, NAMES)
    check_choice("which", which, WHICH)
    check_instance("why", why, str)
    check_output_dir("directory", directory, files=[f"{name}.npz", f"{name}.json"])
    ckpt_root = checkpoints.resolve_checkpoint_dir(checkpoint_dir)
    best_step = next(iter(checkpoints.saved_steps(ckpt_root, checkpoints.BEST)), None)
    latest_step = next(iter(checkpoints.saved_steps(ckpt_root, checkpoints.LATEST)), None)
    fallback = which == "best" and best_step is None
    if fallback:  # as load() does: the latest save
        which = "latest"
    weights = checkpoints.load_weights(checkpoint_dir, which=which)
    family_name, model = weights.spec.family_name, weights.spec.model
    expected, variant = HOLDS[name]  # and for an MLP, its variance head
    held = getattr(model, "baseline_variance", None) if variant is not None else None
    if (family_name, held) != (expected, variant):
        def what(family, variance):
            return f"a {family!r} model" + (f" with baseline_variance={variance!r}"
                                             if variance else "")
        raise ValueError(f"checkpoint_dir holds {what(family_name, held)}; name {name!r} needs "
                         f"{what(expected, variant)}")
    data = _params_bytes(weights.params)
    if len(data) > MAX_BYTES:
        raise ValueError(f"{name}: {len(data) / 2**20:.1f} MB of weights, over the "
                         f"{MAX_BYTES / 2**20:.0f} MB budget")
    root = make_output_dir("directory", directory)
    meta = {"name": name, "kind": family_name, "step": weights.step,
            "source": str(checkpoint_dir), "which": which,
            "why": why or (("--which best, but " if fallback else "")
                           + _default_why(which, weights.step, best_step, latest_step)),
            "note": note,
            "sha256": hashlib.sha256(data).hexdigest(), "config": weights.restored.config}
    meta["seal"] = seal(meta, data)
    text = json.dumps(meta, indent=2) + "\n"
    write_files({root / f"{name}.npz": data, root / f"{name}.json": text},
                name="directory file")  # temporary files, then the renames
    return root / f"{name}.npz"
