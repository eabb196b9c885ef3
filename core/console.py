"""Whole lines on stderr: every message cellcal writes there starts a line of its own (ADR 0043).

A message (an error, "interrupted", a note) goes out through :func:`say`: a progress bar
drawn on the terminal is cleared first, then the line and its newline are written in one
``write`` call, so a Ctrl-C lands before or after it, never between the text and its end.
The plain progress lines of a log are written the same way (:func:`write_line`), and what
Python writes on stderr by itself (warnings, logging) is whole lines too: no line is left
open for a message to run on. The module imports nothing: the entry point loads it first.
"""

from __future__ import annotations

import sys
from typing import IO

__all__ = ["Interrupted", "say", "write_line"]


class Interrupted(KeyboardInterrupt):
    """A Ctrl-C that comes with its own line (said instead of ``cellcal: interrupted``), e.g. what it left undone.

    Args:
        line: The one line to say, ``cellcal: interrupted ...``.
    """

    def __init__(self, line: str) -> None:
        super().__init__(line)
        self.line = line


def write_line(stream: IO[str], text: str) -> None:
    """Write ``text`` and its newline in one call and flush: an interrupt cannot split them."""
    stream.write(f"{text}\n")
    stream.flush()


def say(text: str, stream: IO[str] | None = None) -> None:
    """Write ``text`` as a line of its own on ``stream`` (None: stderr); never raises for a broken stream.

    tqdm bars (looked for only when tqdm was imported) are cleared first and drawn again below
    the line, as ``tqdm.write`` does: a bar sits on a line it leaves open.
    """
    out = sys.stderr if stream is None else stream
    try:
        tqdm_std = sys.modules.get("tqdm.std")
        if tqdm_std is None:
            write_line(out, text)
            return
        with tqdm_std.tqdm.external_write_mode(file=out):
            write_line(out, text)
    except (OSError, ValueError, AttributeError):  # stderr closed, a broken pipe, or no stderr at all
        pass
