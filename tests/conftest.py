"""Shared fixtures. JAX compile time dominates the suite, so generated data is made once per
session and always with the same number of environments (``SMALL_NUM_ENVS``): ``generate`` is
compiled once per (config shape, number of environments), and tests that call it themselves
should use this size to reuse the compiled function."""

from __future__ import annotations

import atexit
import fcntl
import functools
import gc
import json
import os
import pathlib
import shutil
import signal
import tempfile
import time
import types

# One persistent XLA compilation cache per test session, shared by the xdist workers and by the
# subprocesses and notebook kernels the tests start (they inherit the environment): a function
# compiled by one process is loaded by the others. Set before JAX is imported, by the first
# process (removed when it exits); a user's own setting wins. Every program is stored, however
# fast it compiled: most of the suite's thousands of compiles are small, and the two workers and
# the children build many of the same ones (idle 2-core run: pytest 638 s with a 0.5 s floor,
# 538 s with none; docs/results.md, "Test suite time").
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    _cache = tempfile.mkdtemp(prefix="flowmaps-jax-xla-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _cache
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
# Compilation dominates the suite (tiny models, a few steps): XLA's
# ``jax_disable_most_optimizations`` about halves it. The programs are the same, their machine
# code less optimised; tests comparing two programs compare them under the same flag, and the
# stored numbers (the paper world's SHA-256, the shipped models' checks) hold under it too.
# Workers, subprocesses and notebook kernels inherit it; a user's own setting wins.
os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "true")
# XLA:CPU's newer fusion emitters take about twice as long to compile as the classic elemental
# emitter (docs/results.md, "Test suite time", measured by bench_compile.py before issue 49).
# Same programs, rounded differently in places (tests/multidevice's tolerances hold under both).
# Appended unless XLA_FLAGS chooses.
if "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + " --xla_cpu_use_fusion_emitters=false").strip()

import jax
import pytest

from flowmaps_jax.flowsim import FlowSimConfig, Scenes, generate

SMALL_NUM_ENVS = 256


_collected = [time.monotonic()]
# Python collects its oldest generation after every 10 collections of the middle one; in a test
# that traces and compiles (millions of objects made, most kept by JAX's caches) each such pass
# takes about 0.2 s, and garbage collection was 7 % of the suite's time (tests/compile_profile.py;
# docs/results.md). After every 100: what a test leaves is collected between tests (below).
gc.set_threshold(700, 10, 100)


@pytest.fixture(autouse=True)
def _young_heap():
    """Garbage collection during a test sees only the objects made in it (``gc.freeze`` of the
    older ones): a full collection of a session's heap (every compiled program: about 700,000
    objects) takes about a second. What died in earlier tests is collected between two tests,
    at most every 120 s."""
    gc.freeze()
    yield
    gc.unfreeze()
    if time.monotonic() - _collected[0] > 120:
        gc.collect()
        _collected[0] = time.monotonic()


@pytest.fixture(scope="session", autouse=True)
def _collected_at_the_end():
    """What is left is collected while the last test ends, not after it: an xdist worker still
    busy 5 s after it is told to stop gets a SIGINT (execnet), which can land in a gc callback."""
    yield
    gc.collect()


@pytest.fixture(scope="module")
def fast_compiled_module():
    """For a module that compiles under ``support.fast_compile``: JAX's caches are dropped when
    it is done, unless the whole suite compiles that way (above), so that later tests do not
    reuse its less optimised programs (the flag is not part of ``jax.jit``'s cache key)."""
    flag_was_on = jax.config.read("jax_disable_most_optimizations")
    yield
    if not flag_was_on:
        jax.clear_caches()


@pytest.fixture(scope="session")
def flowsim_config() -> FlowSimConfig:
    """The paper's FlowSim configuration."""
    return FlowSimConfig()


@pytest.fixture(scope="session")
def small_scenes(flowsim_config) -> Scenes:
    """SMALL_NUM_ENVS environments from the default config, key 0."""
    return generate(jax.random.key(0), SMALL_NUM_ENVS, flowsim_config)


# ------------------------------------------------------------------ the two test commands

SLOW_COMMAND = "pytest -m slow"


def _leaves_slow(config) -> bool:
    return not config.option.markexpr and config.args_source == pytest.Config.ArgsSource.TESTPATHS


def pytest_collection_modifyitems(config, items):
    """A plain ``pytest`` (no test named, no ``-m``) runs the suite without the tests marked
    ``slow``: the end-to-end runs of the documented commands, the experiments/ scripts, the
    notebooks, the two-device child process and the tests that train, evaluate and search through
    the CLIs. ``pytest -m slow`` runs those; the README's test command runs both, one after the
    other. Naming tests (a file, a node id) or giving ``-m`` selects as usual, the slow ones
    included."""
    if not _leaves_slow(config):
        return
    slow = [item for item in items if item.get_closest_marker("slow")]
    items[:] = [item for item in items if not item.get_closest_marker("slow")]
    config.hook.pytest_deselected(items=slow)


def pytest_terminal_summary(terminalreporter, config):
    if _leaves_slow(config) and not os.environ.get("PYTEST_XDIST_WORKER"):
        terminalreporter.write_line(f"The tests marked slow were left to `{SLOW_COMMAND}` (the "
                                    f"README's test command runs it after this one).")


# tests/multidevice needs several JAX devices, fixed when JAX starts: tests/test_distributed.py
# runs it in a subprocess with XLA_FLAGS=--xla_force_host_platform_device_count=2 and
# FLOWMAPS_MULTIDEVICE=1. A plain `pytest` does not collect it directly.
collect_ignore_glob = [] if os.environ.get("FLOWMAPS_MULTIDEVICE") else ["multidevice/*"]



# ------------------------------------------------------------------ one trained run per world

def _shared_dir(tmp_path_factory, name: str) -> pathlib.Path:
    """The folder ``name`` that every xdist worker of this session finds (in the parent of their
    base temporary folders); a new one of this process's without xdist."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return tmp_path_factory.mktemp(name)
    path = tmp_path_factory.getbasetemp().parent / name
    path.mkdir(exist_ok=True)
    return path


def _made_once(root: pathlib.Path, name: str, make) -> dict:
    """``root / name`` made by ``make()`` once per session: by the first process (xdist worker)
    that asks, holding a lock, while the others wait. Returns the dict (JSON) ``make`` returned,
    saved as ``name.json`` when it is done; a try that failed is removed and made again."""
    record = root / f"{name}.json"
    with open(root / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file is closed
        if not record.exists():
            shutil.rmtree(root / name, ignore_errors=True)
            made = json.dumps(make())
            (root / f"{name}.json.tmp").write_text(made)
            os.replace(root / f"{name}.json.tmp", record)
        return json.loads(record.read_text())


class SmokeRuns:
    """A world's smoke preset trained once per test session (the xdist workers share it: the
    first to ask trains, :func:`_made_once`), each run on first use, through the train CLI in
    this process (:func:`support.run_python_in_process`):

    * ``straight``: never stopped (its output ``printed``; ``saves``: the (folder, step) of every
      checkpoint write, in order);
    * ``stopped``: Ctrl-C (SIGINT from a step callback) at step ``stop_at``, not a multiple of
      the checkpoint interval (``interrupted``: the loop result's ``status`` and ``step``);
    * ``resumed``: a copy of ``stopped`` resumed to the end with ``--resume``.

    Tests only read them; a test that changes a run works on ``copy(name, tmp_path)``."""

    def __init__(self, root: pathlib.Path, args: list[str], stop_at: int):
        self.root, self.args, self.stop_at = root, args, stop_at
        from flowmaps_jax.training import cli

        self.cfg = cli.resolve_config(cli.build_parser().parse_args(
            [*args, "--run-dir", str(root / "x")]))[0]

    def _train(self, name: str, *extra: str) -> str:
        from support import run_python_in_process

        code, out = run_python_in_process(
            ["-m", "flowmaps_jax.train", "--run-dir", str(self.root / name), "--no-progress",
             *extra], self.root)
        assert code == 0, out
        return out

    @functools.cached_property
    def straight(self) -> pathlib.Path:
        from flowmaps_jax.store.checkpoint_store import CheckpointStore
        from flowmaps_jax.worlds import flowsim

        def make():
            flowsim._SPLIT_CACHE.clear()  # the split is generated (and said) by this run
            saves, write = [], CheckpointStore._write

            def counted(store, manager, step, *args, **kwargs):
                write(store, manager, step, *args, **kwargs)
                saves.append((pathlib.Path(str(manager.directory)).name, step))

            with pytest.MonkeyPatch.context() as patch:
                patch.setattr(CheckpointStore, "_write", counted)
                return {"printed": self._train("straight", *self.args), "saves": saves}

        made = _made_once(self.root, "straight", make)
        self.printed, self.saves = made["printed"], [tuple(save) for save in made["saves"]]
        return self.root / "straight"

    @functools.cached_property
    def stopped(self) -> pathlib.Path:
        from flowmaps_jax.training import loop

        def ctrl_c(step, metrics):
            if step == self.stop_at:
                os.kill(os.getpid(), signal.SIGINT)

        def make():
            result = loop.run(self.cfg, self.root / "stopped", on_step=ctrl_c, progress=False,
                              log=lambda _: None)
            return {"status": result.status, "step": result.step}

        self.interrupted = types.SimpleNamespace(**_made_once(self.root, "stopped", make))
        return self.root / "stopped"

    @functools.cached_property
    def resumed(self) -> pathlib.Path:
        stopped = self.stopped

        def make():
            shutil.copytree(stopped, self.root / "resumed")
            return {"printed": self._train("resumed", "--resume")}

        self.resumed_printed = _made_once(self.root, "resumed", make)["printed"]
        return self.root / "resumed"

    def copy(self, name: str, tmp_path: pathlib.Path) -> pathlib.Path:
        """A fresh copy of run ``name`` (``straight``, ``stopped`` or ``resumed``)."""
        return pathlib.Path(shutil.copytree(getattr(self, name), tmp_path / "run"))


@pytest.fixture(scope="session")
def flowsim_runs(tmp_path_factory) -> SmokeRuns:
    """The 2-D FlowSim ``smoke`` preset (20 steps; Ctrl-C at 12: last/ holds 10 and 12)."""
    return SmokeRuns(_shared_dir(tmp_path_factory, "flowsim-runs"), ["--preset", "smoke"], 12)


@pytest.fixture
def at12(flowsim_runs, tmp_path) -> pathlib.Path:
    """A fresh copy of the 2-D smoke run stopped (Ctrl-C) at step 12, in ``tmp_path / "run"``."""
    return flowsim_runs.copy("stopped", tmp_path)


@pytest.fixture(scope="session")
def homes_runs(tmp_path_factory) -> SmokeRuns:
    """FlowSim homes, ``homes-smoke`` (6 steps; Ctrl-C at 4: last/ holds 3 and 4)."""
    return SmokeRuns(_shared_dir(tmp_path_factory, "homes-runs"), ["--preset", "homes-smoke"], 4)


@pytest.fixture(scope="session")
def recorded_data(tmp_path_factory) -> pathlib.Path:
    """3 FlowSim homes x 72 hours as a recorded dataset, 30 % of the object-hours masked (made
    once per session, :func:`_made_once`)."""
    from flowmaps_jax.flowsim.homes import HomesConfig, generate_homes
    from flowmaps_jax.recorded.format import save_recorded
    from flowmaps_jax.recorded.from_homes import from_homes

    config = HomesConfig(regime="mixed", num_hours=72,
                         rooms=("kitchen", "living_room", "bedroom", "bathroom"),
                         objects_per_home=(4, 6))
    root = _shared_dir(tmp_path_factory, "recorded")

    def make():
        save_recorded(from_homes(generate_homes(jax.random.key(0), config, 3), config,
                                 mask_fraction=0.3, seed=0), root / "data")
        return {}

    _made_once(root, "data", make)
    return root / "data"


@pytest.fixture(scope="session")
def recorded_runs(tmp_path_factory, recorded_data) -> SmokeRuns:
    """``--preset smoke --data`` on :func:`recorded_data`, 4 steps, a checkpoint every 2
    (Ctrl-C at 3: last/ holds 2 and 3)."""
    return SmokeRuns(_shared_dir(tmp_path_factory, "recorded-runs"), [
        "--preset", "smoke", "--data", str(recorded_data), "--steps", "4", "--set",
        "val_every=2", "--set", "ckpt_every=2", "--set", "log_every=1"], 3)
