"""Where the suite's time goes: JAX tracing, lowering and XLA compile seconds per test.

An opt-in pytest plugin (not loaded by a plain ``pytest``), and the summary of what it wrote::

    FLOWMAPS_COMPILE_PROFILE=/tmp/profile PYTHONPATH=tests pytest -p compile_profile
    python tests/compile_profile.py /tmp/profile

(the suite; ``-m slow`` profiles its end-to-end runs, ``-m "slow or not slow"`` both at once).

Each process (the xdist workers, or the one process with ``-n 0``) listens to JAX's monitoring
events (``jax.monitoring``: ``jaxpr_trace_duration``, ``jaxpr_to_mlir_module_duration``,
``backend_compile_duration`` with the compiled function's name, and the persistent cache's
``compile_time_saved_sec``), times the checkpoint store's writes and reads
(``CheckpointStore._write``, ``checkpoints._read_step``: orbax) and Python's garbage collections
(``gc.callbacks``), and writes ``<dir>/<worker>.json``: one row per test (its wall seconds, its
CPU seconds with those of the child processes it waited for, and the seconds of each event
inside it), the compile seconds per function, every program written to or loaded from the
persistent compilation cache (its key, the test file, its compile seconds; by wrapping JAX's
private ``compiler._cache_write`` and ``_cache_read``) and the process's peak resident memory.
Inside child processes (notebook kernels, the forced-devices run) nothing is seen but their wall
and CPU time. The summary prints the totals, each worker's test-seconds against its CPU-seconds
(whether the cores were busy), the seconds per test file and the functions that took longest to
compile, and how many compiled programs were loaded again (by another test or worker) against
how many were compiled once and never needed again: sharing a cache cannot save the latter, only
tests that need fewer distinct programs can.

It also counts lowerings and compiles by the line of the repository (``src/``, ``tests/``,
``experiments/``; the innermost on the stack) that started them. A line with hundreds of compiles
is usually eager ``jax.numpy`` work (outside ``jax.jit`` XLA compiles one small program per
operation and shape), and one ``jax.jit`` around its function makes them one program per shape.
"""

from __future__ import annotations

import collections
import functools
import gc
import json
import os
import pathlib
import resource
import sys
import time

EVENTS = {"jaxpr_trace_duration": "trace", "jaxpr_to_mlir_module_duration": "lower",
          "backend_compile_duration": "compile", "compile_time_saved_sec": "cache_saved"}
OTHER_COSTS = ("ckpt_write", "ckpt_read", "gc")  # timed around the store's calls, gc.callbacks


_REPO = str(pathlib.Path(__file__).resolve().parents[1]) + os.sep
_OURS = tuple(_REPO + d + os.sep for d in ("src", "tests", "experiments"))


def _site(frame) -> str:
    """The innermost repository line (``path:line``) on the stack, ``?`` if none."""
    while frame is not None:
        name = frame.f_code.co_filename
        if name.startswith(_OURS):
            return f"{name[len(_REPO):]}:{frame.f_lineno}"
        frame = frame.f_back
    return "?"


class _Recorder:
    def __init__(self):
        self.current = collections.Counter()
        self.functions = collections.Counter()
        self.counts = collections.Counter()
        self.sites = collections.Counter()  # repository line -> lowering + compile seconds
        self.site_counts = collections.Counter()  # repository line -> compiles
        self.rows: list[dict] = []
        self.programs: list[list] = []  # ["write" | "load", cache key, test file, compile s]
        self.test = "?"
        self.start = self.cpu_start = 0.0
        self.gc_start: float | None = None

    def listen(self, event: str, seconds: float, **kwargs) -> None:
        name = EVENTS.get(event.rsplit("/", 1)[-1])
        if name is None:
            return
        self.current[name] += seconds
        if name == "compile":
            self.current["compiles"] += 1
            self.functions[str(kwargs.get("fun_name"))] += seconds
            self.counts[str(kwargs.get("fun_name"))] += 1
        if name in ("lower", "compile"):
            site = _site(sys._getframe(1))
            self.sites[site] += seconds
            self.site_counts[site] += name == "compile"

    def timed(self, name: str, function):
        """``function``, adding its seconds to ``name`` and its calls to ``name + "_n"``."""

        @functools.wraps(function)
        def run(*args, **kwargs):
            start = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                self.current[name] += time.perf_counter() - start
                self.current[name + "_n"] += 1

        return run

    def cache_write(self, write):
        """JAX's ``compiler._cache_write(cache_key, compile_time_secs, ...)``, noting it."""

        @functools.wraps(write)
        def run(cache_key, compile_time_secs, *args, **kwargs):
            self.programs.append(["write", cache_key, self.test, round(compile_time_secs, 4)])
            return write(cache_key, compile_time_secs, *args, **kwargs)

        return run

    def cache_read(self, read):
        """JAX's ``compiler._cache_read(module_name, cache_key, ...)``, noting a find."""

        @functools.wraps(read)
        def run(module_name, cache_key, *args, **kwargs):
            executable, seconds = read(module_name, cache_key, *args, **kwargs)
            if executable is not None:
                self.programs.append(["load", cache_key, self.test, 0.0])
            return executable, seconds

        return run

    def collecting(self, phase: str, info: dict) -> None:
        """A ``gc.callbacks`` entry: the seconds of every collection, under ``gc``."""
        if phase == "start":
            self.gc_start = time.perf_counter()
        elif self.gc_start is not None:
            self.current["gc"] += time.perf_counter() - self.gc_start
            self.current["gc_n"] += 1
            self.gc_start = None


_RECORDER: _Recorder | None = None


def pytest_configure(config):
    global _RECORDER
    if not os.environ.get("FLOWMAPS_COMPILE_PROFILE"):
        raise SystemExit("-p compile_profile needs FLOWMAPS_COMPILE_PROFILE=<directory>")
    from jax import monitoring
    from jax._src import compiler  # private: wrapped only under -p compile_profile

    from flowmaps_jax.store import checkpoint_store, checkpoints

    _RECORDER = _Recorder()
    monitoring.register_event_duration_secs_listener(_RECORDER.listen)
    store = checkpoint_store.CheckpointStore
    store._write = _RECORDER.timed("ckpt_write", store._write)
    checkpoints._read_step = _RECORDER.timed("ckpt_read", checkpoints._read_step)
    gc.callbacks.append(_RECORDER.collecting)
    compiler._cache_write = _RECORDER.cache_write(compiler._cache_write)
    compiler._cache_read = _RECORDER.cache_read(compiler._cache_read)


def _cpu_seconds() -> float:
    """CPU seconds of this process and of its finished children (notebook kernels, the
    forced-devices run)."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


def pytest_runtest_protocol(item, nextitem):
    _RECORDER.current.clear()
    _RECORDER.test = item.nodeid.split("::")[0]
    _RECORDER.start = time.perf_counter()
    _RECORDER.cpu_start = _cpu_seconds()


def pytest_runtest_makereport(item, call):
    if call.when == "teardown":
        _RECORDER.rows.append({"test": item.nodeid, "wall": time.perf_counter() - _RECORDER.start,
                               "cpu": round(_cpu_seconds() - _RECORDER.cpu_start, 3),
                               **{k: round(v, 3) for k, v in _RECORDER.current.items()}})


def pytest_sessionfinish(session):
    out = pathlib.Path(os.environ["FLOWMAPS_COMPILE_PROFILE"])
    out.mkdir(parents=True, exist_ok=True)
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    (out / f"{worker}.json").write_text(json.dumps(
        {"rows": _RECORDER.rows, "functions": _RECORDER.functions.most_common(),
         "counts": dict(_RECORDER.counts), "sites": dict(_RECORDER.sites),
         "site_counts": dict(_RECORDER.site_counts), "programs": _RECORDER.programs,
         "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024}))


def summarise(directory: str, top: int = 25) -> None:
    """Print the totals, seconds per test file and the slowest-compiling functions."""
    rows, functions, counts = [], collections.Counter(), collections.Counter()
    sites, site_counts = collections.Counter(), collections.Counter()
    workers, programs = {}, []
    for path in sorted(pathlib.Path(directory).glob("*.json")):
        data = json.loads(path.read_text())
        rows += data["rows"]
        if data["rows"]:  # the xdist controller runs no tests
            workers[path.stem] = (sum(r["wall"] for r in data["rows"]),
                                  sum(r.get("cpu", 0) for r in data["rows"]),
                                  data.get("max_rss_mb"))
        functions.update(dict(data["functions"]))
        counts.update(data.get("counts", {}))
        sites.update(data.get("sites", {}))
        site_counts.update(data.get("site_counts", {}))
        programs += data.get("programs", [])
    if not rows:
        raise SystemExit(f"no profile in {directory}: run pytest -p compile_profile first")
    total = {k: sum(r.get(k, 0) for r in rows) for k in (
        "wall", *EVENTS.values(), "compiles", *OTHER_COSTS, *(k + "_n" for k in OTHER_COSTS))}
    print(f"{len(rows)} tests, {total['wall']:.0f} test-seconds: XLA compile "
          f"{total['compile']:.0f} s ({total['compiles']:.0f} compiles), tracing "
          f"{total['trace']:.0f} s, lowering {total['lower']:.0f} s; the persistent cache "
          f"saved {total['cache_saved']:.0f} s")
    print(f"checkpoint writes {total['ckpt_write']:.0f} s ({total['ckpt_write_n']:.0f}), "
          f"checkpoint reads {total['ckpt_read']:.0f} s ({total['ckpt_read_n']:.0f}), garbage "
          f"collection {total['gc']:.0f} s ({total['gc_n']:.0f}); in the test processes only")
    if programs:
        _summarise_programs(programs)
    # CPU below wall: a worker waited (I/O, threads); at ~100 % both cores were busy throughout
    for worker, (wall, cpu, rss) in workers.items():
        print(f"{worker}: {wall:.0f} test-seconds, {cpu:.0f} CPU-seconds "
              f"({100 * cpu / max(wall, 1e-9):.0f} %, its children included)"
              + ("" if rss is None else f", peak memory {rss:,} MB"))
    by_file = collections.defaultdict(collections.Counter)
    for r in rows:
        by_file[r["test"].split("::")[0]].update(
            {k: r.get(k, 0) for k in ("wall", "compile", "trace", "lower", *OTHER_COSTS)})
    print(f"\n{'test file':<40} {'wall':>7} {'compile':>8} {'trace+lower':>12} "
          f"{'checkpoints':>12} {'gc':>5}")
    for name, c in sorted(by_file.items(), key=lambda kv: -kv[1]["wall"]):
        print(f"{name:<40} {c['wall']:7.0f} {c['compile']:8.0f} {c['trace'] + c['lower']:12.0f} "
              f"{c['ckpt_write'] + c['ckpt_read']:12.0f} {c['gc']:5.0f}")
    print(f"\n{'function (XLA compile)':<40} {'seconds':>8} {'compiles':>9}")
    for name, seconds in functions.most_common(top):
        print(f"{name:<40} {seconds:8.1f} {counts[name]:9d}")
    if site_counts:
        print(f"\n{'repository line (most compiles)':<60} {'compiles':>9} {'seconds':>8}")
        for site, n in site_counts.most_common(top):
            print(f"{site:<60} {n:9d} {sites[site]:8.1f}")


def _summarise_programs(programs: list[list], top: int = 5) -> None:
    """Programs compiled (persistent-cache writes) against those loaded again, and the test
    files that shared the most."""
    written, loads, pairs = {}, collections.Counter(), collections.Counter()
    for kind, key, test, seconds in programs:
        if kind == "write":
            written.setdefault(key, (test, seconds))
    for kind, key, test, _ in programs:
        if kind == "load" and key in written:
            loads[key] += 1
            pairs[written[key][0], test] += 1
    total = sum(s for _, s in written.values())
    again = sum(written[k][1] for k in loads)
    print(f"programs: {len(written):,} compiled ({total:.0f} s); {len(loads):,} of them loaded "
          f"again from the persistent cache ({sum(loads.values()):,} loads, {again:.0f} s of "
          f"compile spared); the other {len(written) - len(loads):,} "
          f"({100 * (total - again) / max(total, 1e-9):.0f} % of the compile seconds) were "
          f"compiled once and never loaded again")
    for (source, user), n in pairs.most_common(top):
        print(f"  {n:5d} programs of {source} loaded by {user}")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: python tests/compile_profile.py DIRECTORY")
    summarise(sys.argv[1])
