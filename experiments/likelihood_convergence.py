"""Does a trained model's likelihood converge? KL(q‖p) on a fixed query set, grid by grid.

    python experiments/likelihood_convergence.py --checkpoint runs/X/checkpoints --envs 20

Builds the evaluation protocol's queries on the first ``--envs`` validation environments (3
objects each, ``--draws`` boxes from q per query) and prints the KL estimate E_q[log q − log p]
with every solver grid of ``--midpoint`` and ``--accurate``, and the seconds each took. A field
whose likelihood has converged gives the same KL (within the Monte-Carlo noise, which is shared:
the same draws every row) on every fine enough grid; a rough field gives numbers that wander.
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from flowmaps_jax.evaluation import protocol as ev
from flowmaps_jax.flowsim.scenes import validation_split
from flowmaps_jax.predictor import load_model


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", default="pretrained:flowmaps")
    parser.add_argument("--which", default="best", choices=("best", "latest"))
    parser.add_argument("--envs", type=int, default=20, help="environments (3 queries each)")
    parser.add_argument("--draws", type=int, default=8, help="boxes from q per query")
    parser.add_argument("--midpoint", type=int, nargs="*", default=[10, 20, 40, 80])
    parser.add_argument("--accurate", type=int, nargs="*", default=[24, 48, 96])
    args = parser.parse_args(argv)
    model = load_model(args.checkpoint, args.which)
    sim = model.flowsim
    queries = ev.build_eval_queries(validation_split(sim, num_envs=args.envs), sim,
                                    jax.random.key(0), kl_draws=args.draws)
    print(f"{args.checkpoint} (step {model.step}): {args.envs * 3} queries x {args.draws} draws")
    print("| grid | points | KL(q‖p) [nats] | seconds |\n|---|---|---|---|")
    for method, grid in (("midpoint", args.midpoint), ("accurate", args.accurate)):
        for points in grid:
            start = time.perf_counter()
            log_p = np.asarray(model.log_prob(queries.tokens, queries.queries, queries.kl_points,
                                              num_steps=points, method=method))
            kl = float(np.mean(np.asarray(queries.kl_log_q) - log_p))
            print(f"| {method} | {points} | {kl:.4f} | {time.perf_counter() - start:.1f} |",
                  flush=True)


if __name__ == "__main__":
    main()
