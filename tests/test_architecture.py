"""The package's import graph (docs/ARCHITECTURE.md, "Floors"): no import cycles and no library
module importing the command line (``jaxmocap.cli``, ``jaxmocap.commands``).

The graph is read from the source with :mod:`ast` (every ``import`` statement, module-level or
inside a function: a lazy import is still a dependency), except imports under
``if TYPE_CHECKING:``, which never run. Cycles are the strongly connected components of more
than one module (Tarjan's algorithm, written out here so that the check depends on nothing).
"""

from __future__ import annotations

import ast
from pathlib import Path

import jaxmocap

PACKAGE = Path(jaxmocap.__file__).resolve().parent
LONG_MODULE_LINES = 600  # longer library modules say why at their top ("Why one file")


def _modules() -> dict[str, Path]:
    mods = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        mods[".".join(parts)] = path
    return mods


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


def _imports(tree: ast.AST):
    """Every Import/ImportFrom node, skipping ``if TYPE_CHECKING:`` bodies."""
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.If) and _is_type_checking(node):
            stack.extend(node.orelse)
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        stack.extend(ast.iter_child_nodes(node))


def import_graph() -> dict[str, set[str]]:
    """module -> the ``jaxmocap`` modules it imports (``from a import b`` counts ``a.b`` when
    that is a module, else ``a``)."""
    mods = _modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for mod, path in mods.items():
        is_pkg = path.name == "__init__.py"
        for node in _imports(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                if node.level:
                    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
                    base = base[: len(base) - (node.level - 1)]
                    src = ".".join(base + ([node.module] if node.module else []))
                else:
                    src = node.module or ""
                targets = [f"{src}.{a.name}" if f"{src}.{a.name}" in mods else src
                           for a in node.names]
            for t in targets:
                while t and t not in mods and "." in t:
                    t = t.rsplit(".", 1)[0]
                if t in mods and t != mod:
                    graph[mod].add(t)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            for w in children:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


def test_cycle_finder_on_known_graphs():
    g = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert cycles(g) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []
    assert sorted(cycles({"a": {"b"}, "b": {"a"}, "c": {"d"}, "d": {"c"}})) == [["a", "b"],
                                                                               ["c", "d"]]


def test_graph_reads_relative_lazy_and_type_checking_imports(tmp_path):
    tree = ast.parse("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import os\n"
                     "def f():\n    import json\n")
    names = [a.name for n in _imports(tree) for a in n.names]
    assert "json" in names and "os" not in names and "TYPE_CHECKING" in names
    graph = import_graph()
    assert "jaxmocap.camera" in graph["jaxmocap.trackers.stereo_pf.params"]
    assert "jaxmocap.trackers.shirt.frame" in graph["jaxmocap.trackers.shirt.sequence"]


def test_no_import_cycles():
    assert cycles(import_graph()) == []


def test_libraries_never_import_the_command_line():
    bad = sorted(
        f"{m} -> {t}"
        for m, deps in import_graph().items()
        if not m.startswith(("jaxmocap.cli", "jaxmocap.commands"))
        for t in deps
        if t.startswith(("jaxmocap.cli", "jaxmocap.commands"))
    )
    assert bad == []


def test_long_library_modules_say_why():
    """No library file over ~600 lines without its reason written at its top."""
    long = []
    for mod, path in _modules().items():
        text = path.read_text()
        n = text.count("\n")
        if n > LONG_MODULE_LINES and "Why one file" not in text[:6000]:
            long.append(f"{mod} ({n} lines)")
    assert long == []


def test_the_learned_observation_is_a_room_of_its_own():
    """``jaxmocap.observe`` (issue 49 item 7): the trackers import it, never the reverse."""
    graph = import_graph()
    layer = [m for m in graph if m == "jaxmocap.observe" or m.startswith("jaxmocap.observe.")]
    assert layer
    for m in layer:
        bad = [t for t in graph[m] if t.startswith(("jaxmocap.trackers", "jaxmocap.experiment",
                                                    "jaxmocap.commands", "jaxmocap.cli"))]
        assert not bad, (m, bad)
    assert any(t.startswith("jaxmocap.observe") for t in graph["jaxmocap.trackers.shirt.params"])
