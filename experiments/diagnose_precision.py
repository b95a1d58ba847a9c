"""Where a trained model's samples land: how precisely (distance to the slot boxes) and on which
slots (mass by offset from the object's current slot, against the exact posterior).

The evaluation protocol assigns a sample to a slot only within 0.05 (L2 over the 4 normalised
numbers), so slot TV / top-1 depend on precision as much as on mode coverage; and top-1 / search
cost depend on the model ranking the slots as q does, i.e. on having learned the dynamics. This
prints (1) the distance from each sample to its nearest valid slot box and the per-coordinate
error, (2) for the queries one step ahead (Δτ = 1, where q is (0.2, 0.7, 0.1) on offsets 0, 1, 2
along the visiting order) the mean slot mass at route offsets 0..+3, beyond and off from the
current slot (``evaluation.route_offset_mass``), model vs q.

    python experiments/diagnose_precision.py --checkpoint runs/flowmaps-cpu/checkpoints
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

from flowmaps_jax import evaluation
from flowmaps_jax.flowsim.scenes import validation_split
from flowmaps_jax.predictor import load_model


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True,
                        help="a run or checkpoint directory, or pretrained:NAME")
    parser.add_argument("--num-envs", type=int, default=20, help="environments for (1)")
    parser.add_argument("--ranking-envs", type=int, default=200,
                        help="environments searched for Δτ = 1 queries for (2)")
    parser.add_argument("--samples", type=int, default=100)
    parser.add_argument("--num-steps", type=int, default=10, help="ODE grid points")
    parser.add_argument("--method", default="midpoint", choices=("midpoint", "euler"))
    args = parser.parse_args(argv)

    predictor = load_model(args.checkpoint)  # a directory's best save, or pretrained:NAME
    config = predictor.flowsim
    n_envs = max(args.num_envs, args.ranking_envs)
    evalset = evaluation.build_eval_queries(validation_split(config, n_envs), config,
                                            jax.random.key(0), kl_draws=2)

    def draw(part):
        return np.asarray(predictor.sample(part.tokens, part.queries, args.samples,
                                           jax.random.key(1), num_steps=args.num_steps,
                                           method=args.method))  # (E, M, N, 4)

    part = evalset.take(np.arange(args.num_envs))
    samples = draw(part)
    boxes, mask = np.asarray(part.slot_boxes), np.asarray(part.slot_mask)  # (E, M, F, ·)
    dist = np.linalg.norm(samples[:, :, :, None] - boxes[:, :, None], axis=-1)  # (E, M, N, F)
    dist = np.where(mask[:, :, None], dist, np.inf)
    nearest = np.take_along_axis(boxes[:, :, None], dist.argmin(-1)[..., None, None], axis=3)
    error = np.abs(samples - nearest[..., 0, :]).mean((0, 1, 2))
    d = dist.min(-1)
    print(f"(1) {part.num_queries} queries × {args.samples} samples ({predictor.source}; "
          f"{args.method}, {args.num_steps} grid points)")
    print(f"distance to nearest slot box: median {np.median(d):.3f}, "
          f"within 0.05: {np.mean(d < 0.05):.1%}, within 0.10: {np.mean(d < 0.10):.1%}")
    print("mean absolute error to nearest slot box (y, x, h, w): "
          + ", ".join(f"{e:.3f}" for e in error))

    envs = np.flatnonzero(np.asarray(evalset.horizon)[: args.ranking_envs, 0] == 1)
    if not len(envs):
        print("(2) no Δτ = 1 query among the first --ranking-envs environments")
        return
    part = evalset.take(envs)
    p_hat = evaluation.empirical_slots(draw(part), part.slot_boxes, part.slot_mask)
    exact = evaluation.oracle_slots(part.slot_probs)
    mass = {name: np.asarray(evaluation.route_offset_mass(p, part.slot_now, part.num_slots))
            .mean(axis=(0, 1)) for name, p in (("exact q", exact), ("model p̂", p_hat))}
    print(f"(2) {part.num_queries} queries with Δτ = 1: mean slot mass at route offsets from the "
          "current slot (visiting order)")
    print("offset:   " + "  ".join(f"{k:>6}" for k in evaluation.ROUTE_OFFSET_LABELS))
    for name, m in mass.items():
        print(f"{name}:  " + "  ".join(f"{v:6.3f}" for v in m))


if __name__ == "__main__":
    main()
