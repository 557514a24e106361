"""The installed ``servobench`` package has no import cycle, and the maths imports no transport.

The import graph is built from the source alone (``ast``, nothing is executed):
every ``import`` and ``from ... import`` of a ``servobench`` module is an edge,
at module level or inside a function alike (an import inside a function only
defers a cycle, it does not remove it). Imports under ``if TYPE_CHECKING:``
are not edges: they never run. Importing ``a.b.c`` also runs the packages
``a`` and ``a.b``; those count as edges too, except the importer's own
enclosing packages (which are already being imported when it runs).
Modules are found the way ``import`` finds them (``sys.meta_path``), so the
test sees the installed layout, editable or not.
"""

from __future__ import annotations

import ast
import importlib.util
import pkgutil
import sys
from functools import cache
from importlib.machinery import ModuleSpec
from pathlib import Path

ROOT = "servobench"


@cache
def _spec(name: str) -> ModuleSpec | None:
    """The spec ``import name`` would use, without running any package ``__init__``."""
    parent, _, _ = name.rpartition(".")
    path = None
    if parent:
        parent_spec = _spec(parent)
        if parent_spec is None or parent_spec.submodule_search_locations is None:
            return None
        path = list(parent_spec.submodule_search_locations)
    elif name in sys.modules:
        return sys.modules[name].__spec__
    for finder in sys.meta_path:
        find = getattr(finder, "find_spec", None)
        if find is None:
            continue
        spec = find(name, path)
        if spec is not None:
            return spec
    return None


def _is_module(name: str) -> bool:
    return name.split(".")[0] == ROOT and _spec(name) is not None


def _under_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imported_names(tree: ast.Module, module: str, is_package: bool) -> set[str]:
    """Every ``servobench`` module ``module`` imports (anywhere but under TYPE_CHECKING)."""
    package = module if is_package else module.rpartition(".")[0]
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _under_type_checking(node):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{base}.{node.module}" if node.module else base
            else:
                base = node.module or ""
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                found.add(sub if alias.name != "*" and _is_module(sub) else base)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return {n for n in found if n.split(".")[0] == ROOT}


def _edges(module: str, imported: set[str]) -> set[str]:
    """Imported modules and the packages importing them runs, bar the importer's own."""
    own = {module.rsplit(".", i)[0] for i in range(module.count(".") + 1)}
    out = set()
    for name in imported:
        parts = name.split(".")
        for i in range(1, len(parts) + 1):
            target = ".".join(parts[:i])
            if target not in own and _is_module(target):
                out.add(target)
    return out


@cache
def import_graph() -> dict[str, frozenset[str]]:
    """``module -> modules it imports`` over every module of the installed package."""
    graph: dict[str, frozenset[str]] = {}
    todo = [ROOT]
    while todo:
        name = todo.pop()
        if name in graph:
            continue
        spec = _spec(name)
        assert spec is not None and spec.origin, f"cannot locate {name}"
        is_package = spec.submodule_search_locations is not None
        if is_package:  # every module of the package, imported or not
            todo.extend(
                f"{name}.{m.name}"
                for m in pkgutil.iter_modules(list(spec.submodule_search_locations))
            )
        tree = ast.parse(Path(spec.origin).read_text(encoding="utf-8"), spec.origin)
        edges = _edges(name, _imported_names(tree, name, is_package))
        graph[name] = frozenset(edges)
        todo.extend(edges)
    return graph


def find_cycles(graph: dict[str, frozenset[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                connect(w)
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
            if len(component) > 1 or v in graph.get(v, ()):
                components.append(sorted(component))

    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 10_000))
    try:
        for v in sorted(graph):
            if v not in index:
                connect(v)
    finally:
        sys.setrecursionlimit(limit)
    return components


def _one_cycle(graph: dict[str, frozenset[str]], component: list[str]) -> list[str]:
    """A shortest cycle through the component's first module, for the message."""
    members = set(component)
    start = component[0]
    paths = {start: [start]}
    frontier = [start]
    while frontier:
        nxt = []
        for v in frontier:
            for w in sorted(graph[v] & members):
                if w == start:
                    return paths[v] + [start]
                if w not in paths:
                    paths[w] = paths[v] + [w]
                    nxt.append(w)
        frontier = nxt
    return component


def _reachable(graph: dict[str, frozenset[str]], start: str) -> dict[str, str]:
    """Modules reachable from ``start``, each with the module that first imports it."""
    seen = {start: ""}
    todo = [start]
    while todo:
        v = todo.pop()
        for w in sorted(graph.get(v, ())):
            if w not in seen:
                seen[w] = v
                todo.append(w)
    return seen


# ------------------------------------------------------------------ the builder itself
def _graph_of(files: dict[str, str], tmp_path: Path, monkeypatch) -> dict[str, frozenset[str]]:
    """The graph of a throw-away ``servobench`` package written from ``files``."""
    for rel, text in files.items():
        path = tmp_path / ROOT / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    monkeypatch.setattr(sys, "path", [str(tmp_path)])
    monkeypatch.setattr(sys, "meta_path", [importlib.machinery.PathFinder])
    monkeypatch.delitem(sys.modules, ROOT, raising=False)
    _spec.cache_clear()
    import_graph.cache_clear()
    try:
        return import_graph()
    finally:
        _spec.cache_clear()
        import_graph.cache_clear()


def test_builder_sees_cycles_through_functions_and_packages(tmp_path, monkeypatch):
    graph = _graph_of(
        {
            "__init__.py": "",
            "a.py": "from servobench.fx.b import thing\n",
            "fx/__init__.py": "def make():\n    from servobench import c\n    return c\n",
            "fx/b.py": "from . import sibling\nthing = 1\n",
            "fx/sibling.py": "",
            "c.py": (
                "from typing import TYPE_CHECKING\n"
                "if TYPE_CHECKING:\n    from servobench import d\n"
                "def f():\n    from .a import thing\n"
            ),
            "d.py": "import servobench.c\n",
        },
        tmp_path,
        monkeypatch,
    )
    assert graph["servobench.a"] == {"servobench.fx", "servobench.fx.b"}
    assert graph["servobench.fx.b"] == {"servobench.fx.sibling"}  # not its own package
    assert graph["servobench.c"] == {"servobench.a"}  # TYPE_CHECKING is no edge
    assert find_cycles(graph) == [["servobench.a", "servobench.c", "servobench.fx"]]
    assert _one_cycle(graph, find_cycles(graph)[0]) == [
        "servobench.a",
        "servobench.fx",
        "servobench.c",
        "servobench.a",
    ]


def test_builder_finds_no_cycle_in_a_tree(tmp_path, monkeypatch):
    graph = _graph_of(
        {"__init__.py": "", "a.py": "from servobench import b\n", "b.py": "import math\n"},
        tmp_path,
        monkeypatch,
    )
    assert set(graph) == {"servobench", "servobench.a", "servobench.b"}
    assert find_cycles(graph) == []


# ------------------------------------------------------------------ the package
def test_every_package_is_in_the_graph():
    graph = import_graph()
    for name in (
        "servobench.bench.identify.auto",
        "servobench.bench.diagnose.refit",
        "servobench.drivers.base",
        "servobench.sim_backend.physics.plant",
        "servobench.sim_backend.physics.effects.stribeck",
        "servobench.udev",
    ):
        assert name in graph


def test_no_import_cycle():
    graph = import_graph()
    cycles = find_cycles(graph)
    assert not cycles, "import cycles:\n" + "\n".join(
        f"{' -> '.join(_one_cycle(graph, c))} (tangled: {', '.join(c)})" for c in cycles
    )


def test_identification_imports_no_transport():
    """bench/identify and bench/diagnose reach nothing of servobench.drivers, even indirectly."""
    graph = import_graph()
    for package in ("servobench.bench.identify", "servobench.bench.diagnose"):
        for module in [m for m in graph if m == package or m.startswith(package + ".")]:
            seen = _reachable(graph, module)
            bad = sorted(m for m in seen if m.startswith("servobench.drivers"))
            if bad:
                chain = [bad[0]]
                while seen[chain[-1]]:
                    chain.append(seen[chain[-1]])
                raise AssertionError(f"{module} imports a transport: {' <- '.join(chain)}")
