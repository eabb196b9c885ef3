"""``[cell] strict``: a cell whose poses disagree in the base frame fails like ``--strict``.

The hand-eye cell's simulated camera sits ~1° / ~6 mm off the configured ``[mount]``, so
its poses, seen from two sides, disagree: the verdict is ``inconsistent``.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from repo_paths import REPO_ROOT

from cellcal.core.cli import main

CELL = (REPO_ROOT / "configs" / "sim_handeye.toml").read_text()


def _cell(tmp_path: Path, strict: bool) -> str:
    text = CELL.replace('name = "handeye-sim"\n', f'name = "handeye-sim"\nstrict = {str(strict).lower()}\n', 1)
    assert text != CELL
    path = tmp_path / "cell.toml"
    path.write_text(text)
    return str(path)


def test_strict_cell_fails_a_disagreeing_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["calibrate", "--quiet", "--config", _cell(tmp_path, True), "--out", str(tmp_path / "out")]) == 1
    captured = capsys.readouterr()
    assert "cross-pose verdict inconsistent" in captured.out
    assert ("cellcal: [cell] strict: the poses' planes disagree (cross-pose verdict inconsistent: normal spread"
            in captured.err)
    assert (tmp_path / "out" / "result.json").is_file()  # the result is still written


def test_without_strict_the_summary_line_says_so(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["calibrate", "--quiet", "--config", _cell(tmp_path, False), "--out", str(tmp_path / "out")]) == 0
    assert "; cross-pose verdict inconsistent" in capsys.readouterr().out
