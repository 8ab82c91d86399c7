"""The layering of docs/layout.md holds: no import cycle between ocpar's modules, and no module
imports one of a layer above its own. Every import statement counts, at module level or inside
a function (or under ``if TYPE_CHECKING:``), read from the source with :mod:`ast`."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ROOT / "src"
LAYOUT = ROOT / "docs" / "layout.md"


def modules() -> dict[str, Path]:
    """Every module of ``src/ocpar`` by dotted name (a package by its own name)."""
    found = {}
    for path in sorted((SOURCE / "ocpar").rglob("*.py")):
        parts = list(path.relative_to(SOURCE).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        found[".".join(parts)] = path
    return found


def imported(module: str, path: Path, known: dict[str, Path]) -> set[str]:
    """The ocpar modules ``module`` imports (``from P import N``: the module P.N where that is
    one, else P; a package's own ``__init__`` run by importing one of its modules is not
    counted)."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    targets = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            names = [f"{base}.{alias.name}" for alias in node.names]
        else:
            continue
        for name in names:
            while name and name not in known:
                name = name.rpartition(".")[0]
            if name and name != module:
                targets.add(name)
    return targets


def import_graph() -> dict[str, set[str]]:
    known = modules()
    return {module: imported(module, path, known) for module, path in known.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for start in graph:
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def layers() -> list[tuple[str, list[str]]]:
    """docs/layout.md's table of layers, bottom first: (layer, the modules it names)."""
    text = LAYOUT.read_text(encoding="utf-8").split("## Layers", 1)[1]
    rows = [line.split("|")[1:3] for line in text.splitlines()
            if line.startswith("| ") and "`" in line]
    return [(name.strip(), re.findall(r"`(ocpar[\w.]*)`", names)) for name, names in rows][::-1]


def layer_of(module: str, table: list[tuple[str, list[str]]]) -> int | None:
    """The index (0 the bottom) of the layer whose most specific entry holds ``module``; the
    entry ``ocpar`` holds the package itself only."""
    best = None
    for level, (_, names) in enumerate(table):
        for name in names:
            holds = module == name or (name != "ocpar" and module.startswith(name + "."))
            if holds and (best is None or len(name) > best[1]):
                best = (level, len(name))
    return None if best is None else best[0]


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    return import_graph()


def test_the_graph_sees_function_level_and_relative_imports(graph):
    """The reader finds what it must: ``ocpar.config``'s parser imports the driver inside a
    function, ``ocpar.cli`` imports ``ocpar.results`` at the top."""
    assert "ocpar.driver" in graph["ocpar.config"]
    assert "ocpar.results" in graph["ocpar.cli"]
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycle(graph):
    assert cycles(graph) == []


def test_no_module_imports_a_layer_above_its_own(graph):
    table = layers()
    assert [name for name, _ in table] == ["foundation", "engine", "models", "transcription",
                                           "results", "schemes", "examples", "interfaces"]
    unplaced = sorted(m for m in graph if layer_of(m, table) is None)
    assert unplaced == [], f"modules in no layer of docs/layout.md: {unplaced}"
    upward = [f"{module} ({table[layer_of(module, table)][0]}) imports {target} "
              f"({table[layer_of(target, table)][0]})"
              for module, targets in sorted(graph.items()) for target in sorted(targets)
              if layer_of(target, table) > layer_of(module, table)]
    assert upward == []
