"""Ablation: what makes FlowMaps learn the routines? Equal steps of one schedule per variant.

Every variant is the `cpu-pointer` preset's full schedule (8,500 steps, cosine; the `cpu` preset
before issue 33) with the paper's recipe (the preset before issue 8, ``OLD_CPU``) and then some
fields changed,
trained sequentially (never side by side) and stopped after ``--stop-at`` steps, so variants are
compared at equal steps of the same learning-rate schedule; the step time of each is reported, so
equal wall-clock can be read off too. Each is then scored on the evaluation protocol (first
``--num-envs`` validation environments × 3 objects, 100 samples, exact-likelihood KL) plus the
routine diagnostic (route-offset mass one step ahead).

    python experiments/ablate_routines.py --stop-at 2000 --out runs/ablation

Writes ``<out>/ablation.json`` and prints a Markdown table (docs/results.md keeps it). A variant
whose run directory already holds a checkpoint at ``--stop-at`` is not retrained.

``--smoke`` shrinks every size so that the script can be checked in seconds per variant (its
numbers mean nothing): the ``smoke`` preset's model and data instead of ``cpu``'s, stopped at step
4, scored on 4 environments (one has a Δτ = 1 query) with 16 KL draws and the accurate likelihood
on 3 grid points, written to ``runs/ablation-smoke`` unless
``--out`` says otherwise; combine it with ``--only`` to run fewer variants
(tests/test_experiments.py). Every variant's config is built (and so checked) before the first
training, with or without ``--only``.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import numpy as np

from flowmaps_jax import evaluation
from flowmaps_jax.flowsim.scenes import validation_split
from flowmaps_jax.predictor import load
from flowmaps_jax.training import loop as train
from flowmaps_jax.training.config import apply_overrides, get_preset

# the cpu preset before issue 8 (paper recipe at cpu size); every variant starts from it
OLD_CPU = ["model.head=velocity", "model.condition_on_dtau=false", "short_horizon_frac=0",
           "short_horizon_max=3", "target_noise=0", "pointer_loss=0", "lr=5e-4",
           "model.dropout=0.1", "model.pointer_widths=absolute", "model.pointer_width_scale=1"]
RECIPE = ["model.condition_on_dtau=true", "short_horizon_frac=0.5", "short_horizon_max=1",
          "target_noise=1", "lr=1e-3", "model.dropout=0"]
VARIANTS = {
    "paper (old cpu)": [],
    "recipe, velocity head": RECIPE,
    "recipe, pointer head": [*RECIPE, "model.head=pointer"],
    "recipe, pointer head + pointer loss": [*RECIPE, "model.head=pointer", "pointer_loss=1"],
    "… without short horizons": [*RECIPE, "model.head=pointer", "pointer_loss=1",
                                 "short_horizon_frac=0"],
    "… without Δτ conditioning": [*RECIPE, "model.head=pointer", "pointer_loss=1",
                                  "model.condition_on_dtau=false"],
    "… with lr 5e-4, dropout 0.1": [*RECIPE, "model.head=pointer", "pointer_loss=1",
                                    "lr=5e-4", "model.dropout=0.1"],
    "… with fast log-widths (×10)": [*RECIPE, "model.head=pointer", "pointer_loss=1",
                                     "model.pointer_width_scale=10"],
    "… with pointer loss ×3": [*RECIPE, "model.head=pointer", "pointer_loss=3"],
    # issue 21: widths relative to the object's size (the cpu preset since), and the route head
    "… with relative widths (×10)": [*RECIPE, "model.head=pointer", "pointer_loss=1",
                                     "model.pointer_widths=relative",
                                     "model.pointer_width_scale=10"],
    "route head (transition^Δτ), relative widths": [*RECIPE, "model.head=route", "pointer_loss=1",
                                                    "model.pointer_width_scale=10"],
    # issue 33: the pointer head (the cpu preset until then) and the mixture head, both on
    # endless data, at equal steps of the same schedule
    "pointer head, relative widths, endless data": [*RECIPE, "model.head=pointer",
                                                    "pointer_loss=1",
                                                    "model.pointer_widths=relative",
                                                    "model.pointer_width_scale=10",
                                                    "data=endless"],
    "mixture head (table weights + placement flow), endless data": [
        *RECIPE, "model.head=mixture", "pointer_loss=1", "data=endless"],
}


def slug(name: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in name).strip("-").replace("--", "-")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stop-at", type=int, default=None,
                        help="train each variant to this step (default 2000; 4 with --smoke)")
    parser.add_argument("--num-envs", type=int, default=None,
                        help="validation environments scored (default 100; 4 with --smoke)")
    parser.add_argument("--out", default=None,
                        help="output directory (default runs/ablation; runs/ablation-smoke "
                             "with --smoke)")
    parser.add_argument("--only", nargs="*", default=None, help="variant names to run")
    parser.add_argument("--smoke", action="store_true",
                        help="tiny sizes to check that the script runs: the smoke preset, "
                             "stop at step 4, 4 environments, 16 KL draws, a 3-point accurate "
                             "likelihood")
    args = parser.parse_args()
    unknown = sorted(set(args.only or ()) - set(VARIANTS))
    if unknown:
        parser.error(f"--only: no variant named {', '.join(map(repr, unknown))}; the variants are "
                     + ", ".join(map(repr, VARIANTS)))
    preset = "smoke" if args.smoke else "cpu-pointer"  # the cpu preset before issue 33
    for name, full, smoke in (("stop_at", 2000, 4), ("num_envs", 100, 4),
                              ("out", "runs/ablation", "runs/ablation-smoke")):
        if getattr(args, name) is None:
            setattr(args, name, smoke if args.smoke else full)
    # --smoke: the KL on 16 draws and the accurate likelihood on its smallest grid (the tests run
    # this without most of XLA's optimisations, where the 48-point solve is slow)
    scoring = {"kl_draws": 16, "likelihood_steps": 3} if args.smoke else {}
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results_path = out / "ablation.json"
    results = json.loads(results_path.read_text()) if results_path.exists() else {}
    # every variant's config first: a bad override fails now, not after hours of training
    configs = {name: apply_overrides(get_preset(preset), [*OLD_CPU, *overrides])
               for name, overrides in VARIANTS.items()}
    for name, overrides in VARIANTS.items():
        if args.only and name not in args.only:
            continue
        cfg = configs[name]
        run_dir = out / slug(name)
        ckpt = run_dir / "checkpoints" / "last" / str(args.stop_at)
        start = time.perf_counter()
        if not ckpt.exists():
            print(f"=== {name}: training to step {args.stop_at} → {run_dir}", flush=True)
            train.run(cfg, run_dir, stop_at=args.stop_at, progress=False, overwrite=True)
        train_s = time.perf_counter() - start
        records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().split("\n")
                   if line.strip()]
        rates = [r["steps_per_sec"] for r in records
                 if r["kind"] == "train" and r.get("steps_per_sec", 0) > 0]
        routine = [r for r in records if r["kind"] == "routine"][-1]
        predictor = load(run_dir / "checkpoints", which="latest")
        scenes = validation_split(cfg.flowsim, num_envs=args.num_envs)
        res, _, _ = evaluation.run_evaluation([predictor], scenes, cfg.flowsim, None,
                                              sample_counts=(100,), figures=False,
                                              progress=False, **scoring)
        row = res["rows"][predictor.name]
        slot = row["slots"]["100"]
        results[name] = {
            "overrides": overrides, "steps": args.stop_at,
            "step_s": float(1.0 / np.median(rates)) if rates else None,
            "train_s": round(train_s, 1),
            "kl": row["kl"]["overall"]["mean"],
            "kl_by_horizon": {h: v["mean"] for h, v in row["kl"]["by_horizon"].items()},
            "tv": slot["tv"]["overall"]["mean"], "top1": slot["top1"]["overall"]["mean"],
            "search_cost_ratio": slot["search_cost_ratio"]["overall"]["mean"],
            "offsets_one_step": row["route_offsets_one_step"]["mean"],
            "routine_probe": {k: routine[k] for k in ("offset_0", "offset_+1", "offset_+2",
                                                      "offset_off")},
        }
        results_path.write_text(json.dumps(results, indent=2) + "\n")
        print(table(results), flush=True)


def table(results: dict) -> str:
    lines = ["| variant | step s | KL | TV@100 | top-1@100 | search cost@100 | "
             "Δτ=1 mass at offsets 0 / +1 / +2 (off) |", "|---|---|---|---|---|---|---|"]
    for name, r in results.items():
        m = [_cell(v, ".2f") for v in r["offsets_one_step"]]  # null: no Δτ = 1 query was scored
        lines.append(f"| {name} | {_cell(r['step_s'], '.3f')} | {_cell(r['kl'], '.2f')} | "
                     f"{_cell(r['tv'], '.3f')} | {_cell(r['top1'], '.2f')} | "
                     f"{_cell(r['search_cost_ratio'], '.3f')} | {m[0]} / {m[1]} / {m[2]} "
                     f"({m[5]}) |")
    return "\n".join(lines)


def _cell(value, fmt: str) -> str:
    """A table cell: the number, or "–" where the JSON holds null (nothing to measure)."""
    return "–" if value is None else format(value, fmt)


if __name__ == "__main__":
    main()
