"""The one progress display of the ``cellcal`` commands, on stderr.

On a terminal: a tqdm bar, gone when done. Anywhere else (a log file, a pipe, CI) a bar's
redraws would leave ``\\r``-separated fragments (``0/3``) in the log, so the run says once
how many steps it has (``3 poses to go (0/3)``) and each finished step is one plain line:
``pose 2/3 done``. A long run (more than :data:`MAX_PLAIN_LINES` steps) prints a line per
percent, and always the last step. :data:`PLAIN_LINE` matches those lines. Each line is one
write call with its newline, so a Ctrl-C never leaves one open for the next message (ADR 0043).
"""

from __future__ import annotations

import re
import sys
from typing import IO, TYPE_CHECKING, Any

from cellcal.core.console import write_line

if TYPE_CHECKING:
    from cellcal.core.calibration.calibrator import ProgressFactory

__all__ = ["MAX_PLAIN_LINES", "PLAIN_LINE", "PlainProgress", "progress_factory"]

#: Most lines a plain progress display prints for one run (about one per percent beyond this).
MAX_PLAIN_LINES = 100
#: A line of :class:`PlainProgress` (to tell progress from the other lines of a log).
PLAIN_LINE = re.compile(r"\d+ \w+ to go \(0/\d+\)|\w+ \d+/\d+ done")


class PlainProgress:
    """tqdm's ``update`` / ``close`` as plain lines, for a stream that is not a terminal.

    ``3 poses to go (0/3)`` when made, then ``pose 1/3 done`` and so on.

    Args:
        total: Steps of the run.
        desc: What the steps are, plural (``"poses"``), for the first line.
        unit: What one step is (``"pose"``, ``"trial"``).
        stream: Where the lines go (stderr).
    """

    def __init__(self, total: int, desc: str, unit: str, stream: IO[str]) -> None:
        self.total = total
        self.unit = unit
        self.stream = stream
        self.n = 0
        import threading  # here: not at `cellcal --help`

        self._every = max(1, -(-total // MAX_PLAIN_LINES))  # ceil: at most MAX_PLAIN_LINES lines
        self._lock = threading.Lock()  # a study's worker results arrive on another thread
        write_line(stream, f"{total} {desc} to go (0/{total})")

    def update(self, n: int = 1) -> None:
        """Count ``n`` finished steps; print a line for the step when it is one to show."""
        with self._lock:
            before, self.n = self.n, self.n + n
            if self.n == self.total or self.n // self._every > before // self._every:
                write_line(self.stream, f"{self.unit} {self.n}/{self.total} done")

    def close(self) -> None:
        """Nothing to clear: the lines stay."""


def _is_terminal(stream: IO[str]) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError, OSError):  # no isatty, or a closed stream
        return False


def progress_factory(desc: str, unit: str, quiet: bool) -> ProgressFactory | None:
    """A factory of progress displays counting ``unit`` s, labelled ``desc``; None when ``quiet``.

    A tqdm bar when stderr is a terminal (tqdm is imported only then), else plain lines
    (:class:`PlainProgress`).
    """
    if quiet:
        return None
    stream = sys.stderr
    if not _is_terminal(stream):
        def plain(total: int) -> Any:
            return PlainProgress(total, desc, unit, stream)

        return plain
    import threading

    from tqdm import tqdm

    tqdm.set_lock(threading.RLock())  # one process draws the bars: no multiprocessing lock (7 ms to make)

    def progress(total: int) -> Any:
        return tqdm(total=total, desc=desc, unit=unit, file=stream, leave=False)

    return progress
