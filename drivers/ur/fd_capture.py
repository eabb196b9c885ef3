"""What a C++ library prints while it connects, kept out of the user's terminal: :func:`captured_output`.

ur_rtde writes its own lines (``connect: Connection refused``, reconnect notes) with
``std::cout`` / ``std::cerr``, straight to the process's file descriptors 1 and 2, where
``sys.stdout`` redirection cannot reach them. Around a connect, both descriptors point
at a temporary file; what landed there is logged at DEBUG level (``--log-level debug``)
and never shown otherwise. The driver's own error message says what went wrong.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import sys
import tempfile
import threading
from collections.abc import Iterator
from typing import IO

log = logging.getLogger(__name__)

#: Most bytes of captured output kept for the debug log.
MAX_CAPTURED_BYTES = 4096
#: One capture at a time: a second one nested or in another thread writes into the first's file.
_ACTIVE = threading.Lock()


def _flush_c_streams() -> None:
    """Flush C stdio buffers (``std::cout`` syncs with them) so buffered text lands in the capture."""
    with contextlib.suppress(Exception):
        ctypes.CDLL(None).fflush(None)


def _flush_python_streams() -> None:
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()


@contextlib.contextmanager
def captured_output(what: str, limit: int = MAX_CAPTURED_BYTES) -> Iterator[None]:
    """Send file descriptors 1 and 2 to a temporary file for the block; log what arrived at DEBUG.

    Everything the process writes to its stdout and stderr during the block (every thread's)
    is captured, so keep the block short: a connect, bounded by its own deadline. Where the
    descriptors cannot be redirected (closed, or another capture is active) the block runs
    as is.

    Args:
        what: What the block does, for the debug line (e.g. ``"ur 10.0.0.2: connect"``).
        limit: Most bytes of the captured text kept for the log.
    """
    if not _ACTIVE.acquire(blocking=False):
        yield
        return
    try:
        with tempfile.TemporaryFile() as sink:
            _flush_python_streams()
            try:
                saved = [os.dup(1), os.dup(2)]
            except OSError:
                saved = []
            if not saved:
                yield
                return
            try:
                os.dup2(sink.fileno(), 1)
                os.dup2(sink.fileno(), 2)
                yield
            finally:
                _flush_python_streams()
                _flush_c_streams()
                for fd, copy in zip((1, 2), saved, strict=True):
                    os.dup2(copy, fd)
                    os.close(copy)
                _log_captured(sink, what, limit)
    finally:
        _ACTIVE.release()


def _log_captured(sink: IO[bytes], what: str, limit: int) -> None:
    """Log at DEBUG the first ``limit`` bytes written to ``sink``, one line, if any."""
    sink.seek(0)
    data = sink.read(limit + 1)
    text = data[:limit].decode("utf-8", "replace")
    if text.strip():
        more = " [...]" if len(data) > limit else ""
        log.debug("%s: the vendor library printed: %s%s", what,
                  " | ".join(line.strip() for line in text.splitlines() if line.strip()), more)
