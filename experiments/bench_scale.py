"""Data-parallel scaling: training and sampling throughput on 1, 2, ... devices.

Each device count runs in a fresh subprocess. On a CPU-only machine the devices are forced host
devices (``XLA_FLAGS=--xla_force_host_platform_device_count=N``): they share the same cores, so
this shows the partitioning overhead, not a speed-up. On a GPU/TPU machine the first N real
devices are used.

    python experiments/bench_scale.py                         # cpu preset, 1 and 2 devices
    python experiments/bench_scale.py --devices 1 2 4 8       # a multi-GPU node
    python experiments/bench_scale.py --preset paper --set batch_size=256 --precision float32 bf16

Training: query-samples per second (batch_size × Q per step) of the fused train step
(``flowmaps_jax.training.loop.compiled_functions``, as ``python -m flowmaps_jax.train`` runs
it), after compilation. Sampling: boxes per second of ``Predictor.sharded().sample`` (FlowMaps,
10-point midpoint solver) on ``--sample-scenes`` scenes × Q queries × N samples.
Agreement: every row starts from the same params and draws the same batches, so each row's
losses and final params are compared with the first row's (largest relative loss difference
over the steps, largest absolute param difference): device counts differ only in float
summation order, bf16 by its rounding.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import subprocess
import sys
import tempfile
import time

import numpy as np


def measure(devices: int, precision: str, params_out: str, preset: str, extra: list[str],
            steps: int, sample_scenes: int, sample_n: int) -> dict:
    """Time training and sampling on ``devices`` devices (in this process); the final params
    go to ``params_out`` (.npz) for the parent's comparison."""
    import jax

    from flowmaps_jax import distributed
    from flowmaps_jax.flowsim.scenes import scene_tokens, train_split
    from flowmaps_jax.predictor import Predictor
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
    losses = [metrics["loss"]]
    start = time.perf_counter()
    for _ in range(steps):
        state, metrics = compiled.train_step(state, scenes)
        losses.append(metrics["loss"])  # kept on device: no sync inside the timed loop
    jax.block_until_ready((state, metrics))
    train_s = (time.perf_counter() - start) / steps
    np.savez(params_out, *[np.asarray(x) for x in jax.tree.leaves(state.params)])

    predictor = Predictor.from_params(state.ema_params, cfg.model, cfg.family,
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
            "sample_boxes_per_s": b * q * sample_n / sample_s, "sample_s": sample_s,
            "losses": [float(x) for x in jax.device_get(losses)]}


def _child_env(devices: int, accelerator: bool) -> dict[str, str]:
    env = dict(os.environ)
    if not accelerator:
        flags = env.get("XLA_FLAGS", "")
        env["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={devices}".strip()
        env["JAX_PLATFORMS"] = "cpu"
    return env


def _cpu_name() -> str:
    with contextlib.suppress(OSError):
        out = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
        for line in out.splitlines():
            if line.startswith("Model name:"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown CPU"


def _run_child(devices: int, precision: str, params_out: str, accelerator: bool) -> dict:
    """One row, measured in a fresh subprocess."""
    child = ["--child", str(devices), precision, params_out]
    proc = subprocess.run([sys.executable, __file__, *sys.argv[1:], *child], capture_output=True,
                          text=True, env=_child_env(devices, accelerator))
    lines = [x for x in proc.stdout.splitlines() if x.startswith("RESULT ")]
    if proc.returncode != 0 or not lines:
        raise SystemExit(f"{devices} devices, {precision} failed:\n{proc.stdout[-2000:]}"
                         f"{proc.stderr[-4000:]}")
    return json.loads(lines[0][len("RESULT "):])


def _differences(row: dict, base: dict) -> tuple[float, float]:
    """(largest relative loss difference over the steps, largest absolute param difference)."""
    loss, ref = np.asarray(row["losses"]), np.asarray(base["losses"])
    with np.load(row["params"]) as a, np.load(base["params"]) as b:
        params = max(float(np.max(np.abs(a[k] - b[k]))) for k in a.files)
    return float(np.max(np.abs(loss - ref) / np.abs(ref))), params


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--devices", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    parser.add_argument("--precision", nargs="+", default=["float32"],
                        choices=("float32", "bf16"), help="one row per precision and device count")
    parser.add_argument("--steps", type=int, default=10, help="timed train steps")
    parser.add_argument("--sample-scenes", type=int, default=64)
    parser.add_argument("--samples", type=int, default=25, help="boxes per query")
    parser.add_argument("--child", nargs=3, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    common = (args.preset, args.overrides, args.steps, args.sample_scenes, args.samples)
    if args.child is not None:
        devices, precision, params_out = args.child
        print("RESULT " + json.dumps(measure(int(devices), precision, params_out, *common)))
        return 0

    import jax  # the parent only asks which backend there is

    accelerator = jax.default_backend() != "cpu"
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for precision in args.precision:
            for devices in args.devices:
                if accelerator and devices > jax.device_count():
                    print(f"skipping {devices} devices: only {jax.device_count()} present")
                    continue
                params_out = f"{tmp}/{precision}-{devices}.npz"
                rows.append({**_run_child(devices, precision, params_out, accelerator),
                             "params": params_out})
        base = rows[0]
        diffs = [_differences(r, base) for r in rows]
    machine = (f"{rows[0]['platform']}: {rows[0]['device_kind']}" if accelerator
               else f"{_cpu_name()}, {os.cpu_count()} cores, forced host devices")
    print(f"# bench_scale: preset {args.preset} {' '.join(args.overrides)}; {machine}; "
          f"{args.steps + 1} train steps from the same start, compared with the first row")
    print("| devices | precision | batch × Q | compile s | step ms | train samples/s "
          "| sample boxes/s | max rel. Δloss | max abs. Δparam |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r, (d_loss, d_param) in zip(rows, diffs, strict=True):
        print(f"| {r['devices']} | {r['precision']} | {r['batch']} × {r['Q']} | "
              f"{r['compile_s']:.1f} | {1000 * r['step_s']:.1f} | "
              f"{r['train_samples_per_s']:.0f} "
              f"({r['train_samples_per_s'] / base['train_samples_per_s']:.2f}×) | "
              f"{r['sample_boxes_per_s']:.0f} "
              f"({r['sample_boxes_per_s'] / base['sample_boxes_per_s']:.2f}×) | "
              f"{d_loss:.1e} | {d_param:.1e} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
