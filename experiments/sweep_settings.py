"""Screen training settings at equal steps by what the protocol scores, not just the CFM loss.

The validation CFM loss is dominated by the irreducible noise of the conditional target, so it
barely separates settings that differ in box *precision*, which is what slot TV / top-1 need
(a sample counts for a slot only within 0.05). Each variant ``name:key=value,key=value`` trains
the preset with those overrides (``--set`` syntax), then is scored on the first ``--eval-envs``
validation environments of the evaluation protocol: KL, slot TV @100, and the share of samples
within 0.05 of a slot box. Caution (docs/results.md, "Sharper boxes"): precision forms late in
training, so a short screen can rank settings by KL while their full-length precision disagrees.

    python experiments/sweep_settings.py --steps 1500 --out runs/sweep_settings \\
        base: uniform:t_sampler=uniform lr1e-3:lr=1e-3
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time
import types

import numpy as np

from flowmaps_jax import evaluation
from flowmaps_jax.evaluation.cli import build_parser as evaluate_parser
from flowmaps_jax.evaluation.cli import check_size
from flowmaps_jax.flowsim.scenes import validation_split
from flowmaps_jax.predictor import load
from flowmaps_jax.training.config import apply_overrides, get_preset
from flowmaps_jax.training.loop import run
from flowmaps_jax.validation import check_int


def parse_variant(text: str) -> tuple[str, list[str]]:
    """``"name:k=v,k=v"`` → (name, ["k=v", "k=v"]); ``"name:"`` is the unchanged preset."""
    name, _, rest = text.partition(":")
    if not name:
        raise ValueError(f"variant must look like name:key=value,...; got {text!r}")
    return name, [item for item in rest.split(",") if item]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("variants", nargs="+", help="name:key=value,key=value (name: = preset)")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--eval-envs", type=int, default=40)
    parser.add_argument("--kl-draws", type=int, default=evaluation.DEFAULT_KL_DRAWS,
                        help="draws from q per query for the KL")
    parser.add_argument("--likelihood-steps", type=int,
                        default=evaluation.DEFAULT_LIKELIHOOD_STEPS,
                        help="grid points of the accurate likelihood behind the KL; 0: off")
    parser.add_argument("--out", default="runs/sweep_settings")
    args = parser.parse_args(argv)

    # Everything is checked before any training writes a run directory: the options, every
    # variant's config, and each evaluation's memory and work (the evaluate CLI's shared estimate,
    # at its defaults for what this script does not set).
    check_int("--eval-envs", args.eval_envs)
    check_int("--kl-draws", args.kl_draws, 2)
    likelihood_steps = check_int("--likelihood-steps", args.likelihood_steps, 0) or None
    if likelihood_steps is not None:  # the accurate likelihood's grid: 3 points at least
        check_int("--likelihood-steps", likelihood_steps, 3)
    base = {"steps": args.steps, "warmup_steps": min(200, args.steps // 10),
            "val_every": args.steps, "ckpt_every": args.steps,
            "log_every": max(1, args.steps // 10)}
    variants = [(name, overrides, apply_overrides(apply_overrides(get_preset(args.preset), base),
                                                  overrides))
                for name, overrides in map(parse_variant, args.variants)]
    scoring = evaluate_parser().parse_args([
        "--checkpoint", "(each variant)", "--samples", "100", "--kl-draws", str(args.kl_draws),
        "--likelihood-steps", str(args.likelihood_steps)])
    for _, _, cfg in variants:  # check_size reads a predictor's family_name, model and flowsim only
        model = types.SimpleNamespace(family_name=cfg.family, model=cfg.model, flowsim=cfg.flowsim)
        check_size([model], args.eval_envs, cfg.flowsim, scoring)
    rows = []
    for name, overrides, cfg in variants:
        run_dir = pathlib.Path(args.out) / name
        start = time.perf_counter()
        result = run(cfg, run_dir, progress=False, log=lambda _: None, overwrite=True)
        train_s = time.perf_counter() - start
        predictor = load(result.checkpoint_dir)
        scenes = validation_split(cfg.flowsim, args.eval_envs)
        results, model_rows, _ = evaluation.run_evaluation(
            [predictor], scenes, cfg.flowsim, sample_counts=(100,), kl_draws=args.kl_draws,
            likelihood_steps=likelihood_steps, figures=False, progress=False)
        row = results["rows"][predictor.name]
        # share of samples assigned to some slot (within 0.05) = 1 − the off bin of p̂
        near = 1.0 - float(np.mean(model_rows[-1].slots[100]["p_hat"][..., -1]))
        record = {"name": name, "overrides": overrides, "steps": result.step,
                  "train_seconds": round(train_s, 1), "val_loss": result.best_val_loss,
                  "kl": row["kl"]["overall"]["mean"],
                  "tv100": row["slots"]["100"]["tv"]["overall"]["mean"],
                  "top1_100": row["slots"]["100"]["top1"]["overall"]["mean"],
                  "within_0.05": near}
        rows.append(record)
        print(json.dumps(record), flush=True)

    print(f"\n{'variant':>14}  {'val loss':>8}  {'KL':>6}  {'TV@100':>6}  {'top1':>5}  "
          f"{'<0.05':>6}  {'train s':>7}")
    for r in rows:
        print(f"{r['name']:>14}  {r['val_loss']:8.4f}  {r['kl']:6.2f}  {r['tv100']:6.3f}  "
              f"{r['top1_100']:5.2f}  {r['within_0.05']:6.1%}  {r['train_seconds']:7.0f}")


if __name__ == "__main__":
    main()
