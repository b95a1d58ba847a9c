"""Inference throughput: FlowMaps samples/s and the time of the exact log-likelihood.

Usage: python experiments/bench_sample.py [--preset paper] [--queries 100] [--samples 25]
       [--queries-per-scene 1] [--logp-queries 600] [--logp-draws 10] [--repeats 3]

* Sampling: ``--queries`` queries × ``--samples`` samples with the reference's 10-point midpoint
  grid (9 intervals × 2 = 18 velocity evaluations per sample). By default every query has its own
  scene (``--queries-per-scene 1``: one map encoding per query, the least sharing). Timed after
  compilation and a warm-up call; the median of ``--repeats`` calls.
* Likelihood: ``--logp-queries`` queries (3 per scene, as in the evaluation protocol)
  × ``--logp-draws`` boxes each, exact change of variables on the same 10-point midpoint
  grid, in chunks of 50 scenes as ``flowmaps_jax.evaluate`` runs it.

Random-init parameters (timing does not depend on the weights' values); synthetic scenes with 13
real tokens of 20, like FlowSim's 10 furniture pieces + 3 objects.
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import numpy as np

from flowmaps_jax.model import init_params
from flowmaps_jax.predictor import Predictor
from flowmaps_jax.tokens import Queries, SceneTokens
from flowmaps_jax.training.config import get_preset


def synthetic_inputs(num_scenes: int, queries_per_scene: int, max_tokens: int, seed: int = 0):
    """Valid SceneTokens (num_scenes, S) and Queries (num_scenes, queries_per_scene)."""
    rng = np.random.default_rng(seed)
    real = np.arange(max_tokens) < 13
    tau = rng.integers(0, 18, num_scenes).astype(np.int32)
    tokens = SceneTokens(
        boxes=np.where(real[None, :, None], rng.uniform(0, 0.7, (num_scenes, max_tokens, 4)),
                       0.0).astype(np.float32),
        descriptor=np.where(real, rng.integers(0, 6, (num_scenes, max_tokens)), 0).astype(np.int32),
        kind=np.broadcast_to(real & (np.arange(max_tokens) >= 10), (num_scenes, max_tokens)
                             ).astype(np.int32),
        mask=np.broadcast_to(real, (num_scenes, max_tokens)).copy(),
        tau=tau)
    queries = Queries(
        descriptor=rng.integers(0, 3, (num_scenes, queries_per_scene)).astype(np.int32),
        tau_q=np.broadcast_to(tau[:, None] + 1, (num_scenes, queries_per_scene)).astype(np.int32))
    return tokens, queries


def timed(fn, repeats: int) -> tuple[float, float, float]:
    """(first call incl. compilation, median wall time of ``repeats`` later calls, and the CPU
    time this process used per call over those calls) in seconds. CPU time / wall time shows how
    many of the cores the process actually got (the machine may be shared)."""
    start = time.perf_counter()
    jax.block_until_ready(fn(0))
    first = time.perf_counter() - start
    times = []
    cpu_start = time.process_time()
    for i in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(i + 1))
        times.append(time.perf_counter() - start)
    cpu = (time.process_time() - cpu_start) / repeats
    return first, float(np.median(times)), cpu


def _cores(cpu: float, wall: float) -> str:
    return f"{cpu / wall:.2f} of {os.cpu_count()} cores busy"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="paper", help="model size: paper, cpu or smoke")
    parser.add_argument("--queries", type=int, default=100)
    parser.add_argument("--samples", type=int, default=25)
    parser.add_argument("--queries-per-scene", type=int, default=1)
    parser.add_argument("--num-steps", type=int, default=10, help="ODE grid points")
    parser.add_argument("--logp-queries", type=int, default=600)
    parser.add_argument("--logp-draws", type=int, default=10)
    parser.add_argument("--chunk-scenes", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    preset = get_preset(args.preset)
    cfg, max_tokens = preset.model, preset.flowsim.max_tokens  # S: token slots per scene
    predictor = Predictor.from_params(init_params(jax.random.key(0), cfg), cfg,
                                      flowsim=preset.flowsim)
    n_params = sum(x.size for x in jax.tree_util.tree_leaves(predictor.params))
    print(f"{args.preset} model: {cfg}\n{n_params:,} parameters; devices {jax.devices()}")

    qps = args.queries_per_scene
    if args.queries % qps:
        raise SystemExit("--queries must be a multiple of --queries-per-scene")
    tokens, queries = synthetic_inputs(args.queries // qps, qps, max_tokens)
    evals = 2 * (args.num_steps - 1)

    def sample(i):
        return predictor.sample(tokens, queries, args.samples, jax.random.key(i),
                                num_steps=args.num_steps)

    first, median, cpu = timed(sample, args.repeats)
    total = args.queries * args.samples
    print(f"sample: {args.queries} queries ({qps} per scene) × {args.samples} samples, midpoint "
          f"{args.num_steps} grid points ({evals} velocity evaluations per sample): "
          f"{median:.3f} s → {total / median:,.0f} samples/s "
          f"(first call incl. compilation {first:.1f} s; {_cores(cpu, median)})")

    if args.logp_queries < 3 or args.logp_queries % 3:
        raise SystemExit("--logp-queries must be a positive multiple of 3 (3 objects per scene)")
    scenes = args.logp_queries // 3
    chunk = min(args.chunk_scenes, scenes)
    if scenes % chunk:
        raise SystemExit("--logp-queries / 3 must be a multiple of --chunk-scenes")
    tokens, queries = synthetic_inputs(chunk, 3, max_tokens, seed=1)
    x = jax.random.uniform(jax.random.key(2), (chunk, 3, args.logp_draws, 4)) * 0.5

    def log_prob(i):
        del i
        return [predictor.log_prob(tokens, queries, x, num_steps=args.num_steps)
                for _ in range(scenes // chunk)]

    first, median, cpu = timed(log_prob, max(1, args.repeats - 2))
    rows = args.logp_queries * args.logp_draws
    print(f"log_prob: {args.logp_queries} queries × {args.logp_draws} draws = {rows:,} boxes, "
          f"exact divergence, midpoint {args.num_steps} grid points, chunks of {chunk} scenes: "
          f"{median:.2f} s → {rows / median:,.0f} boxes/s "
          f"(first call incl. compilation {first:.1f} s; {_cores(cpu, median)})")


if __name__ == "__main__":
    main()
