"""How precisely a trained model's samples land on the slot boxes b_k of the exact posterior.

The evaluation protocol assigns a sample to a slot only within 0.05 (L2 over the 4 normalised
numbers), so slot TV / top-1 depend on precision as much as on mode coverage. This prints the
distance from each sample to its nearest valid slot box and the per-coordinate error.

    python experiments/diagnose_precision.py --checkpoint runs/flowmaps-cpu/checkpoints
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

from flowmaps_jax import evaluate
from flowmaps_jax.flowsim.scenes import validation_split
from flowmaps_jax.sample import load


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--num-envs", type=int, default=20)
    parser.add_argument("--samples", type=int, default=100)
    parser.add_argument("--num-steps", type=int, default=10, help="ODE grid points")
    parser.add_argument("--method", default="midpoint", choices=("midpoint", "euler"))
    args = parser.parse_args(argv)

    predictor = load(args.checkpoint)
    config = predictor.flowsim
    evalset = evaluate.build_eval_queries(validation_split(config, args.num_envs), config,
                                          jax.random.key(0), kl_draws=2)
    samples = np.asarray(predictor.sample(evalset.tokens, evalset.queries, args.samples,
                                          jax.random.key(1), num_steps=args.num_steps,
                                          method=args.method))  # (E, M, N, 4)
    boxes, mask = np.asarray(evalset.slot_boxes), np.asarray(evalset.slot_mask)  # (E, M, F, ·)
    dist = np.linalg.norm(samples[:, :, :, None] - boxes[:, :, None], axis=-1)  # (E, M, N, F)
    dist = np.where(mask[:, :, None], dist, np.inf)
    nearest = np.take_along_axis(boxes[:, :, None], dist.argmin(-1)[..., None, None], axis=3)
    error = np.abs(samples - nearest[..., 0, :]).mean((0, 1, 2))
    d = dist.min(-1)
    print(f"{evalset.num_queries} queries × {args.samples} samples ({predictor.source}; "
          f"{args.method}, {args.num_steps} grid points)")
    print(f"distance to nearest slot box: median {np.median(d):.3f}, "
          f"within 0.05: {np.mean(d < 0.05):.1%}, within 0.10: {np.mean(d < 0.10):.1%}")
    print("mean absolute error to nearest slot box (y, x, h, w): "
          + ", ".join(f"{e:.3f}" for e in error))


if __name__ == "__main__":
    main()
