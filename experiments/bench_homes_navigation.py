"""Homes navigation throughput: episodes per second of each policy, and prior evaluations per
second of each reference row, after compilation.

Usage: python experiments/bench_homes_navigation.py [--homes 1000] [--queries 100]
       [--dp-episodes 20000] [--prior-homes 200] [--prior-queries 3] [--repeats 3]
       [--regime mixed]

Episodes: ``--homes`` × ``--queries`` queries on generated homes (``homes.draw_queries``), each
with a Dirichlet(1) belief over the object's allowed receptacles (the scoring posterior is the
same belief); "most-probable" and "nearest" time the jitted, vmapped simulator (visiting order
+ walk + scores), "optimal" the exact subset DP on the first ``--dp-episodes`` episodes (grouped
by size on the host). Priors: each reference row on ``--prior-homes`` × ``--prior-queries``
queries (the exact posterior reads the last 168 hours). Times are medians of ``--repeats``
calls after a warm-up call. Target (issue 35): ≥ 100,000 episodes/s for the simulator.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.evaluation import priors as pr
from flowmaps_jax.flowsim.homes import HomesConfig, generate_homes
from flowmaps_jax.flowsim.homes.queries import draw_queries
from flowmaps_jax.navigation import navigation as nav


def median_seconds(fn, repeats: int) -> float:
    jax.block_until_ready(fn())  # warm-up (compiles)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def dirichlet_beliefs(key, allowed) -> jax.Array:
    """(E, Q, R) Dirichlet(1) beliefs over the allowed receptacles."""
    g = jax.random.gamma(key, 1.0, allowed.shape)
    g = jnp.where(allowed, g, 0.0)
    return g / g.sum(-1, keepdims=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--homes", type=int, default=1000)
    parser.add_argument("--queries", type=int, default=100, help="queries per home")
    parser.add_argument("--dp-episodes", type=int, default=20_000)
    parser.add_argument("--prior-homes", type=int, default=200)
    parser.add_argument("--prior-queries", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--regime", default="mixed")
    args = parser.parse_args()
    config = HomesConfig(regime=args.regime)
    key = jax.random.key(0)
    homes = generate_homes(key, config, args.homes)
    queries = draw_queries(jax.random.fold_in(key, 1), homes, config, args.queries)
    n = args.homes * args.queries
    allowed = pr.allowed_slots(homes, queries)
    belief = dirichlet_beliefs(jax.random.fold_in(key, 2), allowed)
    _, start_distance = nav.start_points(homes, config)
    print(f"jax {jax.__version__} on {jax.devices()[0].platform}, {os.cpu_count()} CPUs; "
          f"{n:,} episodes ({args.homes} homes x {args.queries} queries), regime "
          f"{args.regime}, allowed receptacles per object {float(allowed.sum(-1).mean()):.2f} "
          f"on average (max {int(allowed.sum(-1).max())})")
    for policy in ("most-probable", "nearest"):
        def simulate(policy=policy):
            orders = nav.visit_orders(policy, belief, homes, queries, start_distance)
            return nav.walk_orders(orders, homes, queries, belief, start_distance)

        seconds = median_seconds(simulate, args.repeats)
        looks = float(np.asarray(simulate()["looks"]).mean())
        print(f"{policy:>14}: {n / seconds:12,.0f} episodes/s  ({seconds:.3f} s; mean looks "
              f"{looks:.2f})")
    m = min(args.dp_episodes, n)
    per_home = -(-m // args.queries)
    sub = jax.tree.map(lambda x: x[:per_home], homes)
    subq = jax.tree.map(lambda x: x[:per_home], queries)
    seconds = median_seconds(lambda: nav.optimal_orders(belief[:per_home], sub, subq,
                                                        start_distance[:per_home]),
                             args.repeats)
    count = per_home * args.queries
    print(f"{'optimal':>14}: {count / seconds:12,.0f} episodes/s  ({seconds:.3f} s for "
          f"{count:,} episodes; exact subset DP)")
    ph = min(args.prior_homes, args.homes)
    ph_homes = jax.tree.map(lambda x: x[:ph], homes)
    ph_queries = draw_queries(jax.random.fold_in(key, 3), ph_homes, config, args.prior_queries)
    count = ph * args.prior_queries
    rows = {"exact (H = 168)": pr.exact_prior(config), "frequency (H = 168)":
            pr.frequency_prior(), "last-seen": pr.last_seen_prior(), "uniform": pr.uniform_prior}
    for name, prior in rows.items():
        seconds = median_seconds(lambda prior=prior: prior(ph_homes, ph_queries), args.repeats)
        print(f"prior {name:>20}: {count / seconds:12,.0f} prior evaluations/s  "
              f"({seconds:.4f} s for {count:,} queries)")


if __name__ == "__main__":
    main()
