"""Every script in experiments/ runs (issue 17, item 6), at a tiny size, so that a refactor of the
package cannot leave a benchmark, sweep, diagnosis or figure script broken.

One test per script: ``python experiments/<script> <tiny arguments>``, run in the test's own
process (:func:`support.run_python_in_process`: the script as ``__main__`` with its ``sys.argv``;
JAX is imported once and the scripts share compiled programs) in a fresh temporary working
directory (every output directory the script takes is given inside it, so nothing is written
into the repository), with ``MPLBACKEND=Agg``. It must exit 0 and print what the script exists
to print (a table row with numbers, a "wrote" line, ...): a regular expression per script, so
that a script that runs but prints nothing useful fails too. The tiny sizes are the scripts' own
options (one size, one repeat, a few steps, the smoke preset, a few environments);
``check_behaviour.py`` has ``--smoke`` for this. The numbers are not
checked: at these sizes they mean nothing.

They run with XLA's ``jax_disable_most_optimizations`` (:func:`support.fast_compile`, and
``JAX_DISABLE_MOST_OPTIMIZATIONS=true`` for the child processes that ``bench_train.py`` and
``bench_scale.py`` start; ``check_behaviour.py --smoke`` runs its CLIs in-process): compilation
dominates these runs and skipping most of XLA's optimisation passes halves it (the programs are
the same, they only run slower, which does not matter at these sizes). JAX's caches are cleared
when the module is done, so no later test reuses those programs. Child processes share the
suite's persistent XLA cache (tests/conftest.py).

``check_multihost.py`` is not run here: it starts two JAX processes joined by
``jax.distributed`` (about 2 minutes on 2 cores); tests/test_distributed.py runs it when
``FLOWMAPS_TEST_MULTIHOST=1``. The notebooks (``*.ipynb``) run in tests/test_notebooks.py.

A new script needs an entry in :data:`TINY` (or :data:`NOT_RUN`, with the reason):
:func:`test_every_script_is_covered` fails until it has one.
"""

from __future__ import annotations

import pathlib
import re
import time

import pytest
from support import fast_compile, run_python_in_process

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("fast_compiled_module")]

REPO = pathlib.Path(__file__).resolve().parents[1]
EXPERIMENTS = REPO / "experiments"
NUM = r"-?[\d,]+(?:\.\d+)?"  # a printed number: 12, 1,234, 0.125, -8.8

# script -> (tiny arguments, what its output must contain (regex, multiline), files it must
# write, relative to the working directory). Seconds: measured on the 2-core machine with a
# training running beside it, cold XLA cache.
TINY: dict[str, tuple[list[str], str, list[str]]] = {
    # ~15 s: 4 environments, 1 repeat, the paper's world and the mixed habits world with
    # histories of 2
    "bench_flowsim.py": (
        ["--sizes", "4", "--repeats", "1", "--world", "routine", "mixed", "--history", "2"],
        rf"^world: mixed .*\n(?:.*\n)*^\s+4\s+{NUM}\s+{NUM}\s+{NUM}\s+{NUM}\s+{NUM}\s+{NUM}$",
        []),
    # ~10 s: the homes-smoke preset's own 6 steps, a rate every 2 (one child process; the
    # program is that of the suite's homes-smoke run, tests/conftest.py, found in its cache)
    "bench_homes_train.py": (
        ["--presets", "homes-smoke", "--steps", "6", "--log-every", "2"],
        rf'^\{{"preset": "homes-smoke", .*"steps_per_sec": {NUM}\}}$', []),
    # ~10 s: 8 homes x 4 queries, 16 DP episodes, the priors on 4 homes x 2 queries, 1 repeat
    "bench_homes_navigation.py": (
        ["--homes", "8", "--queries", "4", "--dp-episodes", "16", "--prior-homes", "4",
         "--prior-queries", "2", "--repeats", "1"],
        rf"^\s+most-probable:\s+{NUM} episodes/s(?:.*\n)*^\s+optimal:\s+{NUM} episodes/s"
        rf"(?:.*\n)*^prior\s+uniform:\s+{NUM} prior evaluations/s", []),
    # ~45 s: a D=16 one-layer model, B=2 × Q=2, 1 timed step, and the sampling benchmark
    "bench_model.py": (
        ["--queries", "2", "--batch", "2", "--steps", "1", "--dim", "16", "--encoder-layers", "1",
         "--cdit-blocks", "1", "--heads", "2", "--sampling"],
        rf"^B=2 Q=2: .*{NUM} query-samples/s wall.*\n^sampling .* {NUM} samples/s wall", []),
    # ~20 s: smoke-size model, 2 queries × 2 samples, 3 grid points, 1 repeat
    "bench_sample.py": (
        ["--preset", "smoke", "--queries", "2", "--samples", "2", "--num-steps", "3",
         "--logp-queries", "3", "--logp-draws", "2", "--repeats", "1"],
        rf"^sample: 2 queries .* {NUM} samples/s.*\n^log_prob: 3 queries .* {NUM} boxes/s", []),
    # ~30 s: the smoke preset on 1 device (one child process), 1 timed step
    "bench_scale.py": (
        ["--devices", "1", "--preset", "smoke", "--steps", "1", "--sample-scenes", "2",
         "--samples", "2"],
        rf"^\| 1 \| float32 \| 8 × 2 \| {NUM} \| {NUM} \| {NUM} \(1\.00×\) \|", []),
    # ~6 s: 16 episodes, budget 3, 1 repeat, every policy
    "bench_search.py": (
        ["--episodes", "16", "--budget", "3", "--repeats", "1"],
        rf"^\s+optimal:\s+{NUM} episodes/s", []),
    # ~25 s: the smoke preset, Q=1, B=2, 1 timed step (one child process)
    "bench_train.py": (
        ["--presets", "smoke", "--queries", "1", "--steps", "1", "--envs", "4", "--batch", "2"],
        rf"^smoke\s+32\s+1\+1\s+2\s+1\s+{NUM}\s+{NUM}\s+{NUM}\s+{NUM}\s+{NUM}$", []),
    # ~40 s: two smoke trainings (4 steps each) and a 2-environment evaluation; compared
    # with itself, so the comparison runs too
    "check_behaviour.py": (
        ["--smoke", "--out", "fingerprint.json", "--compare", "fingerprint.json"],
        r"^identical to fingerprint\.json \(atol 0\.0\)$", ["fingerprint.json"]),
    # ~30 s: 1 environment, 2 draws, one grid size per solver, both models (the fresh route
    # head at the smoke preset's size)
    "check_likelihood.py": (
        ["--envs", "1", "--draws", "2", "--midpoint", "3", "--accurate", "3", "--preset",
         "smoke"],
        rf"^pretrained:flowmaps \(step \d+\)\n.*\n^\s+midpoint\s+3\s+{NUM}.*\n^\s+accurate\s+3\s+"
        rf"{NUM}", []),
    # ~20 s: the preferences world, 2 environments
    "habits_exact.py": (
        ["--worlds", "preferences", "--num-envs", "8"],
        rf"^\| exact, H = 1 \| {NUM} \| {NUM} \| {NUM} \| {NUM} ± {NUM} \|$", []),
    # ~20 s: the shipped (routine-world, H = 1) model on 2 environments
    "habits_model.py": (
        ["--checkpoint", "pretrained:flowmaps", "--num-envs", "2", "--by-horizon"],
        rf"^\| pretrained:flowmaps \(H = 1, step \d+\) \| {NUM} \| {NUM} \| {NUM} \| {NUM} ± "
        rf"{NUM} \| {NUM} \|$(?:.*\n)*^\| (?:\d|≥ 6) \| \d+ \| {NUM} \({NUM}\) \| "
        rf"1\.0000 \(1\.00\) \|$", []),
    # ~25 s: the README quick start; it prints nothing and writes fork_next.png
    "quickstart.py": ([], "", ["fork_next.png"]),
    # ~35 s: the docs figures and the quick-start figure, into figures/
    "render_docs_figures.py": (
        ["--out", "figures"],
        r"^wrote figures/flowsim_posterior\.png$(?:.*\n)*^wrote .*quickstart_fork\.png$",
        ["figures/flowsim_scene.png", "figures/flowsim_timeline.png",
         "figures/flowsim_orders.png", "figures/flowsim_posterior.png",
         "figures/quickstart_fork.png"]),
    # ~10 s: one variant with an override, the smoke preset, 2 environments scored (4 KL draws,
    # the accurate likelihood on 3 grid points). At the preset's own 20 steps (warm-up 2) and lr,
    # the training is the suite's smoke run's program (tests/conftest.py), and the KL draws
    # those of the README's shortened evaluate (tests/test_docs_commands.py)
    "sweep_settings.py": (
        ["tiny:lr=1e-3", "--preset", "smoke", "--steps", "20", "--eval-envs", "2", "--kl-draws",
         "4", "--likelihood-steps", "3", "--out", "sweep_settings"],
        rf'^\{{"name": "tiny", "overrides": \["lr=1e-3"\], "steps": 20, .*"kl": {NUM}',
        ["sweep_settings/tiny/metrics.jsonl"]),
}
NOT_RUN = {
    "check_multihost.py": "two JAX processes joined by jax.distributed, about 2 minutes on 2 "
                          "cores: tests/test_distributed.py::test_two_hosts runs it with "
                          "FLOWMAPS_TEST_MULTIHOST=1",
}
MAX_SCRIPTS = 16  # bench_homes_train.py (issue 54) joined the benchmarks
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_every_script_is_covered():
    """Each experiments/*.py has a tiny run here or a reason not to, and no entry is stale."""
    scripts = {p.name for p in EXPERIMENTS.glob("*.py")}
    assert not scripts - set(TINY) - set(NOT_RUN), (
        f"give {sorted(scripts - set(TINY) - set(NOT_RUN))} tiny arguments in TINY")
    assert not (set(TINY) | set(NOT_RUN)) - scripts, (
        f"{sorted((set(TINY) | set(NOT_RUN)) - scripts)} no longer exist: remove them")
    assert not set(TINY) & set(NOT_RUN)
    # issue 49: the benchmarks and the tools a user or a test runs, not one-off diagnostics (those
    # go once their findings are recorded in docs/results.md, with their commands)
    assert len(scripts) <= MAX_SCRIPTS, f"{len(scripts)} scripts in experiments/: at most " \
        f"{MAX_SCRIPTS}"


@pytest.mark.parametrize("script", sorted(TINY.keys() | NOT_RUN.keys()))
def test_script_runs_at_a_tiny_size(script, tmp_path, monkeypatch):
    if script in NOT_RUN:
        pytest.skip(f"{script}: {NOT_RUN[script]}")
    if not (EXPERIMENTS / script).exists():
        pytest.fail(f"experiments/{script} is gone: remove its entry from TINY")
    args, expected, files = TINY[script]
    monkeypatch.setenv("MPLBACKEND", "Agg")
    monkeypatch.setenv("JAX_DISABLE_MOST_OPTIMIZATIONS", "true")  # for child processes
    start = time.perf_counter()
    with fast_compile():
        code, output = run_python_in_process([str(EXPERIMENTS / script), *args], tmp_path)
    seconds = time.perf_counter() - start
    print(f"{script} {' '.join(args)}: exit {code} in {seconds:.1f} s")
    command = f"$ python experiments/{script} {' '.join(args)}"
    assert code == 0, f"{command}\nexit code {code}\n{output[-6000:]}"
    assert re.search(expected, output, re.MULTILINE), (
        f"{command}\nthe output lacks /{expected}/:\n{output[-6000:]}")
    for name in files:
        path = tmp_path / name
        assert path.is_file() and path.stat().st_size > 0, f"{command}\ndid not write {name}"
        if name.endswith(".png"):
            assert path.read_bytes()[:8] == PNG_MAGIC, f"{name} is not a PNG"


@pytest.mark.parametrize("args, named", [
    (["--kl-draws", "1"], "kl-draws"),
    (["--likelihood-steps", "2"], "likelihood-steps"),
    (["--kl-draws", "100000000"], "--kl-draws 100000000"),  # the shared memory estimate
    (["later:bogus=1"], "bogus"),  # a bad second variant, found before the first trains
])
def test_sweep_settings_checks_everything_before_training(args, named, tmp_path):
    """A bad option, an evaluation too large for the shared resource budget, or a bad variant
    stops sweep_settings.py before the first variant trains: a ValueError naming it, and no run
    directory written."""
    code, output = run_python_in_process(
        [str(EXPERIMENTS / "sweep_settings.py"), "tiny:lr=1e-3", *args, "--preset", "smoke",
         "--steps", "2", "--eval-envs", "2", "--out", "sweep"], tmp_path)
    assert code == 1 and "ValueError" in output and named in output.replace("_", "-")
    assert not (tmp_path / "sweep").exists()
