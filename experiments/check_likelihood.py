"""Does the likelihood converge? The flow's log-density on a uniform grid and on the stiff grid.

Two models, each on boxes drawn from the protocol's smoothed q one step ahead:

1. A route-head FlowMaps whose residual is zero (fresh weights, ``--preset``'s model size):
   its flow carries noise exactly onto a Gaussian mixture, so log p has a closed form to
   compare with.
2. A trained model (``--checkpoint``, default the pretrained ``pretrained:flowmaps``).

For each, the mean log p at increasing grid sizes with the paper's midpoint solver (uniform grid)
and with ``method="accurate"`` (RK4 on t = 1 − (1 − s)⁴), and the time per solve.

    python experiments/check_likelihood.py
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from flowmaps_jax.evaluation.protocol import build_eval_queries
from flowmaps_jax.flowsim.scenes import validation_split
from flowmaps_jax.model import init_params
from flowmaps_jax.model.family import canonical_inputs
from flowmaps_jax.model.flowmaps_family import route_mixture_log_prob
from flowmaps_jax.predictor import Predictor, load_model
from flowmaps_jax.training.config import get_preset


def closed_form(predictor: Predictor, ev) -> float:
    """Mean log p of the KL points under the route head's mixture (exact when residual = 0)."""
    tokens, queries = canonical_inputs(ev.tokens, ev.queries)
    return float(np.mean(route_mixture_log_prob(predictor.params, predictor.model, tokens,
                                                queries, ev.kl_points)))


def table(predictor: Predictor, ev, grids, reference: float | None, label: str) -> None:
    print(f"\n{label}" + ("" if reference is None else f" (closed form: {reference:.4f})"))
    print(f"{'method':>9} {'points':>7} {'mean log p':>11} {'minus closed form':>18} {'s':>6}")
    for method, points in grids:
        for n in points:
            predictor.log_prob(ev.tokens, ev.queries, ev.kl_points, num_steps=n, method=method)
            start = time.perf_counter()
            lp = float(np.mean(predictor.log_prob(ev.tokens, ev.queries, ev.kl_points,
                                                  num_steps=n, method=method)))
            seconds = time.perf_counter() - start
            diff = "" if reference is None else f"{lp - reference:+.4f}"
            print(f"{method:>9} {n:>7} {lp:11.4f} {diff:>18} {seconds:6.2f}", flush=True)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", default="pretrained:flowmaps")
    parser.add_argument("--envs", type=int, default=11, help="environments (3 queries each)")
    parser.add_argument("--draws", type=int, default=32, help="boxes from q per query")
    parser.add_argument("--midpoint", type=int, nargs="+", default=[10, 40, 160, 640])
    parser.add_argument("--accurate", type=int, nargs="+", default=[12, 24, 48, 96, 192])
    parser.add_argument("--preset", default="cpu", choices=["smoke", "cpu", "paper"],
                        help="the fresh route head's model size and world (smoke: a tiny check)")
    args = parser.parse_args(argv)
    grids = [("midpoint", args.midpoint), ("accurate", args.accurate)]
    cfg = get_preset(args.preset)
    scenes = validation_split(cfg.flowsim, num_envs=args.envs)
    ev = build_eval_queries(scenes, cfg.flowsim, jax.random.key(3), kl_draws=args.draws,
                            horizon=1)
    model = dataclasses_replace_head(cfg.model)
    fresh = Predictor.from_params(init_params(jax.random.key(0), model), model)
    exact = closed_form(fresh, ev)
    table(fresh, ev, grids, exact, "route head, residual zero (fresh weights)")
    trained = load_model(args.checkpoint, "latest")
    ref = None
    if trained.model.head == "route":
        ref = closed_form(trained, ev)
        print("(the trained route head's residual is not zero: closed form = its mixture only)")
    table(trained, ev, grids, ref, f"{args.checkpoint} (step {trained.step})")


def dataclasses_replace_head(model):
    import dataclasses

    return dataclasses.replace(model, head="route", pointer_width_scale=10.0)


if __name__ == "__main__":
    main()
