"""Every code block of the site marked runnable runs, as written, and succeeds.

The marker is the line ``<!-- runnable -->`` right before a fenced ``bash`` or ``python`` block
(docs/contributing/docs.md, ADR 0048). The blocks of a page run in order in one new folder that
holds the test's environment as ``.venv`` and the checkout's ``configs/`` and ``examples/``, like
a checkout's root: a later block sees what an earlier one wrote.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
from repo_paths import REPO_ROOT

DOCS = REPO_ROOT / "docs"
MARKER = "<!-- runnable -->"
#: Blocks marked when this test was written; fewer found means the marker drifted (update it when adding blocks).
MIN_BLOCKS = 17
#: Seconds one block may take (the slowest, `cellcal track` on the built-in cell: about 10 s on a loaded 2-core box).
BLOCK_TIMEOUT_S = 120
#: What a page's folder holds from the checkout besides ``.venv``.
CHECKOUT = ("configs", "examples")


@dataclass(frozen=True)
class Block:
    """A marked block: its page (relative to docs/), its 1-based line, its language and its text."""

    page: str
    line: int
    lang: str
    body: str


def marked_blocks(text: str, page: str) -> list[Block]:
    """The blocks of a page that follow the marker, in order (a marker shown inside a code block is text).

    Raises:
        ValueError: If a marker is not followed by a fenced bash or python block.
    """
    lines = text.splitlines()
    blocks = []
    fence = ""  # the open fence's backticks, while inside a block
    for i, line in enumerate(lines):
        ticks = re.match(r"^(`{3,})", line)
        if fence:
            if ticks and line.strip() == fence:
                fence = ""
            continue
        if ticks:
            fence = ticks[1]
            continue
        if line.strip() != MARKER:
            continue
        opening = re.match(r"^```(\w*)", lines[i + 1]) if i + 1 < len(lines) else None
        if opening is None or opening[1] not in ("bash", "python"):
            raise ValueError(f"docs/{page}:{i + 1}: {MARKER} is not followed by a ```bash or ```python block")
        end = next((j for j in range(i + 2, len(lines)) if lines[j].strip() == "```"), None)
        if end is None:
            raise ValueError(f"docs/{page}:{i + 2}: the block after {MARKER} is not closed")
        blocks.append(Block(page, i + 2, opening[1], "\n".join(lines[i + 2:end]) + "\n"))
    return blocks


def pages() -> dict[str, list[Block]]:
    """Page -> its marked blocks, for every page of docs/ that has one."""
    found = {}
    for path in sorted(DOCS.rglob("*.md")):
        page = path.relative_to(DOCS).as_posix()
        blocks = marked_blocks(path.read_text(encoding="utf-8"), page)
        if blocks:
            found[page] = blocks
    return found


def test_the_marker_is_read_as_documented() -> None:
    text = ("intro\n<!-- runnable -->\n```bash\necho one\n```\n\n```bash\necho not marked\n```\n"
            "<!-- runnable -->\n```python title=\"x.py\"\nprint(2)\n```\n")
    assert marked_blocks(text, "p.md") == [Block("p.md", 3, "bash", "echo one\n"),
                                           Block("p.md", 11, "python", "print(2)\n")]
    with pytest.raises(ValueError, match=r"docs/p.md:1: .* not followed by"):
        marked_blocks("<!-- runnable -->\n```toml\n[cell]\n```\n", "p.md")
    with pytest.raises(ValueError, match="not followed by"):
        marked_blocks("<!-- runnable -->\n\ntext\n", "p.md")
    shown = "````markdown\n<!-- runnable -->\n```bash\necho shown\n```\n````\n"
    assert marked_blocks(shown, "p.md") == []


def test_the_site_marks_the_blocks_a_reader_copies() -> None:
    found = pages()
    assert sum(len(blocks) for blocks in found.values()) >= MIN_BLOCKS
    # the first five minutes: calibrate the sim and use its result from Python; a driver on an emulator
    assert [b.lang for b in found["getting-started.md"]] == ["bash", "bash", "python"]
    assert any("o3r_emulator" in b.body for b in found["backends.md"])
    assert any("sim_cell(" in b.body for b in found["testing.md"])  # the fakes without pytest
    assert {f"commands/{name}.md" for name in ("calibrate", "handeye", "track", "record")} <= set(found)


def _run(block: Block, cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    if block.lang == "bash":
        argv = ["bash", "-e", "-o", "pipefail", "-c", block.body]
    else:
        script = cwd / f"block-{block.line}.py"
        script.write_text(block.body, encoding="utf-8")
        argv = [str(Path(sys.prefix) / "bin" / "python"), str(script)]
    return subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=BLOCK_TIMEOUT_S,
                          stdin=subprocess.DEVNULL)


@pytest.mark.parametrize("page", sorted(pages()))
def test_the_marked_blocks_of_a_page_run(page: str, tmp_path: Path) -> None:
    (tmp_path / ".venv").symlink_to(Path(sys.prefix), target_is_directory=True)
    for name in CHECKOUT:
        (tmp_path / name).symlink_to(REPO_ROOT / name, target_is_directory=True)
    env = {**os.environ, "PATH": f"{Path(sys.prefix) / 'bin'}{os.pathsep}{os.environ.get('PATH', '')}",
           "MPLBACKEND": "Agg"}
    for block in pages()[page]:
        done = _run(block, tmp_path, env)
        assert done.returncode == 0, (f"docs/{block.page}:{block.line} ({block.lang}) exited {done.returncode}\n"
                                      f"--- stdout\n{done.stdout[-3000:]}\n--- stderr\n{done.stderr[-3000:]}")
