"""The README fits the first five minutes, and its two commands are the ones CI runs (ADR 0048)."""

from __future__ import annotations

import re

from repo_paths import REPO_ROOT

README = (REPO_ROOT / "README.md").read_text(encoding="utf-8")
CI_RUN = (REPO_ROOT / ".ci" / "run").read_text(encoding="utf-8")
GETTING_STARTED = (REPO_ROOT / "docs" / "getting-started.md").read_text(encoding="utf-8")


def bash_blocks(text: str) -> list[str]:
    """The bodies of the fenced ``bash`` blocks of a Markdown text, stripped."""
    return [body.strip() for body in re.findall(r"^```bash\n(.*?)^```$", text, flags=re.S | re.M)]


def test_the_readme_is_at_most_200_lines() -> None:
    assert len(README.splitlines()) <= 200


def test_the_readme_s_two_commands_are_the_ones_ci_runs_and_the_site_shows() -> None:
    install, tests = bash_blocks(README)[:2]
    assert install.startswith("python3 -m venv .venv && ") and install.endswith("cellcal calibrate --out cellcal-out")
    assert tests.startswith("python3 -m venv .venv && ") and "-m pytest" in tests
    ci_lines = {line.strip() for line in CI_RUN.splitlines()}
    assert install in ci_lines and tests in ci_lines
    assert install in bash_blocks(GETTING_STARTED) and tests in bash_blocks(GETTING_STARTED)


def test_the_readme_s_command_table_names_every_command() -> None:
    from cellcal.core.cli.app import SUBCOMMANDS

    table = re.findall(r"^\| `cellcal (\w+)", README, flags=re.M)
    assert table == list(SUBCOMMANDS)


def test_the_readme_says_where_the_docs_are_and_its_links_exist() -> None:
    assert "mkdocs serve" in README and "mkdocs build --strict" in README
    links = re.findall(r"\]\((docs/[^)#]+)\)", README)
    assert len(links) >= 5
    assert [link for link in links if not (REPO_ROOT / link).is_file()] == []
