"""The import graph of ``src/flowmaps_jax``: no circles, and inference never reaches training.

Every module is parsed with ``ast``; an edge is any ``import`` of a ``flowmaps_jax`` module
anywhere in it: at the top, inside a function (a lazy import) or under ``TYPE_CHECKING``.
Importing ``a.b.c`` also runs ``a/__init__.py`` and ``a/b/__init__.py``: the reach of a module
follows those too, while circles are looked for along the written edges only (a package's
``__init__`` importing its own modules is not a circle).
"""

from __future__ import annotations

import ast
import functools
import pathlib
import subprocess
import sys

import pytest

SRC = pathlib.Path(__file__).resolve().parents[1] / "src"
PACKAGE = "flowmaps_jax"


def _name(path: pathlib.Path) -> str:
    parts = path.relative_to(SRC).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_name(path): path for path in sorted((SRC / PACKAGE).rglob("*.py"))}

# The modules that load, run and export a trained model: none may import flowmaps_jax.training,
# not even lazily, so that sampling a pretrained model needs neither optax nor the training loop.
INFERENCE = sorted(
    name for name in MODULES
    if name in (f"{PACKAGE}.{m}" for m in ("predictor", "export", "flow", "tokens", "boxes",
                                            "validation", "distributed", "tables",
                                            "atomic_files", "untrusted_files", "resources"))
    or name.startswith((f"{PACKAGE}.model", f"{PACKAGE}.flowsim", f"{PACKAGE}.store",
                        f"{PACKAGE}.worlds", f"{PACKAGE}.recorded")))
STORE = sorted(name for name in MODULES if name.startswith(f"{PACKAGE}.store"))
# What sits above the store: it may import none of them, lazily or not.
ABOVE_STORE = tuple(f"{PACKAGE}.{m}" for m in ("training", "predictor", "evaluation", "search",
                                              "export", "train", "evaluate"))


def _known(target: str) -> str | None:
    """The module an import of ``target`` loads (``a.b.name`` of a non-module: ``a.b``)."""
    while target and target not in MODULES:
        target = target.rpartition(".")[0]
    return target or None


def _targets(name: str, node: ast.AST) -> list[str]:
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    if not isinstance(node, ast.ImportFrom):
        return []
    base = node.module or ""
    if node.level:  # relative: from the module's package (a package is its own __init__)
        package = name if MODULES[name].name == "__init__.py" else name.rpartition(".")[0]
        for _ in range(node.level - 1):
            package = package.rpartition(".")[0]
        base = f"{package}.{base}" if base else package
    # "from pkg import mod" imports the module pkg.mod; "from mod import attr" the module mod
    return [f"{base}.{alias.name}" if f"{base}.{alias.name}" in MODULES else base
            for alias in node.names]


@functools.cache
def edges(name: str) -> frozenset[str]:
    """The flowmaps_jax modules ``name`` imports anywhere in its source."""
    tree = ast.parse(MODULES[name].read_text(), filename=str(MODULES[name]))
    found = set()
    for node in ast.walk(tree):
        for target in _targets(name, node):
            if target == PACKAGE or target.startswith(PACKAGE + "."):
                module = _known(target)
                if module is not None and module != name:
                    found.add(module)
    return frozenset(found)


def _parents(name: str) -> list[str]:
    parts = name.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts))]


def reach(name: str) -> dict[str, str]:
    """Every module importing ``name`` may load, each with the chain that loads it."""
    chains = {name: name}
    todo = [name]
    while todo:
        current = todo.pop()
        for nxt in [*edges(current), *_parents(current)]:
            if nxt not in chains:
                chains[nxt] = f"{chains[current]} -> {nxt}"
                todo.append(nxt)
    return chains


def _cycles(nodes=MODULES, out_of=edges) -> list[list[str]]:
    """The strongly connected components with more than one node (Tarjan); by default of the
    modules, along the written edges."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in out_of(v):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(nodes):
        if v not in index:
            visit(v)
    return out


def test_the_graph_is_read():
    assert len(MODULES) > 40
    assert f"{PACKAGE}.model.flowmaps_family" in edges(f"{PACKAGE}.predictor")
    # a lazy import is an edge too
    assert f"{PACKAGE}.predictor" in edges(f"{PACKAGE}.training.loop")
    assert {f"{PACKAGE}.store", f"{PACKAGE}.export"} <= set(INFERENCE)
    assert len(STORE) > 5
    # the store reads stored configs through their world
    assert f"{PACKAGE}.worlds" in edges(f"{PACKAGE}.store.model_spec")
    # no package by world: the homes' parts live in the layers (issue 49)
    assert not any(m == f"{PACKAGE}.homes" or m.startswith(f"{PACKAGE}.homes.") for m in MODULES)


def test_no_import_circles():
    assert _cycles() == []


PACKAGES = sorted(name for name, path in MODULES.items() if path.name == "__init__.py")


def _child(package: str, module: str) -> str | None:
    """The module or subpackage directly in ``package`` that holds ``module`` (None: outside)."""
    if not module.startswith(package + "."):
        return None
    return f"{package}.{module[len(package) + 1:].split('.')[0]}"


def package_graph(package: str) -> dict[str, set[str]]:
    """The import graph between the direct members of ``package`` (its modules and subpackages,
    each standing for everything inside it): an edge wherever a module of one imports a module
    of another. The package's own ``__init__`` is no member."""
    graph: dict[str, set[str]] = {}
    for name in MODULES:
        source = _child(package, name)
        if source is None:
            continue
        graph.setdefault(source, set())
        for target in edges(name):
            member = _child(package, target)
            if member is not None and member != source:
                graph[source].add(member)
    return graph


def test_the_package_graph_is_read():
    top = package_graph(PACKAGE)
    assert f"{PACKAGE}.navigation" in top[f"{PACKAGE}.evaluation"]
    assert f"{PACKAGE}.evaluation" in top[f"{PACKAGE}.search"]
    assert f"{PACKAGE}.training.config" in \
        package_graph(f"{PACKAGE}.training")[f"{PACKAGE}.training.loop"]
    # the circle evaluation <-> search (search.navigation) would be found
    top[f"{PACKAGE}.navigation"].add(f"{PACKAGE}.search")
    assert [f"{PACKAGE}.evaluation", f"{PACKAGE}.navigation", f"{PACKAGE}.search"] in \
        _cycles(top, lambda member: sorted(top[member]))
    assert len(PACKAGES) > 10


@pytest.mark.parametrize("package", PACKAGES)
def test_no_package_imports_a_package_that_imports_it(package):
    """Between the members of every package (the top level: ``evaluation/``, ``search/``,
    ``predictor``, ...; and inside each subpackage), no circle of any length: a package's modules
    never import, lazily or not, a package that imports it."""
    graph = package_graph(package)
    assert _cycles(graph, lambda member: sorted(graph[member])) == []


LAYERS = (
    ("validation", "atomic_files", "untrusted_files", "resources", "boxes", "distributed"),
    ("tokens", "flow", "tables"),
    ("flowsim", "model", "recorded"),
    ("worlds",),
    ("store",),
    ("predictor", "export"),
    ("navigation",),
    ("evaluation", "search"),
    ("training",),
    ("train", "evaluate", "data"),
)
"""The layers, bottom up, each a list of module-name prefixes under the package (the longest
prefix decides). A world is a plug-in below the layers that use it: its simulator in
``flowsim`` (the 2-D maps, ``flowsim.homes``), its model family in ``model``, its data hooks in
``worlds``."""


def _layer(name: str) -> int:
    rest = name[len(PACKAGE) + 1:]
    best = max(((len(p), i) for i, layer in enumerate(LAYERS) for p in layer
                if rest == p or rest.startswith(p + ".")), default=None)
    assert best is not None, f"{name} is in no layer of LAYERS"
    return best[1]


def test_no_module_imports_a_higher_layer():
    """Every import, lazy ones included, points to the module's own layer or one below."""
    upward = [f"{name} (layer {_layer(name)}) -> {target} (layer {_layer(target)})"
              for name in sorted(MODULES) if name != PACKAGE
              for target in sorted(edges(name)) if target != PACKAGE
              and _layer(target) > _layer(name)]
    assert upward == []


@pytest.mark.parametrize("module", INFERENCE)
def test_inference_never_imports_training(module):
    """Lazy imports included (every import in the source is an edge)."""
    chains = reach(module)
    training = sorted(m for m in chains if m.startswith(f"{PACKAGE}.training"))
    assert not training, f"{module} imports training: {chains[training[0]]}"


@pytest.mark.parametrize("module", STORE)
def test_the_store_imports_nothing_above_it(module):
    chains = reach(module)
    above = sorted(m for m in chains if m.startswith(ABOVE_STORE))
    assert not above, f"{module} reaches up: {chains[above[0]]}"


def test_only_the_store_imports_orbax():
    importers = []
    for name, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            if any(n == "orbax" or n.startswith("orbax.") for n in names):
                importers.append(name)
    assert importers and all(m.startswith(f"{PACKAGE}.store.") for m in importers), importers


def test_importing_the_predictor_loads_neither_optax_nor_training():
    code = ("import sys, flowmaps_jax.predictor, flowmaps_jax.export, flowmaps_jax.store.rundir, "
            "flowmaps_jax.store.checkpoint_store; print(sorted(m for m in sys.modules if "
            "m == 'optax' or "
            "m.startswith(('optax.', 'flowmaps_jax.training'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_every_family_is_registered_once_with_its_loss_in_its_own_module():
    from flowmaps_jax.model import MODEL_FAMILIES
    from flowmaps_jax.training import objectives

    for name, family in MODEL_FAMILIES.items():
        assert family.name == name
        home = [m for m in list(sys.modules.values())
                if getattr(m, "FAMILY", None) is family and m.__name__.startswith(PACKAGE)]
        assert [m.__name__ for m in home] == [family.loss.__module__], name
        assert family.loss.__module__.startswith(f"{PACKAGE}.model."), name
    assert not hasattr(objectives, "LOSSES")  # one registry: the families carry their losses
