"""The in-process stand-in of :class:`~cellcal.devices.isolation.NativeHost`: :class:`InlineHost`.

The same calls, run in this process: for debugging a backend under a debugger, and for unit
tests that replace the library's classes with mocks. A crash in the library ends cellcal.
"""

from __future__ import annotations

import contextlib
import importlib
from collections.abc import Callable, Iterator
from types import ModuleType
from typing import Any, TypeVar

from ..blocking import BoundedCaller

T = TypeVar("T")


class InlineHost:
    """Runs the library in this process; blocking calls in :class:`BoundedCaller` threads.

    Args:
        name: Who this is for messages, e.g. ``"ur 10.0.0.2"``.
        library: The native library, e.g. ``"ur_rtde"``.
        backend: The backend's registered name.
    """

    isolated = False

    def __init__(self, name: str, *, library: str, backend: str, **_: Any) -> None:
        self.name = name
        self.library = library
        self.backend = backend
        self.caller = BoundedCaller(name)

    def start(self, timeout: float) -> None:
        """Nothing to start."""

    def module(self, name: str) -> ModuleType:
        """``import name`` here."""
        return importlib.import_module(name)

    @contextlib.contextmanager
    def deadline(self, timeout: float, what: str) -> Iterator[None]:
        """No bound of its own (in-process calls are bounded by :meth:`bounded` only)."""
        yield

    def bounded(self, fn: Callable[[], T], timeout: float, what: str,
                on_late: Callable[[T], None] | None = None) -> T:
        """``fn()`` in a worker thread, abandoned after ``timeout`` s (its late result given to ``on_late``)."""
        return self.caller.call(fn, timeout, what, on_late=on_late)

    def drop(self, obj: Any, *, disconnect: bool = True) -> None:
        """Disconnect ``obj`` now, on this thread (it may block for the library's own timeout).

        In-process the object is disconnected whatever ``disconnect`` says: a test or a debugger may
        still hold it, and its destructor would then never run.
        """
        method = getattr(obj, "disconnect", None)
        if callable(method):
            with contextlib.suppress(Exception):
                method()

    def close(self, timeout: float = 1.0) -> None:
        """Wait (bounded) for abandoned calls."""
        self.caller.join(timeout)
