"""Benchmark FlowSim generation: compile time and environments per second.

Counts layouts (with redraws), visiting orders and T-step rollouts, i.e. one full ``generate``
call, timed after compilation with ``block_until_ready``. Also reports CPU time (all threads),
which stays meaningful when other processes share the machine: on an otherwise idle machine with
n cores, wall time is at best CPU time / n.

    python experiments/bench_flowsim.py [--sizes 1000 10000 100000] [--repeats 5]
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import jax
import numpy as np

from flowmaps_jax.flowsim import FlowSimConfig, generate


def _timed(fn):
    wall, cpu = time.perf_counter(), time.process_time()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - wall, time.process_time() - cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 100000])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--dynamics", default="markov", choices=["markov", "schedule_jitter"])
    args = parser.parse_args()

    config = FlowSimConfig(dynamics=args.dynamics)
    print(f"jax {jax.__version__} on {jax.devices()[0].platform}, {os.cpu_count()} CPU cores, "
          f"{platform.processor() or platform.machine()}, load average "
          f"{os.getloadavg()[0]:.1f}")
    print(f"config: F={config.num_furniture} M={config.num_objects} T={config.num_timesteps} "
          f"map={config.map_size} candidates={config.layout_candidates} "
          f"dynamics={config.dynamics}")
    print(f"{'envs':>8} {'compile s':>10} {'best wall s':>12} {'env/s (wall)':>13} "
          f"{'cpu s':>8} {'env/cpu-s':>10} {'redraw rate':>12}")
    for size in args.sizes:
        key = jax.random.key(0)
        _, compile_wall, _ = _timed(lambda key=key, size=size: generate(key, size, config))
        best_wall, best_cpu, redraws = np.inf, np.inf, []
        for repeat in range(args.repeats):
            key = jax.random.key(repeat + 1)
            scenes, wall, cpu = _timed(lambda key=key, size=size: generate(key, size, config))
            best_wall, best_cpu = min(best_wall, wall), min(best_cpu, cpu)
            redraws.append(np.asarray(scenes.layout_redraws))
        redraws = np.concatenate(redraws)
        print(f"{size:>8} {compile_wall:>10.2f} {best_wall:>12.4f} {size / best_wall:>13,.0f} "
              f"{best_cpu:>8.3f} {size / best_cpu:>10,.0f} "
              f"{np.mean(redraws):>12.3f}")
    print("redraw rate = mean layout redraws per environment "
          f"(fraction of environments redrawn at least once: {np.mean(redraws > 0):.3f})")


if __name__ == "__main__":
    main()
