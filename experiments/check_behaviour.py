"""Behaviour fingerprint: fixed-seed trainings and a smoke evaluation, through the public CLIs only.

Refactors must not change numbers. This script trains three tiny models (FlowMaps with the
velocity head, FlowMaps with the cpu preset's pointer recipe, the MLP baseline) for a few steps
with a fixed seed, evaluates them against the exact posterior, and prints one JSON document:
every ``metrics.jsonl`` record (timings removed) and every ``results.json`` row. Compare two
fingerprints with ``--compare``::

    python experiments/check_behaviour.py --out /tmp/now.json \
        --compare docs/behaviour_reference.json

exits 1 and prints the first differences if anything moved by more than ``--atol`` (default 0:
bit-identical on the same machine). The reference was written before the issue-9 restructure.

``--smoke`` runs two of the trainings, FlowMaps and the MLP, and the evaluation at a tiny size (4
steps each, 2 environments, 4 samples, 4 KL draws, the accurate likelihood on 3 grid points;
about 20 s): a check that the script and the CLIs it drives still run
(tests/test_experiments.py). The two trainings are the README's as the suite shortens them
(tests/test_docs_commands.py), so the suite compiles their programs once; the pointer recipe's
would be compiled for this check alone. Its fingerprint compares only with
another ``--smoke`` fingerprint, never with docs/behaviour_reference.json. With ``--smoke`` the
CLIs' ``main(argv)`` run in this process (one JAX start-up) instead of ``python -m`` subprocesses.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import json
import pathlib
import subprocess
import sys
import tempfile

RUNS = {
    "flowmaps": ["--preset", "smoke", "--steps", "30"],
    "pointer": ["--preset", "smoke", "--steps", "30", "--set", "model.head=pointer",
                "--set", "model.condition_on_dtau=true", "--set", "short_horizon_frac=0.5",
                "--set", "target_noise=1.0", "--set", "pointer_loss=1.0"],
    "mlp": ["--preset", "smoke", "--steps", "30", "--family", "mlp"],
}
SMOKE_STEPS = "4"  # --smoke: training steps per run (instead of 30; the smoke preset warms up 2)
SMOKE_RUNS = ("flowmaps", "mlp")  # --smoke: the runs trained (and evaluated)
EVALUATE = ["--num-envs", "12", "--samples", "8,16", "--kl-draws", "16"]
SMOKE_EVALUATE = ["--num-envs", "2", "--samples", "4", "--kl-draws", "4", "--likelihood-steps", "3"]
# Wall-clock rates and temp-dir paths differ from run to run; everything else must not.
VOLATILE_KEYS = {"seconds", "sec_per_step", "steps_per_sec", "samples_per_sec", "elapsed",
                 "time", "wall_s", "source"}


def _strip(obj):
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items() if k not in VOLATILE_KEYS}
    if isinstance(obj, list):
        return [_strip(v) for v in obj]
    return obj


def _run(args: list[str], in_process: bool = False) -> None:
    """``python -m ARGS`` in a subprocess; with ``in_process`` (``--smoke``), the module's
    ``main(argv)`` in this process instead (one JAX start-up for the four commands)."""
    if in_process:
        out = io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
            try:
                code = importlib.import_module(args[0]).main(args[1:])
            except SystemExit as err:  # argparse errors
                code = err.code
        if code:
            raise SystemExit(f"{' '.join(args)} failed (exit {code}):\n{out.getvalue()}")
        return
    proc = subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(args)} failed:\n{proc.stdout}\n{proc.stderr}")


def fingerprint(work: pathlib.Path, smoke: bool = False) -> dict:
    out: dict = {}
    runs = {name: RUNS[name] for name in SMOKE_RUNS} if smoke else RUNS
    for name, args in runs.items():
        if smoke:
            args = [SMOKE_STEPS if prev == "--steps" else a
                    for prev, a in zip(["", *args[:-1]], args, strict=True)]
        run_dir = work / name
        _run(["flowmaps_jax.train", *args, "--run-dir", str(run_dir), "--no-progress"], smoke)
        lines = (run_dir / "metrics.jsonl").read_text().splitlines()
        out[f"train/{name}"] = [_strip(json.loads(line)) for line in lines]
    _run(["flowmaps_jax.evaluate", "--checkpoint", str(work / "flowmaps"),
          "--baseline", *(str(work / name) for name in runs if name != "flowmaps"),
          *(SMOKE_EVALUATE if smoke else EVALUATE), "--no-figures", "--no-progress",
          "--out", str(work / "eval")], smoke)
    results = json.loads((work / "eval" / "results.json").read_text())
    out["evaluate"] = _strip({"protocol": results["protocol"], "rows": results["rows"]})
    return out


def _diff(a, b, atol: float, path: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        keys = sorted(set(a) | set(b))
        return [d for k in keys for d in (_diff(a.get(k), b.get(k), atol, f"{path}/{k}")
                                          if k in a and k in b else [f"{path}/{k}: missing"])]
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: length {len(a)} != {len(b)}"]
        pairs = enumerate(zip(a, b, strict=True))
        return [d for i, (x, y) in pairs for d in _diff(x, y, atol, f"{path}[{i}]")]
    if isinstance(a, float) and isinstance(b, float):
        return [] if abs(a - b) <= atol else [f"{path}: {a!r} != {b!r}"]
    return [] if a == b else [f"{path}: {a!r} != {b!r}"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=None, help="write the fingerprint JSON here")
    parser.add_argument("--compare", default=None, help="reference fingerprint to compare with")
    parser.add_argument("--atol", type=float, default=0.0, help="tolerance on float values")
    parser.add_argument("--smoke", action="store_true",
                        help=f"tiny size ({' and '.join(SMOKE_RUNS)}, {SMOKE_STEPS} steps each, 2 "
                             "environments): checks that everything runs; compare only with "
                             "another --smoke fingerprint")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        fp = fingerprint(pathlib.Path(tmp), smoke=args.smoke)
    text = json.dumps(fp, indent=1, sort_keys=True)
    if args.out:
        pathlib.Path(args.out).write_text(text + "\n")
    if args.compare:
        reference = _strip(json.loads(pathlib.Path(args.compare).read_text()))
        diffs = _diff(reference, fp, args.atol)
        if diffs:
            print(f"{len(diffs)} differences from {args.compare}:\n" + "\n".join(diffs[:30]))
            return 1
        print(f"identical to {args.compare} (atol {args.atol})")
    elif not args.out:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
