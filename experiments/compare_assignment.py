"""The slot assignment, v1 against v2, on one model and on the two "perfect sampler" rows.

v1 (the first protocol): a sample counts for slot k when its four numbers (y, x, h, w) lie within
0.05 (L2) of the object's box there. v2 (docs/protocol.md): the nearest slot centre, off beyond
max(0.05, 3 · 0.35 · side). Rows: draws of the slot from q ("oracle samples", never off), draws
of boxes from the smoothed q the KL uses ("smoothed-q samples"), and the model. Under a rule that
agrees with q, the smoothed-q row scores like the oracle-samples row.

    python experiments/compare_assignment.py --checkpoint pretrained:flowmaps
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

from flowmaps_jax.evaluation.kl import sample_gt_mixture
from flowmaps_jax.evaluation.protocol import build_eval_queries
from flowmaps_jax.evaluation.slots import sampled_oracle_slots, slot_scores
from flowmaps_jax.flowsim.scenes import validation_split
from flowmaps_jax.predictor import load_model
from flowmaps_jax.tables import empirical_slots


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", default="pretrained:flowmaps")
    parser.add_argument("--which", default="latest", choices=("best", "latest"))
    parser.add_argument("--num-envs", type=int, default=200)
    parser.add_argument("--samples", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    predictor = load_model(args.checkpoint, args.which)
    config = predictor.flowsim
    scenes = validation_split(config, num_envs=args.num_envs)
    ev = build_eval_queries(scenes, config, jax.random.key(args.seed), kl_draws=2)
    n = args.samples
    key = jax.random.key(args.seed + 1)
    samples = {
        "smoothed-q samples": sample_gt_mixture(jax.random.fold_in(key, 1), ev.slot_probs,
                                                ev.slot_boxes, n, ev.slot_mask),
        f"{predictor.name} ({args.checkpoint}, step {predictor.step})":
            predictor.sample(ev.tokens, ev.queries, n, jax.random.fold_in(key, 2)),
    }
    oracle = sampled_oracle_slots(jax.random.fold_in(key, 3), ev.slot_probs, n)
    print(f"{ev.num_queries} queries ({args.num_envs} held-out environments), {n} samples each")
    print(f"| rule | row | TV @{n} | top-1 @{n} | rank cost @{n} | off |")
    print("|---|---|---|---|---|---|")
    for rule in ("v1", "v2"):
        rows = {"oracle samples": oracle}
        rows.update({name: empirical_slots(x, ev.slot_boxes, ev.slot_mask, rule=rule)
                     for name, x in samples.items()})
        for name, p_hat in rows.items():
            s = slot_scores(p_hat, ev.slot_probs, ev.slot_mask)
            off = np.asarray(p_hat)[..., -1].mean()
            print(f"| {rule} | {name} | {s['tv'].mean():.3f} | {s['top1'].mean():.3f} | "
                  f"{s['search_cost_ratio'].mean():.3f} | {off:.3f} |", flush=True)


if __name__ == "__main__":
    main()
