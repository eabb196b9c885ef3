"""pyproject.toml lists every package of the tree, so ``pip install .`` ships all of them."""

from __future__ import annotations

import tomllib

from repo_paths import REPO_ROOT


def test_every_source_package_is_listed_in_pyproject() -> None:
    setup = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(setup["packages"])
    found = set()
    for package, folder in setup["package-dir"].items():
        for init in (REPO_ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(REPO_ROOT / folder).parts
            found.add(".".join((package, *rel)))
    assert found - listed == set(), "packages missing from [tool.setuptools] packages"
    assert listed - found == set(), "listed packages with no __init__.py"
