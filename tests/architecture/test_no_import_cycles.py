"""No two modules of one package import each other, function-level imports included.

import-linter's layers see the packages, not the modules inside one; a circle between two
sibling modules (one of them importing the other inside a function to get past the load
order) keeps coming back unless something looks. This test reads every module of the
source packages with ``ast``: each import anywhere in a module counts, except those under
``if TYPE_CHECKING:`` (type-only, never run). A circle is broken by moving the shared
piece into a module both import, or by inverting one direction (a protocol, a callback).
"""

from __future__ import annotations

import ast
from pathlib import Path

from repo_paths import REPO_ROOT

#: The source packages and their folders (pyproject.toml's package-dir).
PACKAGES = {"cellcal.core": "core", "cellcal.devices": "devices", "cellcal.drivers": "drivers",
            "cellcal.sims": "sims", "cellcal.testing": "testing"}


def _modules() -> dict[str, Path]:
    out: dict[str, Path] = {}
    for package, folder in PACKAGES.items():
        root = REPO_ROOT / folder
        for path in root.rglob("*.py"):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join([package, *parts])] = path
    return out


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imports(tree: ast.AST, module: str, is_package: bool) -> set[str]:
    """Every name this module imports at run time (module and ``module.name`` alike)."""
    base = module.split(".") if is_package else module.split(".")[:-1]
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            parts = base[:len(base) - node.level + 1] if node.level else []
            source = ".".join(parts + ([node.module] if node.module else []))
            found.add(source)
            found.update(f"{source}.{alias.name}" for alias in node.names)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        graph[name] = {m for m in _imports(tree, name, path.name == "__init__.py") if m in modules and m != name}
    return graph


def _parent(module: str) -> str:
    return module.rpartition(".")[0]


def test_the_walk_finds_the_modules_and_their_imports() -> None:
    graph = _graph()
    assert "cellcal.core.study.pool" in graph["cellcal.core.study.trials"]
    assert "cellcal.devices.recording.wrappers" in graph["cellcal.devices.recording.writer"]
    assert "cellcal.sims.o3r.wire" in graph["cellcal.sims.o3r.encoder"]


def test_no_two_sibling_modules_import_each_other() -> None:
    graph = _graph()
    circles = sorted({tuple(sorted((a, b))) for a, targets in graph.items() for b in targets
                      if a in graph.get(b, set()) and _parent(a) == _parent(b)})
    assert not circles, "modules of one package that import each other: " + "; ".join(
        f"{a} <-> {b}" for a, b in circles)
