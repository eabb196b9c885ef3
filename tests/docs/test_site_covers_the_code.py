"""The site documents every command and every configuration table, each once, from the code (ADR 0048).

The lists come from the code: the subcommands from ``cellcal``'s argparse parser, the tables from
the configuration's classes and the registered backends (docs/hooks/cellcal_docs.py, which also
renders them when the site is built). The markers are found in the pages' Markdown.
"""

from __future__ import annotations

import importlib.util
import re
import sys
from collections import Counter
from types import ModuleType

import pytest
from repo_paths import REPO_ROOT

DOCS = REPO_ROOT / "docs"


def _load(name: str) -> ModuleType:
    """A module of docs/hooks/ (not a package: mkdocs and griffe load them by path)."""
    spec = importlib.util.spec_from_file_location(name, DOCS / "hooks" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault(name, module)
    spec.loader.exec_module(module)
    return module


hook = _load("cellcal_docs")
griffe_rst = _load("griffe_rst")


def markers(kind: str) -> Counter[str]:
    """How often each ``<!-- kind: X -->`` marker appears across the site's pages."""
    found: Counter[str] = Counter()
    for path in DOCS.rglob("*.md"):
        found.update(re.findall(rf"^<!-- {kind}: (\S+) -->$", path.read_text(encoding="utf-8"), flags=re.M))
    return found


def test_every_subcommand_has_its_page_with_its_options_once() -> None:
    from cellcal.core.cli.app import SUBCOMMANDS

    names = list(hook.subcommands())
    assert names == list(SUBCOMMANDS)  # every subcommand module registered a parser
    assert markers("cli-options") == Counter(names)
    for name in names:
        assert f"<!-- cli-options: {name} -->" in (DOCS / "commands" / f"{name}.md").read_text(encoding="utf-8")
    pages = {p.stem for p in (DOCS / "commands").glob("*.md")} - {"index"}
    assert pages == set(names)
    nav = (REPO_ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    assert [n for n in names if f"commands/{n}.md" not in nav] == []


def test_every_configuration_table_is_documented_once() -> None:
    from cellcal.core.calibration.config import TOP_LEVEL_TABLES
    from cellcal.devices.registry import default_registry

    tables = hook.config_tables()
    # the walk reaches every table the loader knows and every registered backend's table
    assert {t.split(".")[0].split(":")[0] for t in tables} == set(TOP_LEVEL_TABLES)
    assert {f"{e.kind}:{e.name}" for e in default_registry().entries()} <= set(tables)
    assert {"plan.poses", "sim.artefacts", "sim.events", "camera.model"} <= set(tables)
    assert markers("config-table") == Counter(list(tables))


def test_a_table_is_rendered_with_every_key_its_default_and_range() -> None:
    from cellcal.core.calibration.config import SafetySection
    from cellcal.devices.config import schema_of

    text = hook.config_table("safety")
    assert text.startswith("### `[safety]` {#config-safety}")
    rows = {line.split("|")[1].strip().strip("`"): line for line in text.splitlines() if line.startswith("| `")}
    assert set(rows) == set(schema_of(SafetySection))
    assert "| `0.25` | ≥ 0.0001, ≤ 3 |" in rows["max_speed_m_s"]
    assert "| 3 × number | `[-0.7, -0.7, 0.0]` |" in rows["workspace_min_m"]
    assert "| unset |" in rows["arrival_tolerance_m"]
    backend = hook.config_table("camera:o3r")
    assert '| `backend` | string | **required** | `"o3r"` |' in backend
    assert "| `xmlrpc_port` | integer | `80` | ≥ 1, ≤ 65535 | XML-RPC TCP port |" in backend
    with pytest.raises(Exception, match="no table 'nonsense'"):
        hook.config_table("nonsense")


def test_a_command_is_rendered_with_every_argument() -> None:
    text = hook.cli_options("paper")
    assert "cellcal paper [-h] [--true-angle DEG]" in text
    assert "| `TABLE.csv` | measurement table |" in text
    assert "| `--true-angle DEG` | true angle between plane and optical axis, degrees (default 80) |" in text
    with pytest.raises(Exception, match="no subcommand 'nonsense'"):
        hook.cli_options("nonsense")


def test_the_decision_index_lists_every_record() -> None:
    index = hook.adr_index(DOCS, DOCS / "adr")
    records = sorted(p.name for p in (DOCS / "adr").glob("[0-9][0-9][0-9][0-9]-*.md"))
    assert re.findall(r"\]\(([^)]+)\)", index) == records
    assert "- [ADR 0001: " in index


def test_fence_words_of_the_doc_tests_become_titles() -> None:
    text = "```python file=src/a.py\nx = 1\n```\n```console run\n$ ls\n```\n```bash title=\"t\"\n```\n"
    assert hook.fence_titles(text) == "```python title=\"src/a.py\"\nx = 1\n```\n```console\n$ ls\n```\n" \
        "```bash title=\"t\"\n```\n"


def test_sphinx_roles_in_docstrings_read_as_code() -> None:
    text = ("See :class:`~cellcal.devices.Frame`, :func:`cellcal.core.fit_full_frame`, :meth:`.capture` and "
            ":class:`x <a.B>`.")
    assert griffe_rst.plain_roles(text) == "See `Frame`, `cellcal.core.fit_full_frame`, `capture` and `x`."


def test_doctests_in_docstrings_are_fenced() -> None:
    text = "Example:\n    >>> x = 1\n    >>> x\n    1\n\nAfter."
    fenced = "Example:\n    ```pycon\n    >>> x = 1\n    >>> x\n    1\n    ```\n\nAfter."
    assert griffe_rst.fenced_doctests(text) == fenced
