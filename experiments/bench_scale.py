"""Data-parallel scaling: training and sampling throughput on 1, 2, ... devices.

Each device count runs in a fresh subprocess. On a CPU-only machine the devices are forced host
devices (``XLA_FLAGS=--xla_force_host_platform_device_count=N``): they share the same cores, so
this shows the partitioning overhead, not a speed-up. On a GPU/TPU machine the first N real
devices are used.

    python experiments/bench_scale.py                         # cpu preset, 1 and 2 devices
    python experiments/bench_scale.py --devices 1 2 4 8       # a multi-GPU node
    python experiments/bench_scale.py --preset paper --set batch_size=256 --precision bf16

Training: query-samples per second (batch_size × Q per step) of the fused train step
(``flowmaps_jax.training.loop.compiled_functions``, as ``python -m flowmaps_jax.train`` runs
it), after compilation. Sampling: boxes per second of ``Predictor.sharded().sample`` (FlowMaps,
10-point midpoint solver) on ``--sample-scenes`` scenes × Q queries × N samples.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time


def measure(devices: int, preset: str, extra: list[str], steps: int, sample_scenes: int,
            sample_n: int, precision: str) -> dict:
    """Time training and sampling on ``devices`` devices (in this process)."""
    import jax

    from flowmaps_jax import distributed
    from flowmaps_jax.flowsim.scenes import scene_tokens, train_split
    from flowmaps_jax.sample import Predictor
    from flowmaps_jax.tokens import Queries
    from flowmaps_jax.training import loop
    from flowmaps_jax.training import state as train_state
    from flowmaps_jax.training.config import apply_overrides, get_preset

    cfg = apply_overrides(get_preset(preset), [*extra, f"devices={devices}",
                                               f"precision={precision}", "train_envs=512"])
    mesh = distributed.training_mesh(cfg.devices)
    compiled = loop.compiled_functions(cfg, mesh)
    scenes = distributed.replicate(train_split(cfg.flowsim, num_envs=cfg.train_envs), mesh)
    state = train_state.init_state(cfg, objective=compiled.objective, mesh=mesh)
    start = time.perf_counter()
    state, metrics = compiled.train_step(state, scenes)
    jax.block_until_ready(metrics)
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    for _ in range(steps):
        state, metrics = compiled.train_step(state, scenes)
    jax.block_until_ready((state, metrics))
    train_s = (time.perf_counter() - start) / steps

    predictor = Predictor.from_params(state.ema_params, cfg.model, cfg.model_kind,
                                      cfg.flowsim).sharded(devices)
    b, q = sample_scenes, cfg.queries_per_scene
    env = jax.numpy.arange(b) % cfg.train_envs
    tokens = jax.device_get(scene_tokens(jax.device_get(scenes), env, env % 10, cfg.flowsim))
    queries = Queries(descriptor=jax.numpy.broadcast_to(
        jax.numpy.asarray(cfg.flowsim.object_descriptors)[jax.numpy.arange(q) % 3], (b, q)
    ).astype("int32"),
        tau_q=jax.numpy.broadcast_to(tokens.tau[:, None] + 1, (b, q)).astype("int32"))
    key = jax.random.key(0)
    jax.block_until_ready(predictor.sample(tokens, queries, sample_n, key))  # compile
    reps = 3
    start = time.perf_counter()
    for i in range(reps):
        jax.block_until_ready(predictor.sample(tokens, queries, sample_n,
                                               jax.random.fold_in(key, i)))
    sample_s = (time.perf_counter() - start) / reps
    device = jax.devices()[0]
    return {"devices": devices, "platform": device.platform, "device_kind": device.device_kind,
            "preset": preset, "precision": precision, "batch": cfg.batch_size, "Q": q,
            "compile_s": compile_s, "step_s": train_s,
            "train_samples_per_s": cfg.batch_size * q / train_s,
            "sample_boxes_per_s": b * q * sample_n / sample_s, "sample_s": sample_s}


def _child_env(devices: int, accelerator: bool) -> dict[str, str]:
    env = dict(os.environ)
    if not accelerator:
        flags = env.get("XLA_FLAGS", "")
        env["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={devices}".strip()
        env["JAX_PLATFORMS"] = "cpu"
    return env


def _cpu_name() -> str:
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
        for line in out.splitlines():
            if line.startswith("Model name:"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--devices", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    parser.add_argument("--precision", default="float32", choices=("float32", "bf16"))
    parser.add_argument("--steps", type=int, default=10, help="timed train steps")
    parser.add_argument("--sample-scenes", type=int, default=64)
    parser.add_argument("--samples", type=int, default=25, help="boxes per query")
    parser.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    common = (args.preset, args.overrides, args.steps, args.sample_scenes, args.samples,
              args.precision)
    if args.child is not None:
        print("RESULT " + json.dumps(measure(args.child, *common)))
        return 0

    import jax  # the parent only asks which backend there is

    accelerator = jax.default_backend() != "cpu"
    rows = []
    for devices in args.devices:
        if accelerator and devices > jax.device_count():
            print(f"skipping {devices} devices: only {jax.device_count()} present")
            continue
        proc = subprocess.run([sys.executable, __file__, *sys.argv[1:], "--child", str(devices)],
                              capture_output=True, text=True, env=_child_env(devices, accelerator))
        lines = [x for x in proc.stdout.splitlines() if x.startswith("RESULT ")]
        if proc.returncode != 0 or not lines:
            print(proc.stdout[-2000:], proc.stderr[-4000:], file=sys.stderr)
            return 1
        rows.append(json.loads(lines[0][len("RESULT "):]))
    machine = (f"{rows[0]['platform']}: {rows[0]['device_kind']}" if accelerator
               else f"{_cpu_name()}, {os.cpu_count()} cores, forced host devices")
    print(f"# bench_scale: preset {args.preset} {' '.join(args.overrides)} "
          f"precision {args.precision}; {machine}")
    print("| devices | batch × Q | compile s | step ms | train samples/s | sample boxes/s |")
    print("|---|---|---|---|---|---|")
    base = rows[0]
    for r in rows:
        print(f"| {r['devices']} | {r['batch']} × {r['Q']} | {r['compile_s']:.1f} | "
              f"{1000 * r['step_s']:.1f} | {r['train_samples_per_s']:.0f} "
              f"({r['train_samples_per_s'] / base['train_samples_per_s']:.2f}×) | "
              f"{r['sample_boxes_per_s']:.0f} "
              f"({r['sample_boxes_per_s'] / base['sample_boxes_per_s']:.2f}×) |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
