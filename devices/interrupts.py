"""Ctrl-C held back over a few lines that must not be torn, and delivered right after them."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator

__all__ = ["interrupts_held"]


@contextlib.contextmanager
def interrupts_held() -> Iterator[None]:
    """Hold back Ctrl-C (SIGINT) inside the block and deliver it, once, when the block ends.

    For state that a KeyboardInterrupt half-way through would tear (an MCAP writer's chunk
    and index, a child process started but not yet known to the code that must stop it).
    Python runs signal handlers in the main thread only, so elsewhere there is nothing to
    hold back; a handler installed outside Python cannot be restored, so it is left alone.
    """
    previous = signal.getsignal(signal.SIGINT) if threading.current_thread() is threading.main_thread() else None
    if previous is None:
        yield
        return
    held: list[int] = []
    signal.signal(signal.SIGINT, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if held:
            signal.raise_signal(signal.SIGINT)  # now, to the handler it was meant for
