"""Score models trained on a habits world against the exact posterior given the history.

For each model (a run directory, a checkpoint directory or ``pretrained:NAME``) and the world its
config names, held-out environments of that world, one query per (environment, object) with τ in
7 … 18 (so 8 observations exist) and Δτ ≥ 1. Rows: each model (its table weights, read without
sampling; mass on tables of another kind counts as "off"), the exact posterior given the last
1 / 8 observations, the empirical frequency of the last 8, last-seen and uniform over the kind.
Every row is scored against the exact posterior with H = 8, as experiments/habits_exact.py does:
TV, top-1, search-cost ratio, and the mean rank of the true table (realised rank), per habit.

    python experiments/habits_model.py --checkpoint runs/habits-preferences [--num-envs 400]

``--by-horizon`` adds, per habit, the search-cost ratio and top-1 of each model and of the exact
posterior given one map, by Δτ (1 … 5, then 6 and more): where a model's excess over the exact
answer comes from.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np
from habits_exact import realised_rank  # experiments/ is on the path when run as a script

from flowmaps_jax.evaluation.slots import slot_scores
from flowmaps_jax.flowsim import HABITS, empirical_frequency, generate
from flowmaps_jax.flowsim.habits import history_posterior, hypothesis_table, observed_history
from flowmaps_jax.flowsim.scenes import scene_tokens
from flowmaps_jax.flowsim.worlds import world_of
from flowmaps_jax.predictor import load_model
from flowmaps_jax.tokens import Queries

REFERENCE_H = 8
TEST_SEED = 2026
CHUNK = 256


def model_slots(predictor, scenes, config, env, obj, tau, tau_q):
    """(N, F + 1) the model's mass on each slot of the queried object's order, off bin last."""
    h = predictor.model.history
    out = []
    for start in range(0, env.size, CHUNK):
        part = slice(start, start + CHUNK)
        tokens = scene_tokens(scenes, env[part], tau[part], config, history=h)
        queries = Queries(descriptor=jnp.asarray(scenes.object_kind)[env[part], obj[part]][:, None],
                          tau_q=jnp.asarray(tau_q[part])[:, None])
        w = np.asarray(predictor.table_weights(tokens, queries))[:, 0]  # (n, S + 1)
        order = np.asarray(scenes.visit_order)[env[part], obj[part]]  # (n, F)
        slots = np.where(order >= 0, np.take_along_axis(w, np.maximum(order, 0), axis=1), 0.0)
        out.append(np.concatenate([slots, 1.0 - slots.sum(1, keepdims=True)], axis=1))
    return np.concatenate(out).clip(0.0, 1.0)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", nargs="+", required=True)
    parser.add_argument("--num-envs", type=int, default=400)
    parser.add_argument("--which", default="best", choices=["best", "latest"])
    parser.add_argument("--by-horizon", action="store_true",
                        help="also tabulate the models and exact H = 1 by Δτ, per habit")
    args = parser.parse_args(argv)
    predictors = [load_model(spec, which=args.which) for spec in args.checkpoint]
    config = predictors[0].flowsim
    world = world_of(config)
    scenes = generate(jax.random.key(TEST_SEED), args.num_envs, config)
    m, t, f = config.num_objects, config.num_timesteps, config.num_furniture
    rng = np.random.default_rng(TEST_SEED)
    env, obj = np.repeat(np.arange(args.num_envs), m), np.tile(np.arange(m), args.num_envs)
    tau = rng.integers(REFERENCE_H - 1, t - 1, env.size)
    horizon = rng.integers(1, t - tau)
    mask = np.arange(f) < np.asarray(scenes.num_slots)[env, obj][:, None]
    truth = np.asarray(scenes.slot)[env, tau + horizon, obj]
    q = np.asarray(history_posterior(scenes, config, env, obj, tau, horizon, REFERENCE_H))
    history, valid = observed_history(scenes, env, obj, tau, REFERENCE_H)
    off = np.zeros((env.size, 1))
    rows = {}
    for spec, predictor in zip(args.checkpoint, predictors, strict=True):
        rows[f"{spec} (H = {predictor.model.history}, step {predictor.step})"] = model_slots(
            predictor, scenes, config, env, obj, tau, tau + horizon)
    for h in (1, REFERENCE_H):
        rows[f"exact, H = {h}"] = np.concatenate([np.asarray(history_posterior(
            scenes, config, env, obj, tau, horizon, h)), off], 1)
    rows[f"empirical frequency, H = {REFERENCE_H}"] = np.concatenate(
        [np.asarray(empirical_frequency(history, valid, f)), off], 1)
    rows["last-seen"] = np.concatenate([np.eye(f)[np.asarray(history)[:, -1]], off], 1)
    rows["uniform over the kind"] = np.concatenate([mask / mask.sum(1, keepdims=True), off], 1)
    family = hypothesis_table(f)[0][np.asarray(scenes.habit)[env, obj]]
    print(f"world: {world} ({args.num_envs} held-out environments, {env.size} queries; "
          f"scored against exact, H = {REFERENCE_H})")
    for fam in np.unique(family):
        sel = family == fam
        print(f"\n### habit: {HABITS[fam]} ({sel.sum()} queries)\n")
        print("| row | TV | top-1 | search-cost ratio | realised rank | off |")
        print("|---|---|---|---|---|---|")
        for name, p in rows.items():
            s = slot_scores(p[sel].astype(np.float32), q[sel].astype(np.float32), mask[sel])
            rank = realised_rank(p[sel, :-1], truth[sel], mask[sel])
            print(f"| {name} | {np.mean(s['tv']):.3f} | {np.mean(s['top1']):.3f} | "
                  f"{np.mean(s['search_cost_ratio']):.4f} | {rank.mean():.3f} ± "
                  f"{rank.std() / np.sqrt(rank.size):.3f} | {np.mean(p[sel, -1]):.3f} |")
        if args.by_horizon:
            by_horizon({k: v[sel] for k, v in rows.items()}, q[sel], mask[sel], horizon[sel],
                       len(predictors))


def by_horizon(rows, q, mask, horizon, num_models):
    """Print search-cost ratio (top-1) of the model rows and exact H = 1 by Δτ."""
    names = [*list(rows)[:num_models], "exact, H = 1"]
    print("\n| Δτ | queries | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    bins = [(str(d), horizon == d) for d in range(1, 6)] + [("≥ 6", horizon >= 6)]
    for label, sel in bins:
        if not sel.any():
            continue
        cells = []
        for name in names:
            p = rows[name]
            s = slot_scores(p[sel].astype(np.float32), q[sel].astype(np.float32), mask[sel])
            cells.append(f"{np.mean(s['search_cost_ratio']):.4f} ({np.mean(s['top1']):.2f})")
        print(f"| {label} | {sel.sum()} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
