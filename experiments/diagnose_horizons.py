"""Why is the multi-step posterior wrong? Score a model by horizon on training and held-out homes.

For each horizon Δτ (fixed-horizon query sets, every object of each environment) and for two sets
of environments (the first ``--envs`` of the fixed training split the model saw, and as many
held-out validation environments), it prints, from ``--samples`` samples per query (protocol v2
assignment):

* TV to the exact posterior q and the off-table mass;
* the model's mass at the slot the object actually occupies at τ_q ("p̂(real)") next to the exact
  posterior's mass there ("q(real)");
* for a read-out head, "KL(weights)": the continuous KL(q‖p) of a mixture with q's own components
  and the model's table weights (``Predictor.table_weights``). It is the part of the model's KL
  due to *where* it puts mass; the rest of its KL is the shape of its components.

A model that learned the posterior has p̂(real) ≈ q(real) on both sets. A model that memorised the
training split's single rollout per home puts far more mass than q on the realised slot of the
*training* homes (p̂(real) ≫ q(real)), and is overconfident, so worse than q, on held-out homes.

    python experiments/diagnose_horizons.py --checkpoint pretrained:flowmaps
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

from flowmaps_jax.evaluation.kl import gt_mixture_log_prob
from flowmaps_jax.evaluation.protocol import build_eval_queries
from flowmaps_jax.evaluation.slots import slot_scores
from flowmaps_jax.flowsim.scenes import train_split, validation_split
from flowmaps_jax.predictor import load_model
from flowmaps_jax.tables import empirical_slots


def score(predictor, scenes, config, horizon: int, samples: int, seed: int,
          num_steps: int = 10, method: str = "midpoint") -> dict:
    ev = build_eval_queries(scenes, config, jax.random.key(seed), kl_draws=32, horizon=horizon)
    boxes = predictor.sample(ev.tokens, ev.queries, samples, jax.random.key(seed + 1),
                             num_steps=num_steps, method=method)
    p_hat = np.asarray(empirical_slots(boxes, ev.slot_boxes, ev.slot_mask))
    q = np.asarray(ev.slot_probs)
    real = np.asarray(scenes.slot)[np.asarray(ev.env), np.asarray(ev.tau_q)]  # (E, M)
    pick = lambda p: np.take_along_axis(p, real[..., None], -1)[..., 0]  # noqa: E731
    tv = slot_scores(p_hat, q, ev.slot_mask)["tv"]
    out = {"tv": tv.mean(), "off": p_hat[..., -1].mean(), "p_real": pick(p_hat).mean(),
           "q_real": pick(q).mean(), "kl_weights": float("nan")}
    if predictor.family_name == "flowmaps" and predictor.model.head in ("pointer", "route"):
        w = np.asarray(predictor.table_weights(ev.tokens, ev.queries))[..., :-1]  # (E, M, S)
        order = np.asarray(scenes.visit_order)[np.asarray(ev.env)]  # (E, M, F) token per slot
        w_slot = np.where(order >= 0, np.take_along_axis(w, np.maximum(order, 0), -1), 0.0)
        w_slot = np.maximum(w_slot, 1e-12) * np.asarray(ev.slot_mask)
        w_slot = w_slot / w_slot.sum(-1, keepdims=True)
        log_p = gt_mixture_log_prob(ev.kl_points, w_slot, ev.slot_boxes, ev.slot_mask)
        out["kl_weights"] = float(np.mean(np.asarray(ev.kl_log_q) - np.asarray(log_p)))
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", default="pretrained:flowmaps")
    parser.add_argument("--which", default="latest", choices=("best", "latest"))
    parser.add_argument("--envs", type=int, default=60, help="environments per set and horizon")
    parser.add_argument("--samples", type=int, default=100)
    parser.add_argument("--horizons", type=int, nargs="+", default=[1, 2, 3, 4, 6, 10])
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--num-steps", type=int, default=10, help="sampler grid points")
    parser.add_argument("--method", default="midpoint", help="sampler: midpoint or accurate")
    parser.add_argument("--sets", nargs="+", default=["train", "held-out"],
                        choices=["train", "held-out"])
    args = parser.parse_args(argv)
    predictor = load_model(args.checkpoint, args.which)
    config = predictor.flowsim
    make = {"train": train_split, "held-out": validation_split}
    sets = {name: make[name](config, num_envs=args.envs) for name in args.sets}
    print(f"{args.checkpoint}: {args.envs} environments × {config.num_objects} objects per set "
          f"and horizon, {args.samples} samples per query, sampler {args.method} on "
          f"{args.num_steps} grid points")
    print(f"{'Δτ':>3} {'set':>9} {'TV':>6} {'off':>6} {'p̂(real)':>9} {'q(real)':>8} "
          f"{'KL(weights)':>12}")
    for h in args.horizons:
        for name, scenes in sets.items():
            r = score(predictor, scenes, config, h, args.samples, args.seed, args.num_steps,
                      args.method)
            print(f"{h:>3} {name:>9} {r['tv']:6.3f} {r['off']:6.3f} {r['p_real']:9.3f} "
                  f"{r['q_real']:8.3f} {r['kl_weights']:12.3f}", flush=True)


if __name__ == "__main__":
    main()
