"""No import circle of any length among the source modules, function-level and type-only imports included.

import-linter's layers see the packages, not the modules inside one; a circle between
modules (one of them importing another inside a function, or under ``if TYPE_CHECKING:``,
to get past the load order) keeps coming back unless something looks. This test reads every
module of the source packages with ``ast`` and counts each import statement anywhere in it:
top level, inside a function, under ``TYPE_CHECKING``. ``from P import n`` is an import of
the module ``P.n`` when there is one, else of ``P`` (the name is defined or re-exported
there). The parent packages Python loads before a module are not edges of their own: a
package's ``__init__`` importing its own modules is how a package exposes them. The circles
are the strongly connected components of that graph (Tarjan), of any length. A circle is
broken by moving the shared piece into a module both import, or by inverting one direction
(a protocol, a callback), not by hiding an import (ADR 0047).
"""

from __future__ import annotations

import ast
from collections.abc import Mapping
from pathlib import Path

from repo_paths import REPO_ROOT

#: The source packages and their folders (pyproject.toml's package-dir).
PACKAGES = {"cellcal.core": "core", "cellcal.devices": "devices", "cellcal.drivers": "drivers",
            "cellcal.sims": "sims", "cellcal.testing": "testing"}


def _modules(roots: Mapping[str, Path]) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` file under each package's folder."""
    out: dict[str, Path] = {}
    for package, root in roots.items():
        for path in root.rglob("*.py"):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join([package, *parts])] = path
    return out


def _imports(tree: ast.AST, module: str, is_package: bool, modules: Mapping[str, Path]) -> set[str]:
    """Every module this one imports, wherever the import statement stands."""
    base = module.split(".") if is_package else module.split(".")[:-1]
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            parts = base[:len(base) - node.level + 1] if node.level else []
            source = ".".join(parts + ([node.module] if node.module else []))
            for alias in node.names:
                submodule = f"{source}.{alias.name}"
                found.add(submodule if submodule in modules else source)
    return found


def import_graph(roots: Mapping[str, Path]) -> dict[str, set[str]]:
    """Module -> the modules among ``roots``' it imports (itself left out)."""
    modules = _modules(roots)
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        imported = _imports(tree, name, path.name == "__init__.py", modules)
        graph[name] = {m for m in imported if m in modules and m != name}
    return graph


def circles(graph: Mapping[str, set[str]]) -> list[list[str]]:
    """The import circles: strongly connected components of more than one module, each sorted.

    Tarjan's algorithm, iterative (no recursion limit on a deep chain of imports).
    """
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, targets = work[-1]
            target = next(targets, None)
            if target is not None:
                if target not in index:
                    index[target] = low[target] = len(index)
                    stack.append(target)
                    on_stack.add(target)
                    work.append((target, iter(sorted(graph.get(target, ())))))
                elif target in on_stack:
                    low[node] = min(low[node], index[target])
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
    return sorted(found)


def _loop(graph: Mapping[str, set[str]], members: list[str]) -> list[str]:
    """One closed walk through a circle's members, from its first: ``[a, b, c, a]``."""
    inside = set(members)
    start = members[0]
    paths = {start: [start]}
    frontier = [start]
    while frontier:  # breadth first: the shortest way from start back to it
        nxt = []
        for node in frontier:
            for target in sorted(graph[node] & inside):
                if target == start:
                    return [*paths[node], start]
                if target not in paths:
                    paths[target] = [*paths[node], target]
                    nxt.append(target)
        frontier = nxt
    raise AssertionError(f"{members} is not a circle")


def describe(graph: Mapping[str, set[str]], found: list[list[str]]) -> str:
    """The failure message: each circle's members, and one way round it."""
    return "import circles: " + "; ".join(
        f"{len(c)} modules {', '.join(c)} (e.g. {' -> '.join(_loop(graph, c))})" for c in found)


def _source_roots() -> dict[str, Path]:
    return {package: REPO_ROOT / folder for package, folder in PACKAGES.items()}


def test_the_walk_finds_the_modules_and_their_imports() -> None:
    graph = import_graph(_source_roots())
    assert "cellcal.core.study.pool" in graph["cellcal.core.study.trials"]
    assert "cellcal.devices.recording.wrappers" in graph["cellcal.devices.recording.writer"]
    assert "cellcal.sims.o3r.wire" in graph["cellcal.sims.o3r.encoder"]
    # `from cellcal.core.report import figures` inside a function imports the module figures, not the package
    assert "cellcal.core.report.figures" in graph["cellcal.core.report.render"]
    assert "cellcal.core.report" not in graph["cellcal.core.report.render"]


def test_a_planted_circle_of_three_is_found_with_its_members(tmp_path: Path) -> None:
    """a -> b at the top, b -> c inside a function, c -> a only for the type checker; d, e hang off it."""
    pkg = tmp_path / "planted"
    pkg.mkdir()
    (pkg / "__init__.py").write_text('"""Planted."""\nfrom .a import A\n')
    (pkg / "a.py").write_text("from planted.b import B\nA = B\n")
    (pkg / "b.py").write_text("def make():\n    from . import c\n    return c.C\n\nB = 1\n")
    (pkg / "c.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .a import A\nC = 2\n")
    (pkg / "d.py").write_text("import planted.a\nfrom planted import e\n")
    (pkg / "e.py").write_text("E = 3\n")
    graph = import_graph({"planted": pkg})
    assert graph["planted.b"] == {"planted.c"} and graph["planted.c"] == {"planted.a"}
    found = circles(graph)
    assert found == [["planted.a", "planted.b", "planted.c"]]
    message = describe(graph, found)
    assert message == ("import circles: 3 modules planted.a, planted.b, planted.c "
                       "(e.g. planted.a -> planted.b -> planted.c -> planted.a)")


def test_two_circles_through_one_module_are_one_component() -> None:
    graph = {"m.x": {"m.y"}, "m.y": {"m.x", "m.z"}, "m.z": {"m.y"}, "m.w": {"m.x"}}
    assert circles(graph) == [["m.x", "m.y", "m.z"]]
    assert circles({"m.x": {"m.y"}, "m.y": {"m.z"}, "m.z": set()}) == []


def test_the_source_tree_has_no_import_circle() -> None:
    graph = import_graph(_source_roots())
    found = circles(graph)
    assert not found, describe(graph, found)
