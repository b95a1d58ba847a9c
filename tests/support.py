"""Shared test helpers (importable from every test module; fixtures live in conftest.py).

One tiny model config (``TINY``) for every test that only needs *a* model: sharing the static
config means sharing compiled functions across test modules, which is most of the suite's time.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Sequence

import jax
import numpy as np

from flowmaps_jax.model import ModelConfig
from flowmaps_jax.tokens import Queries, SceneTokens

# A low max_frequency keeps a random velocity field smooth (Lipschitz ~ 10, not ~ 1000), so float
# rounding is not amplified chaotically along the ODE and comparisons can stay tight.
TINY = ModelConfig(dim=16, encoder_layers=1, cdit_blocks=1, heads=2, mlp_ratio=2, dropout=0.0,
                   freq_bands=4, max_frequency=8.0, baseline_hidden=16)
SLOTS, FURNITURE = 20, 10  # FlowSim's token slots and tables


def perturb(params, key: jax.Array, scale=0.3):
    """Noise of std ``scale`` on every parameter, so zero-initialised layers (AdaLN-Zero gates,
    final projections) become active and the model's output is non-trivial. The noise is drawn
    on the host, leaf by leaf in tree order, by numpy's generator seeded with the key's data:
    deterministic in ``key``, and no XLA program to compile; the leaves come back on device."""
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key)).ravel().tolist())
    leaves, treedef = jax.tree_util.tree_flatten(params)
    return treedef.unflatten(jax.device_put(
        [np.asarray(x) + (scale * rng.standard_normal(np.shape(x))).astype(x.dtype)
         for x in leaves]))


def synthetic_tokens(seed: int, num_real: Sequence[int] = (13, 13), slots: int = SLOTS,
                     tau: Sequence[int] | None = None, max_box: float = 0.7) -> SceneTokens:
    """Valid scenes (numpy): scene b has ``num_real[b]`` real tokens, the first ``FURNITURE`` of
    them tables and the rest objects, random boxes in [0, max_box] and descriptors in 0..5,
    padded to ``slots``; tau defaults to 2, 3, ..."""
    rng = np.random.default_rng(seed)
    b = len(num_real)
    real = np.arange(slots)[None] < np.asarray(num_real)[:, None]
    boxes = np.where(real[..., None], rng.uniform(0.0, max_box, (b, slots, 4)), 0.0)
    return SceneTokens(
        boxes=boxes.astype(np.float32),
        descriptor=np.where(real, rng.integers(0, 6, (b, slots)), 0).astype(np.int32),
        kind=((np.arange(slots) >= FURNITURE)[None] & real).astype(np.int32),
        mask=real,
        tau=np.asarray(np.arange(b) + 2 if tau is None else tau, np.int32))


def synthetic_queries(tokens: SceneTokens, q: int, tau_max: int = 20) -> Queries:
    """Q queries per scene of ``tokens``: object categories 0, 1, 2, 0, ... at τ + 1, τ + 2, ...
    (capped at τ_max − 1)."""
    b = len(tokens.tau)
    tau_q = np.minimum(np.asarray(tokens.tau)[:, None] + 1 + np.arange(q)[None], tau_max - 1)
    return Queries(descriptor=np.broadcast_to(np.arange(q) % 3, (b, q)).astype(np.int32),
                   tau_q=tau_q.astype(np.int32))


# --------------------------------------------------------------------------- a toy KL problem

# Two real slots of a 3-slot padded problem: boxes (y, x, h, w), square objects like FlowSim's.
BOXES = np.array([[0.20, 0.30, 0.10, 0.10],
                  [0.60, 0.50, 0.10, 0.10],
                  [0.00, 0.00, 0.00, 0.00]], np.float32)
MASK = np.array([True, True, False])
Q = np.array([0.3, 0.7, 0.0], np.float32)
SHEAR = np.array([[1, 0, -0.5, 0], [0, 1, 0, -0.5], [0, 0, 1, 0], [0, 0, 0, 1]], np.float64)
"""(cy, cx, h, w) → (y, x, h, w): a component's covariance in box coordinates is S Σ Sᵀ."""


def protocol_sd(box) -> np.ndarray:
    return np.array([0.35 * box[2], 0.35 * box[3], 0.02 * box[2], 0.02 * box[3]], np.float64)


def mixture_log_density(x, weights, boxes) -> np.ndarray:
    """log Σ_k w_k N(c(x); c(b_k), diag σ_k²) in float64, written out by hand. x (..., 4)."""
    x = np.asarray(x, np.float64)
    cx = np.stack([x[..., 0] + x[..., 2] / 2, x[..., 1] + x[..., 3] / 2, x[..., 2], x[..., 3]], -1)
    terms = []
    for w, b in zip(weights, np.asarray(boxes, np.float64), strict=True):
        if w > 0:
            mu, sd = np.array([b[0] + b[2] / 2, b[1] + b[3] / 2, b[2], b[3]]), protocol_sd(b)
            terms.append(np.log(w) + np.sum(-0.5 * ((cx - mu) / sd) ** 2
                                            - np.log(sd * np.sqrt(2 * np.pi)), axis=-1))
    return np.logaddexp.reduce(terms, axis=0)


# --------------------------------------------------------------------------- commands in-process


def run_python_in_process(args: Sequence[str], cwd) -> tuple[int, str]:
    """``python ARGS`` (``-m MODULE ...`` or ``SCRIPT.py ...``) run in this process, in ``cwd``:
    (exit code, stdout and stderr together).

    Much cheaper than a subprocess in a test session: JAX and the package are imported once and
    every ``jax.jit`` cache is shared. What ``python`` would do is kept: ``-m MODULE`` calls the
    module's ``main(argv)`` (a package's ``__main__`` module), as its ``__main__`` block does, and
    a script runs as ``__main__`` (:func:`runpy.run_path`) with ``sys.argv`` set and its folder
    first on ``sys.path``. The exit code is that of ``sys.exit(main())``: an uncaught exception
    is 1 (its traceback in the output), ``SystemExit("message")`` is 1 with the message. Use a
    subprocess where the process itself is under test (signals, a fresh interpreter, the
    environment JAX starts with)."""
    import importlib
    import io
    import os
    import runpy
    import sys
    import traceback

    args = list(args)
    out = io.StringIO()
    saved_argv, saved_path, saved_cwd = sys.argv[:], sys.path[:], os.getcwd()
    code: object = 0
    os.chdir(cwd)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
            try:
                if args[0] == "-m":
                    module = importlib.import_module(args[1])
                    if not hasattr(module, "main") and hasattr(module, "__path__"):
                        module = importlib.import_module(args[1] + ".__main__")
                    sys.argv = [args[1], *args[2:]]
                    code = module.main(args[2:])
                else:
                    sys.argv = [args[0], *args[1:]]
                    sys.path.insert(0, os.path.dirname(os.path.abspath(args[0])))
                    runpy.run_path(args[0], run_name="__main__")
            except SystemExit as exit_:
                code = exit_.code
            except Exception:  # what the interpreter does with an uncaught exception
                traceback.print_exc()
                code = 1
            if code is not None and not isinstance(code, int):  # sys.exit("message")
                print(code, file=sys.stderr)
                code = 1
    finally:
        sys.argv, sys.path[:] = saved_argv, saved_path
        os.chdir(saved_cwd)
    return code or 0, out.getvalue()


@contextlib.contextmanager
def fast_compile():
    """XLA's ``jax_disable_most_optimizations`` on inside (what ``JAX_DISABLE_MOST_OPTIMIZATIONS``
    does for a new process): about half the compile time of the tiny end-to-end runs, where
    compilation dominates; the programs are the same, only their machine code is less optimised.
    The flag is not part of ``jax.jit``'s cache key, so a test module that uses this clears JAX's
    caches when it is done (``jax.clear_caches()`` in a module-scoped fixture): later tests in
    the process compile their own optimised programs."""
    previous = jax.config.read("jax_disable_most_optimizations")
    jax.config.update("jax_disable_most_optimizations", True)
    try:
        yield
    finally:
        jax.config.update("jax_disable_most_optimizations", previous)


def run_cli(main, argv, capsys) -> tuple[int, str, str]:
    """``main(argv)`` → (exit code, stdout, stderr); argparse errors exit with 2."""
    try:
        code = main(argv)
    except SystemExit as exit_info:
        code = exit_info.code
    out = capsys.readouterr()
    return code, out.out, out.err


def error_line(err: str) -> str:
    """The one ``error:`` line of stderr (asserted to be one)."""
    lines = [line for line in err.strip().splitlines() if "error:" in line]
    assert len(lines) == 1, err
    return lines[0]


def only_error_line(err: str) -> str:
    """The error line of stderr, which holds nothing else but argparse's usage lines."""
    lines = [line for line in err.strip().splitlines() if line.strip()]
    errors = [i for i, line in enumerate(lines) if "error:" in line]
    assert errors and errors[-1] == len(lines) - 1, err
    assert len(errors) == 1 and "Traceback" not in err, err
    assert errors[0] == 0 or lines[0].startswith("usage:"), err
    return lines[-1]


def unsaved_run(run_dir, config: dict):
    """What a run of ``config`` (its dict) leaves when it is killed before its first checkpoint."""
    (run_dir / "checkpoints" / "last" / "10.orbax-checkpoint-tmp-1").mkdir(parents=True)
    (run_dir / "checkpoints" / "best").mkdir()
    (run_dir / "config.json").write_text(json.dumps(config))
    (run_dir / "metrics.jsonl").write_text('{"kind": "train", "step": 5, "loss": 9.0}\n')
    return run_dir
