"""The run's summary text: what the command printed, kept word for word for ``report.txt``."""

from __future__ import annotations

import contextlib
import io
import sys
from collections.abc import Iterator
from typing import Any, TextIO

__all__ = ["MAX_TEXT_CHARS", "SummaryText"]

#: Characters of printed text kept (a monitor prints for hours; the head and the end are kept).
MAX_TEXT_CHARS = 1 << 20


class _Tee(io.TextIOBase):
    """A text stream that writes to ``target`` and keeps a bounded copy."""

    def __init__(self, target: TextIO, keeper: SummaryText) -> None:
        self.target = target
        self.keeper = keeper

    def write(self, text: str) -> int:
        self.keeper.add(text)
        return self.target.write(text)

    def flush(self) -> None:
        self.target.flush()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.target, name)


class SummaryText:
    """The words a command printed on stdout while :meth:`tee` was active, plus lines it adds itself."""

    def __init__(self) -> None:
        self._parts: list[str] = []
        self._size = 0
        self.dropped = 0

    def add(self, text: str) -> None:
        """Keep ``text`` (past :data:`MAX_TEXT_CHARS`, only the last half of the limit is kept)."""
        self._parts.append(text)
        self._size += len(text)
        if self._size > MAX_TEXT_CHARS:
            whole = "".join(self._parts)
            keep = whole[-MAX_TEXT_CHARS // 2:]
            self.dropped += len(whole) - len(keep)
            self._parts, self._size = [keep], len(keep)

    def line(self, text: str) -> None:
        """Keep one line that went elsewhere (an error on stderr, in the same words)."""
        self.add(text.rstrip("\n") + "\n")

    @contextlib.contextmanager
    def tee(self) -> Iterator[None]:
        """While active, everything printed on stdout is also kept."""
        previous = sys.stdout
        sys.stdout = _Tee(previous, self)  # type: ignore[assignment]
        try:
            yield
        finally:
            sys.stdout = previous

    @property
    def text(self) -> str:
        """The kept text."""
        head = f"[{self.dropped} earlier characters not kept]\n" if self.dropped else ""
        return head + "".join(self._parts)
