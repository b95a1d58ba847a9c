"""Training throughput of the homes network: steps per second of ``python -m flowmaps_jax.train``.

Runs the train command for ``--steps`` steps of each preset in a fresh subprocess (validation
and checkpoints pushed past the end, so only training steps are timed) and reports the median of
the ``steps_per_sec`` the run logs every ``log_every`` steps, leaving out the first record (it
holds the compilation). Run it on an idle machine; two trainings at once halve each other.

    python experiments/bench_homes_train.py                          # the homes preset
    python experiments/bench_homes_train.py --presets homes homes-rhythms --steps 400
    python experiments/bench_homes_train.py --data PATH              # the recorded recipe
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def measure(preset: str, steps: int, data: str | None, log_every: int = 25) -> dict:
    """Median steps/s of one fresh training run of ``preset`` (on ``data`` if given), a record
    every ``log_every`` steps."""
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "run"
        cmd = [sys.executable, "-m", "flowmaps_jax.train", "--preset", preset, "--run-dir",
               str(run), "--no-progress", "--steps", str(steps), "--set", f"log_every={log_every}",
               "--set", f"val_every={steps + 1}", "--set", f"ckpt_every={steps + 1}"]
        if data:
            cmd += ["--data", data]
        start = time.perf_counter()
        done = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - start
        if done.returncode:
            raise SystemExit(f"{' '.join(cmd)} failed:\n{done.stdout[-2000:]}{done.stderr[-2000:]}")
        records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
        rates = [r["steps_per_sec"] for r in records if r.get("kind") == "train"][1:]
    return {"preset": preset, "data": data, "steps": steps, "wall_s": round(wall, 1),
            "steps_per_sec": round(statistics.median(rates), 3) if rates else None}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--presets", nargs="+", default=["homes"])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--data", default=None, help="a recorded dataset (--data of train)")
    parser.add_argument("--log-every", type=int, default=25,
                        help="steps per logged rate (the first, which compiles, is left out)")
    args = parser.parse_args(argv)
    if args.log_every < 1:
        parser.error(f"--log-every must be at least 1; got {args.log_every}")
    if args.steps < 2 * args.log_every + 1:
        parser.error(f"--steps must be at least {2 * args.log_every + 1} (two log records of "
                     f"{args.log_every} steps)")
    import jax

    print(f"jax {jax.__version__} on {jax.default_backend()}, {jax.device_count()} device(s)")
    for preset in args.presets:
        print(json.dumps(measure(preset, args.steps, args.data, args.log_every)))


if __name__ == "__main__":
    main()
