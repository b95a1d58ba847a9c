"""The notebooks in experiments/ run end to end and produce their key outputs.

The module's notebooks run one after the other in ONE "python3" kernel of this venv (nbclient),
started when the first notebook is needed and shut down at the end of the module, so they share its
imports and its in-memory compiled programs. Each notebook is executed at most once per module, when
the first test that needs it runs, top to bottom in a clean namespace (``%reset -f`` first) with its
own temporary directory as working directory. A notebook's failure (its error, a cell over
``CELL_TIMEOUT``, a dead kernel) is raised by that notebook's tests only; the kernel is then shut
down and the next notebook gets a fresh one. The module is marked ``slow`` (a kernel in a child
process, end to end): ``pytest -m slow`` runs it, a plain ``pytest`` leaves it (tests/conftest.py).
The kernel runs with ``JAX_DISABLE_MOST_OPTIMIZATIONS=true``: compilation dominates these small
runs and skipping most of XLA's optimisation passes about halves it (the programs are the same,
only their machine code is less optimised); ``kl_plots.ipynb`` turns it on for ``smoke`` anyway.
``kl_plots.ipynb`` runs with its default parameters: the ``smoke`` preset (it trains FlowMaps and
the MLP baseline for 20 steps and evaluates them on a few environments), so its numbers are not
checked, only that the table, figures and files are there and the oracle row is exact.
"""

from __future__ import annotations

import base64
import json
import os
import pathlib
import re

import nbformat
import numpy as np
import pytest
from jupyter_client.manager import AsyncKernelManager
from jupyter_core.utils import run_sync
from nbclient import NotebookClient

EXPERIMENTS = pathlib.Path(__file__).resolve().parents[1] / "experiments"
TOUR = "flowsim_tour.ipynb"
KL_PLOTS = "kl_plots.ipynb"
SEARCH = "search_demo.ipynb"
HABITS = "habits.ipynb"
HOMES = "homes.ipynb"
NOTEBOOKS = (TOUR, KL_PLOTS, SEARCH, HABITS, HOMES)
pytestmark = pytest.mark.slow
CELL_TIMEOUT = 900  # seconds; a cold kernel on a loaded 2-core machine compiles slowly
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


class _Kernel:
    """The module's kernel: started by the first notebook run, replaced after a failed one."""

    def __init__(self):
        self.km: AsyncKernelManager | None = None

    def execute(self, name: str, workdir: pathlib.Path) -> nbformat.NotebookNode | Exception:
        """Execute one notebook in a clean namespace in its working directory. A failure is
        returned (and raised by the tests of that notebook), not raised here."""
        notebook = nbformat.read(EXPERIMENTS / name, as_version=4)
        # Leaves no name behind: a notebook that forgets an import still fails.
        notebook.cells.insert(0, nbformat.v4.new_code_cell(
            f"%reset -f\n__import__('os').chdir({str(workdir)!r})"))
        if self.km is None:
            self.km = AsyncKernelManager(kernel_name="python3")
        client = NotebookClient(notebook, km=self.km, timeout=CELL_TIMEOUT,
                                resources={"metadata": {"path": str(workdir)}})
        try:  # the environment applies when this call starts the kernel
            client.execute(env=dict(os.environ, JAX_DISABLE_MOST_OPTIMIZATIONS="true"))
        except Exception as err:
            self.shutdown()  # it may still be running the failed cell
            return err
        finally:
            if client.kc is not None:
                client.kc.stop_channels()
        del notebook.cells[0]
        return notebook

    def shutdown(self):
        """Kill the kernel (a graceful shutdown waits seconds for its exit; nothing is lost: each
        notebook's files are written by the time its last cell returns)."""
        if self.km is not None and self.km.has_kernel:
            run_sync(self.km.shutdown_kernel)(now=True)
        self.km = None


class _Executed(dict):
    """name -> executed notebook (or its failure), run on first access."""

    def __init__(self, kernel: _Kernel, workdirs: dict[str, pathlib.Path]):
        super().__init__()
        self.kernel = kernel
        self.workdirs = workdirs

    def __missing__(self, name: str):
        self[name] = self.kernel.execute(name, self.workdirs[name])
        return self[name]


@pytest.fixture(scope="module")
def workdirs(tmp_path_factory) -> dict[str, pathlib.Path]:
    return {name: tmp_path_factory.mktemp(name.removesuffix(".ipynb")) for name in NOTEBOOKS}


@pytest.fixture(scope="module")
def executed(workdirs):
    kernel = _Kernel()
    try:
        yield _Executed(kernel, workdirs)
    finally:
        kernel.shutdown()


def _notebook(executed: dict, name: str) -> nbformat.NotebookNode:
    outcome = executed[name]
    if isinstance(outcome, BaseException):
        raise AssertionError(f"{name} failed to run:\n{outcome}") from outcome
    return outcome


def _outputs(nb: nbformat.NotebookNode) -> list[dict]:
    return [out for cell in nb.cells if cell.cell_type == "code" for out in cell.outputs]


def _stdout(nb: nbformat.NotebookNode) -> str:
    return "".join(o["text"] for o in _outputs(nb)
                   if o["output_type"] == "stream" and o["name"] == "stdout")


def _images(nb: nbformat.NotebookNode) -> list[bytes]:
    return [base64.b64decode(o["data"]["image/png"]) for o in _outputs(nb)
            if "image/png" in o.get("data", {})]


# --------------------------------------------------------------------------- stored notebooks


@pytest.mark.parametrize("name", NOTEBOOKS)
def test_notebook_is_stored_clean(name):
    """Stored without outputs or execution counts (small diffs), with the venv's kernel."""
    nb = nbformat.read(EXPERIMENTS / name, as_version=4)
    nbformat.validate(nb)
    assert nb.metadata["kernelspec"]["name"] == "python3"
    code_cells = [c for c in nb.cells if c.cell_type == "code"]
    assert code_cells and any(c.cell_type == "markdown" for c in nb.cells)
    for cell in code_cells:
        assert cell.outputs == [], f"{name} has stored outputs in:\n{cell.source[:200]}"
        assert cell.execution_count is None


def test_kl_plots_has_a_tagged_smoke_parameter_cell():
    nb = nbformat.read(EXPERIMENTS / KL_PLOTS, as_version=4)
    tagged = [c for c in nb.cells if "parameters" in c.metadata.get("tags", [])]
    assert len(tagged) == 1
    assert 'PRESET = "smoke"' in tagged[0].source
    assert "CHECKPOINT = None" in tagged[0].source


# --------------------------------------------------------------------------- flowsim_tour


def test_flowsim_tour_runs_and_checks_the_posterior(executed):
    nb = _notebook(executed, TOUR)
    text = _stdout(nb)
    # The notebook compares the exact posterior with simulated rollouts and asserts agreement;
    # reaching these lines means those checks passed.
    assert "rollouts start the same way" in text
    assert "row s of P^Δτ equals exact_posterior" in text
    assert "schedule_jitter" in text
    assert "real tokens: 13 of 20" in text  # 10 tables + 3 objects, padded to 20
    # scene, timeline, orders, posterior bars, posterior on the map, transition matrix
    images = _images(nb)
    assert len(images) == 6
    assert all(image.startswith(PNG_MAGIC) for image in images)


# --------------------------------------------------------------------------- kl_plots


def test_kl_plots_shows_the_results_table(executed):
    nb = _notebook(executed, KL_PLOTS)
    tables = [o["data"]["text/markdown"] for o in _outputs(nb)
              if "text/markdown" in o.get("data", {})]
    assert len(tables) == 1
    for row in ("oracle", "oracle samples", "smoothed-q samples", "last-seen", "uniform",
                "MLP (mean)", "FlowMaps"):
        assert f"| {row} |" in tables[0]
    assert "TV @25" in tables[0]


def test_kl_plots_shows_the_figures(executed):
    images = _images(_notebook(executed, KL_PLOTS))
    assert len(images) == 3  # KL, samples, slot bars
    assert all(image.startswith(PNG_MAGIC) for image in images)


def test_kl_plots_trains_both_models_and_writes_the_report(executed, workdirs):
    _notebook(executed, KL_PLOTS)
    runs = workdirs[KL_PLOTS] / "runs"
    for kind in ("flowmaps", "mlp"):
        assert (runs / f"{kind}-smoke-notebook" / "checkpoints").is_dir()
    out = runs / "eval-smoke"
    results = json.loads((out / "results.json").read_text())
    assert list(results["rows"]) == ["oracle", "oracle samples", "smoothed-q samples",
                                     "last-seen", "uniform", "MLP (mean)", "FlowMaps"]
    assert results["protocol"]["num_queries"] == 32 * 3
    assert results["protocol"]["samples"] == [25]
    oracle = results["rows"]["oracle"]
    assert oracle["kl"]["overall"]["mean"] == pytest.approx(0.0, abs=1e-6)
    assert oracle["slots"]["25"]["tv"]["overall"]["mean"] == pytest.approx(0.0, abs=1e-6)
    for row in ("MLP (mean)", "FlowMaps"):
        kl = results["rows"][row]["kl"]
        assert kl["overall"]["count"] == 96
        assert set(kl["by_category"]) == {"fork", "bottle", "remote"}
    assert results["figures"] == ["kl.png", "samples.png", "slots.png"]
    for filename in ("results.md", *results["figures"]):
        assert (out / filename).stat().st_size > 0
    assert "| FlowMaps |" in (out / "results.md").read_text()


# --------------------------------------------------------------------------- search_demo


def test_search_demo_searches_with_every_prior(executed):
    nb = _notebook(executed, SEARCH)
    text = _stdout(nb)
    assert "episode: environment" in text and "dict form (FlowMaps)" in text
    assert "no prior and no policy expects to drive less" in text and "— found" in text
    tables = [o["data"]["text/markdown"] for o in _outputs(nb)
              if "text/markdown" in o.get("data", {})]
    assert len(tables) == 2
    for row in ("exact posterior", "FlowMaps", "MLP (mean)", "MLP (learned)",
                "uniform over the kind", "last-seen first"):
        assert all(f"| {row} |" in t for t in tables)
    assert "| nearest table first |" in tables[1]
    images = _images(nb)
    assert len(images) == 1 and images[0].startswith(PNG_MAGIC)


# --------------------------------------------------------------------------- habits


def test_habits_shows_each_habit_the_sharpening_posterior_and_the_model(executed):
    nb = _notebook(executed, HABITS)
    text = _stdout(nb)
    for habit in ("routine", "preferences", "dynamic"):
        assert f"{habit:>12}: environment" in text
    # the exact posterior given more history puts more mass on the truth, on average
    mean_p = {int(h): float(p) for h, p in
              re.findall(r"^H = (\d+): mean probability of the true place ([\d.]+)$", text, re.M)}
    assert list(mean_p) == [1, 2, 4, 8]
    assert mean_p[8] > mean_p[1]
    tv = re.search(r"^model pretrained:flowmaps-preferences \(step \d+\); total variation to "
                   r"exact H = 8: ([\d.]+)$", text, re.M)
    assert tv and 0.0 <= float(tv.group(1)) <= 1.0
    images = _images(nb)
    assert len(images) == 3  # habits over time, posterior bars by H, the model next to it
    assert all(image.startswith(PNG_MAGIC) for image in images)


# --------------------------------------------------------------------------- homes


def test_homes_shows_a_home_its_exact_posterior_and_the_model(executed):
    nb = _notebook(executed, HOMES)
    text = _stdout(nb)
    for regime in ("preferences", "balanced", "frequent", "routine"):
        assert f"{regime:>12}: object" in text
    rows = re.findall(r"^[* ]\s*\S.* \(\w+\) +([\d.]+) +([\d.]+) +([\d.]+) +([\d.]+)$", text, re.M)
    assert rows, text[:2000]
    values = np.asarray(rows, float)
    assert np.all((values >= 0) & (values <= 1))
    tv = re.search(r"^TV\(exact, FlowMaps\) per object: \[(.*)\]$", text, re.M)
    assert tv and all(0.0 <= float(v) <= 1.0 for v in tv.group(1).split())
    images = _images(nb)
    assert len(images) == 2  # the top view (3 panels) and the 3-D view
    assert all(image.startswith(PNG_MAGIC) for image in images)
