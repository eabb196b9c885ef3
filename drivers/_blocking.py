"""Bounded waits around vendor calls that block without a timeout parameter (:class:`BoundedCaller`).

Used for ``rtde_control.RTDEControlInterface(host)``, ``depthai.Device(info)`` and the
like; why a late call is abandoned rather than cancelled: docs/adr/0015-vendor-drivers.md.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable
from typing import Generic, TypeVar

from cellcal.devices.errors import DeviceTimeoutError

T = TypeVar("T")


class _Call(Generic[T]):
    def __init__(self, fn: Callable[[], T], on_late: Callable[[T], None] | None):
        self.fn = fn
        self.on_late = on_late
        self.result: T | None = None
        self.error: BaseException | None = None
        self.abandoned = False
        self.done = False
        self.lock = threading.Lock()

    def run(self) -> None:
        try:
            value = self.fn()
        except BaseException as exc:
            with self.lock:
                self.error = exc
                self.done = True
            return
        with self.lock:
            self.result = value
            self.done = True
            late = self.abandoned
        if late and self.on_late is not None:
            with contextlib.suppress(Exception):
                self.on_late(value)


class BoundedCaller:
    """Runs blocking vendor calls with a deadline; tracks abandoned workers.

    Each call runs in a worker thread joined with the caller's timeout. A call that
    overruns cannot be cancelled (it is native code), so its worker is *abandoned*: it
    keeps running until the library's own internal timeout ends it, and whatever it
    produces late is released with ``on_late`` (e.g. ``disconnect()``), so no
    connection leaks. :meth:`join` waits (bounded) for abandoned workers; backends
    call it from ``_close()``.

    Args:
        name: Prefix of worker thread names (shows up in thread dumps).
    """

    def __init__(self, name: str):
        self._name = name
        self._abandoned: list[threading.Thread] = []

    def call(self, fn: Callable[[], T], timeout: float, what: str,
             on_late: Callable[[T], None] | None = None) -> T:
        """Run ``fn()`` and return its result, waiting at most ``timeout`` seconds.

        Args:
            fn: The blocking call.
            timeout: Seconds to wait.
            what: What is being done, for the timeout message (e.g. ``"connect to 10.0.0.2"``).
            on_late: Called with the result if ``fn`` completes after the deadline.

        Returns:
            What ``fn`` returned.

        Raises:
            DeviceTimeoutError: If ``fn`` has not returned within ``timeout``.
            Exception: Whatever ``fn`` raised, unchanged.
        """
        call = _Call(fn, on_late)
        worker = threading.Thread(target=call.run, name=f"{self._name}: {what}", daemon=True)
        worker.start()
        worker.join(max(0.0, timeout))
        with call.lock:
            if not call.done:
                call.abandoned = True
                self._abandoned.append(worker)
                raise DeviceTimeoutError(f"{self._name}: {what} did not finish within {timeout:g} s")
        if call.error is not None:
            raise call.error
        return call.result  # type: ignore[return-value]

    @property
    def pending(self) -> int:
        """Number of abandoned workers still running."""
        self._abandoned = [t for t in self._abandoned if t.is_alive()]
        return len(self._abandoned)

    def join(self, timeout: float) -> None:
        """Wait up to ``timeout`` seconds in total for abandoned workers to end."""
        import time

        deadline = time.monotonic() + timeout
        for worker in self._abandoned:
            worker.join(max(0.0, deadline - time.monotonic()))
        self._abandoned = [t for t in self._abandoned if t.is_alive()]
