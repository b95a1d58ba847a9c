"""Forward+backward throughput of the CFM loss (query-samples/s) at a given model size.

Usage: python experiments/bench_model.py [--queries 1 4 8] [--batch 256] [--steps 5]
       [--dim 256 --encoder-layers 8 --cdit-blocks 8 --heads 8] [--slots 13] [--sampling]
       [--no-training]

``--sampling`` also times inference: 100 scenes × 1 query × 25 samples, encoder once, then the
default midpoint solver (10 grid points, 18 velocity evaluations), in samples/s.

B scenes × Q queries per scene share one encoder pass; a query-sample is one (scene, query) pair.
Timing starts after compilation and one warm-up step; dropout is on (as in training). Each line
prints samples per wall-second and per CPU-second (user + sys of this process, all threads); on a
shared machine the CPU-normalised number is the steadier one (on an idle 2-core machine wall ≈
CPU / 2 when both cores are busy).
"""

from __future__ import annotations

import argparse
import resource
import time

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.flow import integrate
from flowmaps_jax.flowsim import FlowSimConfig
from flowmaps_jax.model import ModelConfig, encode, init_params, make_velocity_fn
from flowmaps_jax.model.flowmaps_family import cfm_loss
from flowmaps_jax.tokens import Queries, SceneTokens, TrainBatch


def synthetic_batch(key, batch: int, queries: int, config: ModelConfig,
                    slots: int | None = None) -> TrainBatch:
    """Random but valid batch: 13 real tokens in ``slots`` (default FlowSim's max_tokens) slots,
    τ in [0, 18], τ_q in (τ, 19]."""
    s = FlowSimConfig().max_tokens if slots is None else slots
    k_box, k_desc, k_tau, k_tq, k_tgt = jax.random.split(key, 5)
    tau = jax.random.randint(k_tau, (batch,), 0, config.tau_max - 1)
    tau_q = jax.random.randint(k_tq, (batch, queries), tau[:, None] + 1, config.tau_max)
    tokens = SceneTokens(
        boxes=jax.random.uniform(k_box, (batch, s, 4)) * 0.25,
        descriptor=jax.random.randint(k_desc, (batch, s), 0, config.num_descriptors),
        kind=(jnp.arange(s) >= 10).astype(jnp.int32)[None].repeat(batch, 0),
        mask=(jnp.arange(s) < 13)[None].repeat(batch, 0),
        tau=tau)
    qs = Queries(descriptor=jax.random.randint(k_desc, (batch, queries), 0, 3), tau_q=tau_q)
    return TrainBatch(tokens=tokens, queries=qs,
                      target=jax.random.uniform(k_tgt, (batch, queries, 4)) * 0.5)


def cpu_seconds() -> float:
    """User + system CPU time of this process (all threads), in seconds."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def time_calls(fn, steps: int) -> tuple[float, float, float]:
    """Run ``fn()`` once to compile and warm up, then ``steps`` times.

    Returns (compile+first-call wall s, median wall s per call, mean CPU s per call). The CPU time
    (user + sys over all threads) is less sensitive to other processes on a shared machine.
    """
    t0 = time.perf_counter()
    jax.block_until_ready(fn(0))
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(fn(1))  # warm-up
    walls, cpu0 = [], cpu_seconds()
    for i in range(steps):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(2 + i))
        walls.append(time.perf_counter() - t0)
    return compile_s, float(np.median(walls)), (cpu_seconds() - cpu0) / steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--queries", type=int, nargs="+", default=[1, 4, 8])
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--dim", type=int, default=256)
    parser.add_argument("--encoder-layers", type=int, default=8)
    parser.add_argument("--cdit-blocks", type=int, default=8)
    parser.add_argument("--heads", type=int, default=8)
    parser.add_argument("--slots", type=int, default=None,
                        help="token slots S per scene (13 real; default max_tokens = 20)")
    parser.add_argument("--sampling", action="store_true", help="also time ODE sampling")
    parser.add_argument("--no-training", action="store_true", help="skip the training benchmark")
    args = parser.parse_args()
    config = ModelConfig(dim=args.dim, encoder_layers=args.encoder_layers,
                         cdit_blocks=args.cdit_blocks, heads=args.heads)
    params = init_params(jax.random.key(0), config)
    n_params = sum(x.size for x in jax.tree_util.tree_leaves(params))
    print(f"{config}\nparameters: {n_params:,}  devices: {jax.devices()}")
    grad_fn = jax.jit(jax.value_and_grad(cfm_loss, has_aux=True), static_argnames="config")
    for q in [] if args.no_training else args.queries:
        batch = synthetic_batch(jax.random.key(1), args.batch, q, config, args.slots)
        compile_s, step, cpu = time_calls(
            lambda i: grad_fn(params, config, batch, jax.random.key(2 + i)), args.steps)  # noqa: B023
        n = args.batch * q
        print(f"B={args.batch} Q={q}: {step * 1e3:7.1f} ms/step wall (median of {args.steps}), "
              f"{n / step:7.1f} query-samples/s wall, {cpu * 1e3:7.1f} CPU-ms/step, "
              f"{n / cpu:7.1f} query-samples/CPU-s (compile+first step {compile_s:.1f} s)")
    if args.sampling:
        bench_sampling(params, config, steps=args.steps, slots=args.slots)


def bench_sampling(params, config: ModelConfig, scenes: int = 100, samples: int = 25,
                   steps: int = 3, slots: int | None = None) -> None:
    """Samples/s of encode-once + midpoint integration (all samples of a query share c)."""
    batch = synthetic_batch(jax.random.key(1), scenes, 1, config, slots)

    @jax.jit
    def sample(params, key):
        context = encode(params, config, batch.tokens)
        field = make_velocity_fn(params, config, context, batch.queries)
        return integrate(field, jax.random.normal(key, (scenes, 1, samples, 4)))

    compile_s, run, cpu = time_calls(lambda i: sample(params, jax.random.key(2 + i)), steps)
    n = scenes * samples
    print(f"sampling {scenes} queries x {samples} samples (midpoint, 18 evals): {run:.3f} s wall, "
          f"{n / run:.1f} samples/s wall, {cpu:.3f} CPU-s, {n / cpu:.1f} samples/CPU-s "
          f"(compile+first call {compile_s:.1f} s)")


if __name__ == "__main__":
    main()
