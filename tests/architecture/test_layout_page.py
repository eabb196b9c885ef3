"""The site's layout page (docs/contributing/layout.md) names every folder of the tree, and only ones that exist."""

from __future__ import annotations

import fnmatch
import re
import subprocess
import tomllib

from repo_paths import REPO_ROOT

#: The page whose first code block is the layout (it was the README's "## Layout" section).
LAYOUT_PAGE = REPO_ROOT / "docs" / "contributing" / "layout.md"

#: An entry line of the layout block: indentation (a few spaces; a continuation line's is the description column's),
#: then a folder name ending in '/'.
_ENTRY = re.compile(r"^(?P<indent> {0,12})(?P<name>[\w.-]+(?:/[\w.-]+)*)/(?: |$)")


def layout_entries(page: str) -> dict[str, str]:
    """Folder path (``core/track``) -> its text in the page's layout block (continuation lines included)."""
    found = re.search(r"^```\w*\n(.*?)^```$", page, flags=re.S | re.M)
    assert found is not None, "the layout page has no code block"
    block = found[1]
    entries: dict[str, str] = {}
    stack: list[tuple[int, str]] = []
    current = ""
    for line in block.splitlines():
        found = _ENTRY.match(line)
        if found is None:
            entries[current] += " " + line.strip()
            continue
        indent = len(found["indent"])
        while stack and stack[-1][0] >= indent:
            stack.pop()
        current = "/".join([*(name for _, name in stack), found["name"]])
        stack.append((indent, found["name"]))
        entries[current] = line[found.end():].strip()
    return entries


def tracked_top_level() -> set[str]:
    """The repository's top-level folders (git's tracked files; else the tree minus .gitignore's names)."""
    if (REPO_ROOT / ".git").exists():
        files = subprocess.run(["git", "ls-files"], cwd=REPO_ROOT, capture_output=True, text=True, check=True,
                               timeout=60).stdout.splitlines()
        return {f.split("/", 1)[0] for f in files if "/" in f}
    ignored = [line.strip().strip("/") for line in (REPO_ROOT / ".gitignore").read_text().splitlines() if line.strip()]
    return {p.name for p in REPO_ROOT.iterdir() if p.is_dir() and p.name != ".git"
            and not any(fnmatch.fnmatch(p.name, pattern) for pattern in ignored)}


def test_the_entry_parser_reads_nesting_and_continuations() -> None:
    indent = " " * 20
    page = f"# Layout\n\n```text\na/    one\n  b/  two\n{indent}x/ more\n    c/\nd/e/  three\n```\n\n```\nz/ no\n```\n"
    assert layout_entries(page) == {"a": "one", "a/b": "two x/ more", "a/b/c": "", "d/e": "three"}


def test_the_layout_names_every_folder_of_the_tree() -> None:
    entries = layout_entries(LAYOUT_PAGE.read_text(encoding="utf-8"))
    assert sorted(path for path in entries if not (REPO_ROOT / path).is_dir()) == []

    top = {path.split("/", 1)[0] for path in entries}
    assert sorted(tracked_top_level() - top) == []

    setup = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    unnamed = []
    for package in setup["packages"]:
        parts = package.split(".")[1:]
        folder = "/".join([setup["package-dir"][".".join(package.split(".")[:2])], *parts[1:]])
        parent = folder.rsplit("/", 1)[0]
        # a subpackage has an entry of its own or is named in its parent folder's text (drivers' vendors)
        if folder not in entries and not re.search(rf"\b{parts[-1]}\b", entries.get(parent, "")):
            unnamed.append(folder)
    assert unnamed == []

    examples = {f"examples/{p.name}" for p in (REPO_ROOT / "examples").iterdir() if p.is_dir()}
    assert sorted(examples - set(entries)) == []


def test_the_layout_names_every_benchmark_doc_and_ci_script() -> None:
    entries = layout_entries(LAYOUT_PAGE.read_text(encoding="utf-8"))
    expected = {
        "benchmarks": [p.stem for p in (REPO_ROOT / "benchmarks").glob("*.py")],
        "docs": [p.name for p in (REPO_ROOT / "docs").iterdir()],
        ".ci": [p.name for p in (REPO_ROOT / ".ci").iterdir() if p.is_file()],
    }
    unnamed = {folder: [name for name in names if not re.search(rf"(?<![\w.]){re.escape(name)}\b", entries[folder])]
               for folder, names in expected.items()}
    assert unnamed == {"benchmarks": [], "docs": [], ".ci": []}
