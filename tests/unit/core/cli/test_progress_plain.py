"""Progress on stderr when it is not a terminal: whole lines a log file keeps, no carriage-return redraws."""

from __future__ import annotations

import io
import subprocess
from pathlib import Path

import pytest
from fault_cells import cell_document, cellcal_argv
from toml_files import write_toml

from cellcal.core.cli import progress as progress_module
from cellcal.core.cli.progress import MAX_PLAIN_LINES, PLAIN_LINE, PlainProgress, progress_factory


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_plain_lines_count_the_finished_steps() -> None:
    stream = io.StringIO()
    bar = PlainProgress(3, "poses", "pose", stream)
    for _ in range(3):
        bar.update(1)
    bar.close()
    assert stream.getvalue() == "3 poses to go (0/3)\npose 1/3 done\npose 2/3 done\npose 3/3 done\n"
    assert all(PLAIN_LINE.fullmatch(line) for line in stream.getvalue().splitlines())


def test_a_long_run_prints_about_one_line_per_percent_and_the_last() -> None:
    stream = io.StringIO()
    bar = PlainProgress(1001, "trials", "trial", stream)
    for _ in range(1001):
        bar.update(1)
    lines = stream.getvalue().splitlines()
    assert lines[0] == "1001 trials to go (0/1001)"
    assert lines[1] == "trial 11/1001 done" and lines[-2] == "trial 990/1001 done"
    assert lines[-1] == "trial 1001/1001 done"
    assert len(lines) == 1 + 90 + 1 <= MAX_PLAIN_LINES + 2      # every 11th trial (ceil(1001 / 100)), and the last


def test_the_factory_draws_a_bar_only_on_a_terminal(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(progress_module.sys, "stderr", io.StringIO())
    factory = progress_factory("poses", "pose", quiet=False)
    assert factory is not None and isinstance(factory(3), PlainProgress)
    monkeypatch.setattr(progress_module.sys, "stderr", _Terminal())
    factory = progress_factory("poses", "pose", quiet=False)
    assert factory is not None
    bar = factory(3)
    assert not isinstance(bar, PlainProgress) and type(bar).__name__ == "tqdm"
    bar.close()
    assert progress_factory("poses", "pose", quiet=True) is None


def test_the_cli_writes_plain_lines_to_a_log_file(tmp_path: Path) -> None:
    config = write_toml(tmp_path / "cell.toml", cell_document())
    log = tmp_path / "run.log"
    with log.open("wb") as err:
        done = subprocess.run([*cellcal_argv(), "calibrate", "--config", str(config), "--out", str(tmp_path / "out")],
                              stdout=subprocess.PIPE, stderr=err, timeout=300, check=False)
    assert done.returncode == 0, log.read_text()
    text = log.read_text(encoding="utf-8")
    assert "\r" not in text and "\x1b" not in text
    assert text == "3 poses to go (0/3)\npose 1/3 done\npose 2/3 done\npose 3/3 done\n"
    assert (tmp_path / "out" / "result.json").is_file()
