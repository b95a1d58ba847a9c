"""Compile time: how long XLA takes to build FlowMaps' programs, under chosen XLA_FLAGS.

Usage: python experiments/bench_compile.py [--preset smoke] [--parts sample log_prob train]
       [--flags none xla_cpu_use_fusion_emitters=false] [--optimised] [--repeats 1]

Compilation, not running, is most of the test suite's time (tiny models, a few steps each), so
this is the number to measure when choosing the suite's compiler settings (tests/conftest.py).
Each ``--flags`` variant (``none``: XLA's defaults; otherwise XLA flags without their leading
``--``, several joined by commas) runs in its own child process (XLA reads ``XLA_FLAGS`` once,
at start), which builds the ``--preset``'s model and times, for each part, the lowering (Python
tracing and StableHLO) and the backend compile of:

* ``sample``: :func:`flowmaps_jax.model.flowmaps_family.flow_sample` (64 samples, the 10-point
  grid);
* ``log_prob``: :func:`flowmaps_jax.model.flowmaps_family.flow_log_prob` (64 boxes per query);
* ``train``: the fused train step (:func:`flowmaps_jax.training.state.make_fused_train_step`).

By default the children compile as the suite does, with ``JAX_DISABLE_MOST_OPTIMIZATIONS=true``;
``--optimised`` turns that off (what a training run gets). The persistent compilation cache is
off in the children, so every compile is a real one. Prints one line per variant and part, and
the median over ``--repeats`` children.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

PARTS = ("sample", "log_prob", "train")
DEFAULT_FLAGS = ("none", "xla_cpu_use_fusion_emitters=false")


def xla_flags(variant: str) -> str:
    """``none`` (or "") → ""; ``a=1,b=2`` → ``--a=1 --b=2`` (argparse reads no value starting
    "--")."""
    if variant == "none":
        return ""
    return " ".join("--" + f.strip().lstrip("-") for f in variant.split(",") if f.strip())


def _child(preset: str, parts: list[str]) -> dict[str, tuple[float, float]]:
    """In the child process: {part: (lowering seconds, backend compile seconds)}."""
    import jax

    from flowmaps_jax.flowsim import generate
    from flowmaps_jax.model.flowmaps_family import flow_log_prob, flow_sample
    from flowmaps_jax.training import state as train_state
    from flowmaps_jax.training.config import get_preset
    from flowmaps_jax.worlds.flowsim import default_batch_fn

    cfg = get_preset(preset)
    scenes = generate(jax.random.key(0), max(cfg.batch_size, 8), cfg.flowsim)
    state = train_state.init_state(cfg, jax.random.key(0))
    batch = jax.jit(default_batch_fn(cfg))(jax.random.key(1), scenes)
    b, q = batch.queries.tau_q.shape
    keys = jax.random.split(jax.random.key(2), b)
    boxes = jax.numpy.full((b, q, 64, 4), 0.5)
    lowerers = {
        "sample": lambda: flow_sample.lower(state.params, cfg.model, batch.tokens, batch.queries,
                                            keys, 64),
        "log_prob": lambda: flow_log_prob.lower(state.params, cfg.model, batch.tokens,
                                                batch.queries, boxes),
        "train": lambda: train_state.make_fused_train_step(cfg).lower(state, scenes),
    }
    out = {}
    for part in parts:
        start = time.perf_counter()
        lowered = lowerers[part]()
        lowered_at = time.perf_counter()
        lowered.compile()
        out[part] = (lowered_at - start, time.perf_counter() - lowered_at)
    return out


def _run_child(flags: str, args) -> dict[str, tuple[float, float]]:
    env = dict(os.environ, XLA_FLAGS=xla_flags(flags), JAX_ENABLE_COMPILATION_CACHE="false")
    env["JAX_DISABLE_MOST_OPTIMIZATIONS"] = "false" if args.optimised else "true"
    proc = subprocess.run([sys.executable, __file__, "--child", "--preset", args.preset,
                           "--parts", *args.parts], env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"the child with XLA_FLAGS={flags!r} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="smoke", help="training preset whose model is compiled")
    p.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS))
    p.add_argument("--flags", nargs="+", default=list(DEFAULT_FLAGS),
                   help="XLA_FLAGS variants, one child each: none, or flags without their leading "
                        "-- joined by commas")
    p.add_argument("--optimised", action="store_true",
                   help="compile with XLA's optimisations (default: as the test suite does)")
    p.add_argument("--repeats", type=int, default=1, help="children per variant (median)")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.repeats < 1:
        raise SystemExit("--repeats must be at least 1")
    if args.child:
        print(json.dumps(_child(args.preset, args.parts)))
        return
    mode = "optimised" if args.optimised else "JAX_DISABLE_MOST_OPTIMIZATIONS=true"
    print(f"preset {args.preset}, {mode}, median of {args.repeats} child process(es); seconds")
    print(f"{'XLA_FLAGS':<44} {'part':<9} {'lower':>7} {'compile':>8}")
    for flags in args.flags:
        runs = [_run_child(flags, args) for _ in range(args.repeats)]
        for part in args.parts:
            lower = statistics.median(r[part][0] for r in runs)
            compile_ = statistics.median(r[part][1] for r in runs)
            print(f"{xla_flags(flags) or '(none)':<44} {part:<9} {lower:7.2f} {compile_:8.2f}")


if __name__ == "__main__":
    main()
