"""tests/compile_profile.py (the suite's own profile): the recorder and the summary."""

from __future__ import annotations

import json
import re
import sys

import compile_profile
import pytest


def test_recorder_sorts_events_and_counts_compiles():
    rec = compile_profile._Recorder()
    rec.listen("/jax/core/compile/backend_compile_duration", 2.0, fun_name="jit(step)")
    rec.listen("/jax/core/compile/backend_compile_duration", 1.0, fun_name="jit(step)")
    rec.listen("/jax/core/compile/jaxpr_trace_duration", 0.5, fun_name="step")
    rec.listen("/jax/checkpoint/write/blocking_duration_secs", 9.0)  # not ours: ignored
    assert rec.current == {"compile": 3.0, "compiles": 2, "trace": 0.5}
    assert rec.functions == {"jit(step)": 3.0} and rec.counts == {"jit(step)": 2}


def test_recorder_names_the_repository_line_that_compiled():
    import jax
    import jax.numpy as jnp
    from jax import monitoring

    rec = compile_profile._Recorder()
    monitoring.register_event_duration_secs_listener(rec.listen)
    try:
        x = jnp.zeros((3, 1, 7)) + 1.0  # eager, at shapes nothing else uses: compiled here
        eager_line = sys._getframe().f_lineno - 1
        doubled = jax.jit(lambda v: v * 2.0)(x)
        jit_line = sys._getframe().f_lineno - 1
    finally:
        monitoring.unregister_event_duration_listener(rec.listen)
    assert doubled.shape == (3, 1, 7)
    here = "tests/test_compile_profile.py"
    assert rec.site_counts[f"{here}:{jit_line}"] == 1
    assert rec.site_counts[f"{here}:{eager_line}"] == sum(rec.counts.values()) - 1 >= 1
    assert set(rec.sites) == {f"{here}:{eager_line}", f"{here}:{jit_line}"}


def test_summary_adds_the_workers_up(tmp_path, capsys):
    for worker, wall in (("gw0", 10.0), ("gw1", 4.0)):
        (tmp_path / f"{worker}.json").write_text(json.dumps({
            "rows": [{"test": f"tests/test_{worker}.py::t", "wall": wall, "cpu": wall * 0.9,
                      "compile": wall / 2, "compiles": 3, "trace": 1.0, "lower": 0.5,
                      "ckpt_write": 1.0, "ckpt_write_n": 2, "ckpt_read": 0.5, "ckpt_read_n": 1,
                      "gc": 0.25, "gc_n": 4}],
            "functions": [["jit(step)", wall / 2]], "counts": {"jit(step)": 3},
            "sites": {"src/a.py:7": wall / 4}, "site_counts": {"src/a.py:7": 3},
            "max_rss_mb": 1500}))
    compile_profile.summarise(str(tmp_path))
    out = capsys.readouterr().out
    assert out.startswith("2 tests, 14 test-seconds: XLA compile 7 s (6 compiles), tracing 2 s")
    assert "checkpoint writes 2 s (4), checkpoint reads 1 s (2), garbage collection 0 s (8)" in out
    assert "gw0: 10 test-seconds, 9 CPU-seconds (90 %" in out and "gw1: 4 test-seconds" in out
    assert "peak memory 1,500 MB" in out
    lines = out.splitlines()
    assert "tests/test_gw0.py" in lines[lines.index(next(x for x in lines if x.startswith(
        "test file"))) + 1]  # the slowest file first
    assert re.search(r"^jit\(step\)\s+7\.0\s+6$", out, re.MULTILINE)
    assert re.search(r"^src/a\.py:7\s+6\s+3\.5$", out, re.MULTILINE)


def test_summary_of_nothing_says_so(tmp_path):
    with pytest.raises(SystemExit, match="no profile"):
        compile_profile.summarise(str(tmp_path))


def test_recorder_times_the_store_and_the_collector():
    """``timed`` adds a call's seconds and count even when it raises; ``collecting`` (a
    ``gc.callbacks`` entry) adds the seconds of each collection."""
    import gc
    import time

    rec = compile_profile._Recorder()

    def slow(fail: bool):
        time.sleep(0.02)
        if fail:
            raise ValueError("damaged")
        return 7

    timed = rec.timed("ckpt_read", slow)
    assert timed(False) == 7
    with pytest.raises(ValueError, match="damaged"):
        timed(True)
    assert rec.current["ckpt_read_n"] == 2 and rec.current["ckpt_read"] >= 0.04
    gc.callbacks.append(rec.collecting)
    try:
        gc.collect()
    finally:
        gc.callbacks.remove(rec.collecting)
    assert rec.current["gc_n"] == 1 and rec.current["gc"] > 0


def test_programs_loaded_again_are_told_from_those_compiled_once(capsys):
    """The persistent cache's writes (compiled) and successful reads (loaded again), by test
    file; the wrapped functions are JAX's own, with the arguments the wrappers read."""
    import inspect

    from jax._src import compiler

    assert list(inspect.signature(compiler._cache_write).parameters)[:2] == [
        "cache_key", "compile_time_secs"]
    assert list(inspect.signature(compiler._cache_read).parameters)[:2] == [
        "module_name", "cache_key"]
    rec = compile_profile._Recorder()
    rec.test = "tests/test_a.py"
    write = rec.cache_write(lambda key, seconds, *rest: None)
    read = rec.cache_read(lambda name, key, *rest: (object(), 2) if key == "k1" else (None, None))
    write("k1", 2.0, "jit_f")
    write("k2", 6.0, "jit_g")
    rec.test = "tests/test_b.py"
    assert read("jit_f", "k1")[1] == 2 and read("jit_h", "k3") == (None, None)
    assert rec.programs == [["write", "k1", "tests/test_a.py", 2.0],
                            ["write", "k2", "tests/test_a.py", 6.0],
                            ["load", "k1", "tests/test_b.py", 0.0]]
    compile_profile._summarise_programs(rec.programs)
    out = capsys.readouterr().out
    assert out.startswith("programs: 2 compiled (8 s); 1 of them loaded again from the persistent "
                          "cache (1 loads, 2 s of compile spared); the other 1 (75 % of the "
                          "compile seconds) were compiled once and never loaded again")
    assert "    1 programs of tests/test_a.py loaded by tests/test_b.py" in out
