"""How queries per scene (Q) trade training speed against quality, at equal steps.

Trains the ``cpu`` preset for a fixed number of steps once per Q (each scene's encoder pass is
shared by its Q queries) and prints the final validation CFM loss (EMA weights, fixed noise,
the same validation scenes) next to the measured step time. Quality per wall-clock second then
follows from the step times of ``experiments/bench_train.py`` on an idle machine.

    python experiments/sweep_queries.py --queries 1 4 8 16 --steps 1000 --out runs/sweep_q
"""

from __future__ import annotations

import argparse
import pathlib
import time

from flowmaps_jax.training.config import apply_overrides, get_preset
from flowmaps_jax.training.loop import run


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--queries", type=int, nargs="+", default=[1, 4, 8, 16])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--out", default="runs/sweep_q")
    args = parser.parse_args(argv)

    rows = []
    for q in args.queries:
        cfg = apply_overrides(get_preset(args.preset), {
            "queries_per_scene": q, "steps": args.steps, "warmup_steps": min(100, args.steps // 10),
            "ema_decay": 0.99, "val_every": args.steps, "ckpt_every": args.steps,
            "log_every": max(1, args.steps // 10)})
        start = time.perf_counter()
        result = run(cfg, pathlib.Path(args.out) / f"q{q}", progress=False, log=lambda _: None,
                     overwrite=True)
        seconds = time.perf_counter() - start
        rows.append((q, result.step, result.best_val_loss, seconds,
                     args.steps * cfg.batch_size * q))
        print(f"Q={q:3d}: val loss {result.best_val_loss:.4f} after {result.step} steps "
              f"({seconds:.0f} s incl. data and compile)", flush=True)

    print("\n  Q  steps  query-samples seen  final val loss (EMA)  wall s (incl. compile)")
    for q, steps, seen, val, seconds in ((r[0], r[1], r[4], r[2], r[3]) for r in rows):
        print(f"{q:3d}  {steps:5d}  {seen:18,d}  {val:20.4f}  {seconds:10.0f}")


if __name__ == "__main__":
    main()
