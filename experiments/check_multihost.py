"""Multi-host training on one machine: two processes joined by ``jax.distributed`` (CPU
collectives over gloo) train the smoke model together, then one process continues the run.

    python experiments/check_multihost.py [--steps 6] [--keep DIR]

What it checks (exit 1 with the reason otherwise):
* both processes start through ``flowmaps_jax.distributed.initialize`` from
  ``JAX_COORDINATOR_ADDRESS`` / ``JAX_NUM_PROCESSES`` / ``JAX_PROCESS_ID``, see a 2-device mesh
  over 2 hosts, and each generates only its half of the training environments;
* only process 0 writes ``config.json`` and ``metrics.jsonl``; both report the same best
  validation loss (the replicated state agrees);
* starting them again on the now non-empty run directory (without ``--resume``) is refused by
  process 0, and process 1 stops with it at once (exit code 2 on both);
* the checkpoint they saved together resumes in a single process (1 device) and trains on;
* two processes resume from an older saved step (``--from-step``): process 0 sets the later
  steps aside while the other waits, and both finish.

On 2 cores this takes about 2 minutes (two JAX processes compile side by side).
"""

from __future__ import annotations

import argparse
import os
import pathlib
import re
import socket
import subprocess
import sys
import tempfile
import time


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _train_args(run_dir: pathlib.Path, steps: int) -> list[str]:
    return [sys.executable, "-m", "flowmaps_jax.train", "--preset", "smoke", "--steps",
            str(steps), "--run-dir", str(run_dir), "--no-progress", "--set", "routine_envs=2",
            "--set", "val_every=3", "--set", "log_every=2"]


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("JAX_COORDINATOR", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID"))}
    env.update(JAX_PLATFORMS="cpu", **extra)
    env["XLA_FLAGS"] = env.get("XLA_FLAGS", "").replace(
        "--xla_force_host_platform_device_count=2", "")
    return env


def _two_processes(args: list[str]) -> tuple[list[int], list[str]]:
    """Run ``args`` as processes 0 and 1 of a two-process jax.distributed job: exit codes, logs."""
    address = f"127.0.0.1:{_free_port()}"
    procs = [subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                              env=_env(JAX_COORDINATOR_ADDRESS=address, JAX_NUM_PROCESSES="2",
                                       JAX_PROCESS_ID=str(i)))
             for i in range(2)]
    logs = [p.communicate(timeout=900)[0] for p in procs]
    return [p.returncode for p in procs], logs


def check(work: pathlib.Path, steps: int = 6) -> list[str]:
    """Run the two-host training, a refused second start and the one-process resume in
    ``work``; returns the problems found (empty: all good)."""
    run_dir = work / "run"
    codes, logs = _two_processes(_train_args(run_dir, steps))
    procs = [subprocess.CompletedProcess([], code) for code in codes]
    problems = []
    for i, (proc, log) in enumerate(zip(procs, logs, strict=True)):
        if proc.returncode != 0:
            problems.append(f"process {i} exited with {proc.returncode}:\n{log[-3000:]}")
    if problems:
        return problems
    for i, log in enumerate(logs):
        if "2 devices (cpu" not in log or "2 hosts" not in log:
            problems.append(f"process {i} did not see a 2-host mesh")
        share = f"this host's {32 * i}..{32 * i + 31}"
        if share not in log:
            problems.append(f"process {i} did not generate only its share ({share})")
    best = [re.search(r"best validation loss ([0-9.]+)", log) for log in logs]
    if not all(best) or best[0].group(1) != best[1].group(1):
        problems.append(f"the processes disagree on the best validation loss: "
                        f"{[b.group(1) if b else None for b in best]}")
    for name in ("config.json", "metrics.jsonl"):
        if not (run_dir / name).is_file():
            problems.append(f"{name} was not written")
    # A new run in the same (non-empty) directory: process 0 refuses, and both stop at once.
    start = time.perf_counter()
    codes, logs = _two_processes(_train_args(run_dir, steps))
    refused = time.perf_counter() - start
    if codes != [2, 2] or not all("--resume" in log for log in logs):
        problems.append(f"a second two-process start in a used run directory was not refused "
                        f"by both processes (exit codes {codes}):\n{logs[1][-1500:]}")
    resumed = subprocess.run([sys.executable, "-m", "flowmaps_jax.train", "--resume", "--run-dir",
                              str(run_dir), "--steps", str(steps + 2), "--no-progress"],
                             capture_output=True, text=True, env=_env(), timeout=900)
    if resumed.returncode != 0 or f"Finished {steps + 2} steps" not in resumed.stdout:
        problems.append(f"one process could not continue the two-host run:\n"
                        f"{resumed.stdout[-2000:]}{resumed.stderr[-2000:]}")
    # Back to two processes: continue from step `steps` (step steps + 2 is set aside).
    codes2, logs2 = _two_processes([sys.executable, "-m", "flowmaps_jax.train", "--resume",
                                    "--run-dir", str(run_dir), "--steps", str(steps + 4),
                                    "--from-step", str(steps), "--no-progress"])
    if codes2 != [0, 0] or not all(f"Finished {steps + 4} steps" in log for log in logs2):
        problems.append(f"two processes could not resume from step {steps} (exit codes "
                        f"{codes2}):\n{logs2[0][-1500:]}\n{logs2[1][-1500:]}")
    elif "Moved the later checkpoints" not in logs2[0]:
        problems.append("process 0 did not set the later steps aside")
    print(f"two hosts: {best[0].group(1) if best[0] else '?'} best validation loss after "
          f"{steps} steps; resumed on one process to {steps + 2}: "
          f"{'ok' if resumed.returncode == 0 else 'FAILED'}; a second start in the same "
          f"directory refused by both processes (exit codes {codes}) in {refused:.1f} s; two "
          f"processes resumed from step {steps} to {steps + 4}: exit codes {codes2}")
    return problems


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=6)
    parser.add_argument("--keep", default=None, help="work in this directory and keep it")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = pathlib.Path(args.keep or tmp)
        work.mkdir(parents=True, exist_ok=True)
        problems = check(work, args.steps)
    for problem in problems:
        print("PROBLEM:", problem)
    print("multi-host check:", "FAILED" if problems else "passed")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
