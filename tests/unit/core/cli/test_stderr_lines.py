"""Every message cellcal writes on stderr starts a line of its own, whatever was on stderr before (ADR 0043).

A user saw ``3 poses to go (0/3)cellcal: interrupted``: the progress line was written as its
text and then its newline, and the Ctrl-C landed between the two writes. Here the interrupt
is put between any two writes, deterministically, and a terminal's bar is left drawn.
"""

from __future__ import annotations

import io
import sys
from pathlib import Path

import pytest
from fault_cells import cell_document
from toml_files import write_toml

from cellcal.core.cli import EXIT_INTERRUPTED, main
from cellcal.core.cli.progress import PLAIN_LINE, PlainProgress, progress_factory
from cellcal.core.console import say


class _InterruptedAtWrite(io.StringIO):
    """A log file (not a terminal) where the Ctrl-C lands on the ``n``-th write call, before it writes, once."""

    def __init__(self, n: int) -> None:
        super().__init__()
        self.n = n
        self.calls = 0

    def write(self, text: str) -> int:
        self.calls += 1
        if self.calls == self.n:
            raise KeyboardInterrupt
        return super().write(text)


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def _screen(text: str) -> list[str]:
    """The lines a terminal shows for ``text``: ``\\r`` goes back to the line's start, what follows overwrites."""
    assert "\x1b" not in text  # one bar at position 0 moves no cursor up or down
    lines: list[list[str]] = [[]]
    col = 0
    for ch in text:
        if ch == "\n":
            lines.append([])
            col = 0
        elif ch == "\r":
            col = 0
        else:
            line = lines[-1]
            line[col:col + 1] = [ch]
            col += 1
    return ["".join(line).rstrip() for line in lines]


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_an_interrupt_between_any_two_writes_leaves_the_message_a_line_of_its_own(n: int) -> None:
    # a plain display of 3 steps writes at least 4 times (4 lines); print() wrote 8 (text, then newline)
    stream = _InterruptedAtWrite(n)
    with pytest.raises(KeyboardInterrupt):
        bar = PlainProgress(3, "poses", "pose", stream)
        for _ in range(3):
            bar.update(1)
    say("cellcal: interrupted", stream)
    *progress, message, end = stream.getvalue().split("\n")
    assert (message, end) == ("cellcal: interrupted", "")
    assert len(progress) == n - 1 and all(PLAIN_LINE.fullmatch(line) for line in progress), stream.getvalue()


def test_a_bar_left_drawn_on_a_terminal_is_cleared_for_the_message_and_drawn_again_below(
        monkeypatch: pytest.MonkeyPatch) -> None:
    terminal = _Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    factory = progress_factory("poses", "pose", quiet=False)
    assert factory is not None
    bar = factory(3)
    bar.update(1)
    assert _screen(terminal.getvalue())[-1].startswith("poses:")  # the bar, on a line it leaves open
    say("cellcal: interrupted")
    shown = _screen(terminal.getvalue())
    assert shown[0] == "cellcal: interrupted", shown  # not "cellcal: interrupted| 1/3 [00:00<00:00, ...]"
    assert len(shown) == 2 and shown[1].startswith("poses:") and "1/3" in shown[1], shown
    bar.close()
    assert _screen(terminal.getvalue()) == ["cellcal: interrupted", ""]


def test_the_cli_interrupted_inside_a_progress_write_says_so_on_a_line_of_its_own(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The reported run, in process: the Ctrl-C lands in the second write on stderr (a progress line)."""
    config = write_toml(tmp_path / "cell.toml", cell_document())
    log = _InterruptedAtWrite(2)
    monkeypatch.setattr(sys, "stderr", log)
    code = main(["calibrate", "--config", str(config), "--out", str(tmp_path / "out"), "--no-report"])
    monkeypatch.undo()
    assert code == EXIT_INTERRUPTED
    *progress, message, end = log.getvalue().split("\n")
    assert end == "" and message.startswith("cellcal: interrupted"), log.getvalue()
    assert progress and all(PLAIN_LINE.fullmatch(line) for line in progress), log.getvalue()
    assert not (tmp_path / "out" / "result.json").exists()
