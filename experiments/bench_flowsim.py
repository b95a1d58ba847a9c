"""Benchmark FlowSim generation: compile time and environments per second.

Counts layouts (with redraws), visiting orders and T-step rollouts, i.e. one full ``generate``
call, timed after compilation with ``block_until_ready``. Also reports CPU time (all threads),
which stays meaningful when other processes share the machine: on an otherwise idle machine with
n cores, wall time is at best CPU time / n.

    python experiments/bench_flowsim.py [--sizes 1000 10000 100000] [--repeats 5]
        [--world routine preferences dynamic mixed]

``--world`` generates a habit world (``flowsim.worlds``); with ``--history 8`` each timing also
reads every object's last 8 observations at every timestep out of the scenes (the model's and
the exact posterior's input), so the number is "environments with habits and histories / s".

Then the homes rows (``flowsim.homes``): ``generate_homes`` of 6-room 3-D homes with up to 15
objects over 4 weeks of hourly steps (672), per regime (``--homes``, default ``preferences``;
``--homes`` with no regime skips them), at ``--homes-sizes`` homes (default: each of ``--sizes``
capped at 1000).
"""

from __future__ import annotations

import argparse
import functools
import os
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.flowsim import HABIT_WORLDS, FlowSimConfig, generate, world_config
from flowmaps_jax.flowsim.homes import REGIMES, HomesConfig, generate_homes


def _timed(fn):
    wall, cpu = time.perf_counter(), time.process_time()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - wall, time.process_time() - cpu


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 100000])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--dynamics", default="markov", choices=["markov", "schedule_jitter"])
    parser.add_argument("--world", nargs="+", default=["routine"], choices=list(HABIT_WORLDS))
    parser.add_argument("--history", type=int, default=1,
                        help="also gather each object's last H observations at every timestep")
    parser.add_argument("--homes", nargs="*", default=["preferences"],
                        choices=[*REGIMES, "mixed"], help="homes regimes to time (none: skip)")
    parser.add_argument("--homes-sizes", type=int, nargs="+", default=None,
                        help="homes per call (default: each of --sizes, at most 1000)")
    args = parser.parse_args(argv)
    for world in args.world:
        config = world_config(world, FlowSimConfig(dynamics=args.dynamics))
        print(f"\nworld: {world} (habits {config.habits}), history H={args.history}")
        bench(config, args)
    sizes = args.homes_sizes or sorted({min(size, 1000) for size in args.sizes})
    for regime in args.homes:
        bench_homes(HomesConfig(regime=regime), sizes, args.repeats)


@functools.partial(jax.jit, static_argnums=1)
def _histories(scenes, h: int):
    """(E, T, M, H) slots seen at t − H + 1 … t for every t (−1 before the start): one compiled
    gather, as inside a training step, not H + 2 eager operations."""
    slot = jnp.pad(scenes.slot, ((0, 0), (h - 1, 0), (0, 0)), constant_values=-1)
    t = scenes.slot.shape[1]
    return jnp.stack([slot[:, i:i + t] for i in range(h)], axis=-1)


def bench(config: FlowSimConfig, args) -> None:
    def make(key, size):
        scenes = generate(key, size, config)
        return scenes, (_histories(scenes, args.history) if args.history > 1 else None)

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
        _, compile_wall, _ = _timed(lambda key=key, size=size: make(key, size))
        best_wall, best_cpu, redraws = np.inf, np.inf, []
        for repeat in range(args.repeats):
            key = jax.random.key(repeat + 1)
            (scenes, _), wall, cpu = _timed(lambda key=key, size=size: make(key, size))
            best_wall, best_cpu = min(best_wall, wall), min(best_cpu, cpu)
            redraws.append(np.asarray(scenes.layout_redraws))
        redraws = np.concatenate(redraws)
        print(f"{size:>8} {compile_wall:>10.2f} {best_wall:>12.4f} {size / best_wall:>13,.0f} "
              f"{best_cpu:>8.3f} {size / best_cpu:>10,.0f} "
              f"{np.mean(redraws):>12.3f}")
    print("redraw rate = mean layout redraws per environment "
          f"(fraction of environments redrawn at least once: {np.mean(redraws > 0):.3f})")


def bench_homes(config: HomesConfig, sizes: list[int], repeats: int) -> None:
    """One homes row per size: ``generate_homes`` timed after compilation."""
    print(f"\nhomes: regime {config.regime}, {config.num_rooms} rooms, up to "
          f"{config.max_receptacles} receptacles and {config.max_objects} objects, "
          f"T={config.num_hours} hours")
    print(f"{'homes':>8} {'compile s':>10} {'best wall s':>12} {'homes/s (wall)':>15} "
          f"{'cpu s':>8} {'homes/cpu-s':>12} {'objects':>8}")
    for size in sizes:
        _, compile_wall, _ = _timed(lambda size=size: generate_homes(jax.random.key(0), config,
                                                                     size))
        best_wall, best_cpu = np.inf, np.inf
        for repeat in range(repeats):
            homes, wall, cpu = _timed(lambda repeat=repeat, size=size: generate_homes(
                jax.random.key(repeat + 1), config, size))
            best_wall, best_cpu = min(best_wall, wall), min(best_cpu, cpu)
        objects = float(np.mean(np.sum(np.asarray(homes.object_valid), axis=1)))
        print(f"{size:>8} {compile_wall:>10.2f} {best_wall:>12.4f} {size / best_wall:>15,.0f} "
              f"{best_cpu:>8.3f} {size / best_cpu:>12,.0f} {objects:>8.1f}")


if __name__ == "__main__":
    main()
