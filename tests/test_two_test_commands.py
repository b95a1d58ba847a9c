"""The README's test command is two pytest runs, the suite and then its end-to-end runs (``-m
slow``); ``.ci/run`` runs exactly that command, and a plain ``pytest`` leaves the slow tests to
the second run (tests/conftest.py)."""

from __future__ import annotations

import pathlib
import re
import types

import conftest
import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]


def _config(markexpr: str, source) -> types.SimpleNamespace:
    deselected = []
    return types.SimpleNamespace(
        option=types.SimpleNamespace(markexpr=markexpr), args_source=source,
        hook=types.SimpleNamespace(pytest_deselected=lambda items: deselected.extend(items)),
        deselected=deselected)


def _item(name: str, slow: bool) -> types.SimpleNamespace:
    return types.SimpleNamespace(name=name, get_closest_marker=lambda mark: (
        object() if slow and mark == "slow" else None))


@pytest.mark.parametrize("markexpr, source, runs", [
    ("", pytest.Config.ArgsSource.TESTPATHS, ["fast"]),  # a plain `pytest`
    ("slow", pytest.Config.ArgsSource.TESTPATHS, ["fast", "slow"]),  # -m chooses (here: all)
    ("", pytest.Config.ArgsSource.ARGS, ["fast", "slow"]),  # a file or node id named
])
def test_a_plain_pytest_leaves_the_slow_tests_to_the_second_run(markexpr, source, runs):
    config = _config(markexpr, source)
    items = [_item("fast", False), _item("slow", True)]
    conftest.pytest_collection_modifyitems(config, items)
    assert [item.name for item in items] == runs
    assert [item.name for item in config.deselected] == (["slow"] if runs == ["fast"] else [])


def test_ci_runs_the_readme_test_command_and_it_runs_both():
    readme = (REPO / "README.md").read_text()
    command = re.search(r"^python -m venv \.venv .*pip install -e '\.\[dev\]'.*$", readme, re.M)
    assert command, "the README's test command (venv, install, pytest) is gone"
    ci = (REPO / ".ci" / "run").read_text().strip().splitlines()[-1]
    assert ci == command.group(0).replace("python -m venv", "python3 -m venv")
    assert command.group(0).endswith(f"&& pytest && {conftest.SLOW_COMMAND}")
