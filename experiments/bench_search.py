"""Search throughput: episodes per second of each policy, after compilation.

Usage: python experiments/bench_search.py [--episodes 100000] [--tables 4] [--budget 10]
       [--repeats 3] [--p-miss 0.0]

Synthetic episodes shaped like FlowSim's (K tables of one kind on a 256 px map, a Dirichlet
belief, the object drawn from it, start at the map centre); ``--tables 7`` is the largest the
exact DP accepts. Every policy shares one compiled program (the policy is a traced index);
the time is the median of ``--repeats`` calls after a warm-up call. Target (issue 10):
≥ 100,000 episodes/s for the greedy policies, ≥ 10,000/s for the DP, on the 2-core CPU.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.search import POLICIES, Episodes, run_episodes


def synthetic_episodes(n: int, k: int, seed: int = 0) -> Episodes:
    """n episodes over k tables: Dirichlet(1) beliefs, the target drawn from each belief."""
    rng = np.random.default_rng(seed)
    belief = rng.dirichlet(np.ones(k), n).astype(np.float32)
    belief /= belief.sum(-1, keepdims=True)
    target = (belief.cumsum(-1) < rng.uniform(size=(n, 1))).sum(-1).clip(0, k - 1)
    return Episodes(belief=jnp.asarray(belief),
                    centres=jnp.asarray(rng.uniform(20, 236, (n, k, 2)), jnp.float32),
                    valid=jnp.ones((n, k), bool), start=jnp.full((n, 2), 128.0, jnp.float32),
                    target=jnp.asarray(target, jnp.int32))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=100_000)
    parser.add_argument("--tables", type=int, default=4, help="K tables per episode (≤ 7)")
    parser.add_argument("--budget", type=int, default=10, help="looks per episode")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--p-miss", type=float, default=0.0)
    args = parser.parse_args()
    episodes = synthetic_episodes(args.episodes, args.tables)
    print(f"jax {jax.__version__} on {jax.devices()[0].platform}, {os.cpu_count()} CPUs; "
          f"{args.episodes:,} episodes, K = {args.tables}, budget {args.budget}, "
          f"p_miss {args.p_miss}")
    start = time.perf_counter()
    jax.block_until_ready(run_episodes(episodes, POLICIES[0], budget=args.budget,
                                       p_miss=args.p_miss))
    print(f"compile + first call: {time.perf_counter() - start:.1f} s (shared by all policies)")
    for policy in POLICIES:
        jax.block_until_ready(run_episodes(episodes, policy, budget=args.budget,
                                           p_miss=args.p_miss))  # warm-up
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            out = jax.block_until_ready(run_episodes(episodes, policy, budget=args.budget,
                                                     p_miss=args.p_miss))
            times.append(time.perf_counter() - start)
        seconds = statistics.median(times)
        looks, travel = float(out.looks.mean()), float(out.travel.mean())
        print(f"{policy:>14}: {args.episodes / seconds:12,.0f} episodes/s  ({seconds:.3f} s; "
              f"mean looks {looks:.2f}, travel {travel:.1f} px)")


if __name__ == "__main__":
    main()
