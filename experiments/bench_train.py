"""Training throughput and peak memory at the ``paper`` and ``cpu`` presets.

Throughput is query-samples per second = batch_size × Q × steps / seconds, measured after
compilation (the first step is timed separately as "compile"), with the fused jitted train step
(batch drawn from a FlowSim split inside the step, as ``python -m flowmaps_jax.train`` does).
Each (preset, Q) runs in a fresh subprocess so its peak resident memory (``ru_maxrss``) and its
compile time are its own.

    python experiments/bench_train.py                       # paper + cpu presets, Q in 1 4 8
    python experiments/bench_train.py --presets cpu --queries 1 2 4 8 --steps 20
    python experiments/bench_train.py --presets cpu --queries 8 --set model.head=velocity ...
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time


def measure(preset: str, queries: int, steps: int, envs: int, batch: int | None,
            extra: list[str] | tuple[str, ...] = ()) -> dict:
    """Compile + time ``steps`` fused train steps for one configuration (in this process)."""
    import jax

    from flowmaps_jax.flowsim.scenes import train_split
    from flowmaps_jax.training import objectives
    from flowmaps_jax.training import state as train_state
    from flowmaps_jax.training.config import apply_overrides, get_preset

    overrides = {"queries_per_scene": queries, "train_envs": envs}
    if batch is not None:
        overrides["batch_size"] = batch
    cfg = apply_overrides(apply_overrides(get_preset(preset), list(extra)), overrides)
    scenes = train_split(cfg.flowsim, num_envs=cfg.train_envs)
    objective = objectives.objective_for(cfg)
    state = train_state.init_state(cfg, objective=objective)
    step_fn = train_state.make_fused_train_step(cfg, objective)
    jax.block_until_ready((scenes, state))

    start = time.perf_counter()
    state, metrics = step_fn(state, scenes)
    jax.block_until_ready(metrics)
    compile_s = time.perf_counter() - start

    start = time.perf_counter()
    for _ in range(steps):
        state, metrics = step_fn(state, scenes)
    jax.block_until_ready((state, metrics))
    seconds = time.perf_counter() - start
    n_params = sum(x.size for x in jax.tree.leaves(state.params))
    return {
        "preset": preset, "dim": cfg.model.dim,
        "layers": f"{cfg.model.encoder_layers}+{cfg.model.cdit_blocks}",
        "batch": cfg.batch_size, "Q": queries, "params": int(n_params),
        "compile_s": compile_s, "step_s": seconds / steps,
        "samples_per_s": cfg.batch_size * queries * steps / seconds,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "loss": float(metrics["loss"]),
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--presets", nargs="+", default=["paper", "cpu"])
    parser.add_argument("--queries", nargs="+", type=int, default=[1, 4, 8])
    parser.add_argument("--steps", type=int, default=None,
                        help="timed steps (default: 3 for paper, 10 otherwise)")
    parser.add_argument("--envs", type=int, default=256,
                        help="training-split size (does not affect speed)")
    parser.add_argument("--batch", type=int, default=None, help="override the preset's batch")
    parser.add_argument("--set", dest="extra", action="append", default=[], metavar="KEY=VALUE",
                        help="config overrides applied to every preset (label gets a '*')")
    parser.add_argument("--one", nargs=2, metavar=("PRESET", "Q"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)

    if args.one:  # child process: measure one configuration, print JSON
        preset, q = args.one[0], int(args.one[1])
        steps = args.steps or (3 if preset == "paper" else 10)
        print(json.dumps(measure(preset, q, steps, args.envs, args.batch, args.extra)))
        return

    import jax

    print(f"jax {jax.__version__} on {jax.devices()[0].device_kind}; "
          f"query-samples/s after compilation; peak RSS per subprocess")
    header = (f"{'preset':<6} {'D':>4} {'layers':>6} {'B':>4} {'Q':>3} {'params':>9} "
              f"{'compile s':>9} {'step s':>7} {'samples/s':>10} {'peak MB':>8}")
    print(header)
    print("-" * len(header))
    failed = []
    for preset in args.presets:
        for q in args.queries:
            cmd = [sys.executable, __file__, "--one", preset, str(q), "--envs", str(args.envs)]
            if args.steps:
                cmd += ["--steps", str(args.steps)]
            if args.batch:
                cmd += ["--batch", str(args.batch)]
            for item in args.extra:
                cmd += ["--set", item]
            out = subprocess.run(cmd, capture_output=True, text=True, check=False)
            if out.returncode != 0:
                print(f"{preset:<6} Q={q}: failed\n{out.stderr[-2000:]}")
                failed.append(f"{preset} Q={q}")
                continue
            r = json.loads(out.stdout.strip().splitlines()[-1])
            label = r["preset"] + ("*" if args.extra else "")
            print(f"{label:<6} {r['dim']:>4} {r['layers']:>6} {r['batch']:>4} {r['Q']:>3} "
                  f"{r['params']:>9,} {r['compile_s']:>9.1f} {r['step_s']:>7.3f} "
                  f"{r['samples_per_s']:>10.0f} {r['peak_rss_mb']:>8.0f}", flush=True)
    if failed:  # the other rows are printed; the exit code still says that some failed
        raise SystemExit(f"failed: {', '.join(failed)}")


if __name__ == "__main__":
    main()
