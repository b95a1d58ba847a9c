"""How much does history help, exactly? Per FlowSim world, the exact posterior given the last H
observations (H = 1, 2, 4, 8) against the reference rows, no model involved.

Every row is scored against the exact posterior with H = 8 (the best any predictor that saw 8
observations can do; rows that saw less are scored fairly against it, since their information is
part of it): total variation, top-1 and the search-cost ratio (expected tables visited, visiting
by decreasing probability, over the least possible). "realised rank" is the mean rank of the
object's true table in each row's visiting order (lower is better; an unbiased estimate of the
expected search cost under the true habit).

    python experiments/habits_exact.py [--worlds routine preferences dynamic mixed]
        [--num-envs 400] [--seed 7]
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

from flowmaps_jax.evaluation.slots import slot_scores
from flowmaps_jax.flowsim import HABIT_WORLDS, empirical_frequency, generate, world_config
from flowmaps_jax.flowsim.habits import history_posterior, observed_history

HISTORIES = (1, 2, 4, 8)
REFERENCE_H = 8


def queries(scenes, config, rng):
    """One query per (environment, object): τ in 7 … 18 (8 observations exist), Δτ ≥ 1."""
    e, m, t = scenes.num_envs, config.num_objects, config.num_timesteps
    env, obj = np.repeat(np.arange(e), m), np.tile(np.arange(m), e)
    tau = rng.integers(REFERENCE_H - 1, t - 1, env.size)
    horizon = rng.integers(1, t - tau)
    return env, obj, tau, horizon


def realised_rank(p, truth, mask):
    """Mean rank (1 = first) of the true slot, visiting by decreasing p (ties: mean rank)."""
    p = np.where(mask, p, -np.inf)
    mine = np.take_along_axis(p, truth[:, None], 1)
    higher = np.sum(p > mine + 1e-6, axis=1)
    tied = np.sum(np.abs(p - mine) <= 1e-6, axis=1) - 1
    return 1.0 + higher + 0.5 * tied


def score_world(world: str, num_envs: int, seed: int) -> dict[str, dict[str, float]]:
    config = world_config(world)
    scenes = generate(jax.random.key(seed), num_envs, config)
    env, obj, tau, horizon = queries(scenes, config, np.random.default_rng(seed))
    f = config.num_furniture
    mask = np.arange(f) < np.asarray(scenes.num_slots)[env, obj][:, None]
    truth = np.asarray(scenes.slot)[env, tau + horizon, obj]
    exact = {h: np.asarray(history_posterior(scenes, config, env, obj, tau, horizon, h))
             for h in HISTORIES}
    history, valid = observed_history(scenes, env, obj, tau, REFERENCE_H)
    rows = {f"exact, H = {h}": exact[h] for h in HISTORIES}
    rows[f"empirical frequency, H = {REFERENCE_H}"] = np.asarray(
        empirical_frequency(history, valid, f))
    rows["last-seen"] = np.eye(f)[np.asarray(history)[:, -1]]
    rows["uniform over the kind"] = mask / mask.sum(1, keepdims=True)
    q = exact[REFERENCE_H]
    out = {}
    for name, p in rows.items():
        p_hat = np.concatenate([p, np.zeros((p.shape[0], 1))], axis=1)
        s = slot_scores(p_hat.astype(np.float32), q.astype(np.float32), mask)
        out[name] = {"tv": float(np.mean(s["tv"])), "top1": float(np.mean(s["top1"])),
                     "cost_ratio": float(np.mean(s["search_cost_ratio"])),
                     "rank": float(np.mean(realised_rank(p, truth, mask))),
                     "rank_se": float(np.std(realised_rank(p, truth, mask)) / np.sqrt(p.shape[0]))}
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", nargs="+", default=list(HABIT_WORLDS),
                        choices=list(HABIT_WORLDS))
    parser.add_argument("--num-envs", type=int, default=400)
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args(argv)
    for world in args.worlds:
        result = score_world(world, args.num_envs, args.seed)
        print(f"\n### world: {world} ({args.num_envs} environments, "
              f"{args.num_envs * 3} queries; scored against exact, H = {REFERENCE_H})\n")
        print("| row | TV | top-1 | search-cost ratio | realised rank |")
        print("|---|---|---|---|---|")
        for name, r in result.items():
            print(f"| {name} | {r['tv']:.3f} | {r['top1']:.3f} | {r['cost_ratio']:.3f} | "
                  f"{r['rank']:.3f} ± {r['rank_se']:.3f} |")


if __name__ == "__main__":
    main()
