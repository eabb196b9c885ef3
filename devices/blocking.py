"""Bounded waits around calls that may block without honouring a timeout (:class:`BoundedCaller`).

Public helper for backends (docs/extending.md, section 5): wrap an SDK call that has no
timeout parameter, e.g. ``sdk.Device(serial)``, so ``_connect(timeout)`` returns within
``timeout``. cellcal's own drivers use it for ``rtde_control.RTDEControlInterface(host)``
and ``depthai.Device(info)``; the calibrator and the monitor use it to guard every backend
call. Why a late call is abandoned rather than cancelled: docs/adr/0015-vendor-drivers.md.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable
from typing import Generic, TypeVar

from .errors import DeviceTimeoutError

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
             on_late: Callable[[T], None] | None = None, *,
             error: Callable[[str], Exception] = DeviceTimeoutError) -> T:
        """Run ``fn()`` and return its result, waiting at most ``timeout`` seconds.

        Args:
            fn: The blocking call.
            timeout: Seconds to wait.
            what: What is being done, for the timeout message (e.g. ``"connect to 10.0.0.2"``).
            on_late: Called with the result if ``fn`` completes after the deadline.
            error: Builds the exception raised on a timeout from its one-line message.

        Returns:
            What ``fn`` returned.

        Raises:
            DeviceTimeoutError: If ``fn`` has not returned within ``timeout`` (or what
                ``error`` builds).
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
                raise error(f"{self._name}: {what} did not finish within {timeout:g} s")
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
        deadline = time.monotonic() + timeout
        for worker in self._abandoned:
            worker.join(max(0.0, deadline - time.monotonic()))
        self._abandoned = [t for t in self._abandoned if t.is_alive()]


class _Overrun(BaseException):
    """Raised by the alarm handler inside the guarded call; :class:`DeadlineGuard` turns it into its error.

    A BaseException, so a backend's ``except Exception`` cannot swallow it.
    """


class DeadlineGuard:
    """Bounds calls into a backend that may not honour its own timeout (the calibrator, the monitor).

    Each call may take its own ``timeout`` plus ``grace_s``. On the main thread (a CLI
    run) the call runs in place under a ``SIGALRM`` timer whose handler raises inside
    the overrunning call — a blocking wait is interrupted, ``finally`` blocks run, much as
    Ctrl-C would, and the timer fires again every :data:`REFIRE_S` until the call gives
    up. Elsewhere (no signals off the main thread) the call runs in a worker thread that
    is abandoned on overrun, as :class:`BoundedCaller` does. Either way the caller gets
    :class:`~cellcal.devices.errors.BackendOverrunError` naming the backend and the call.

    Args:
        name: Who is called, for messages, e.g. ``"camera backend 'acme-z1'"``.
        grace_s: Seconds a call may run beyond its own timeout.
    """

    #: Interval at which the alarm fires again while an overrunning call has not given up, seconds.
    REFIRE_S = 0.5

    def __init__(self, name: str, grace_s: float = 2.0):
        self.name = name
        self.grace_s = float(grace_s)
        self._worker = BoundedCaller(name)
        self._armed = False

    def call(self, fn: Callable[[], T], timeout: float, what: str) -> T:
        """Run ``fn()``, allowing ``timeout + grace_s`` seconds.

        Args:
            fn: The backend call.
            timeout: The timeout the call was given, seconds.
            what: The call, for the message, e.g. ``"capture(timeout=5 s)"``.

        Raises:
            BackendOverrunError: If the call did not return in time.
        """
        from .errors import BackendOverrunError

        allowed = float(timeout) + self.grace_s
        message = (f"{self.name}: {what} did not return within {allowed:g} s (its timeout + {self.grace_s:g} s): "
                   "the backend does not honour its timeout")
        if not self._can_alarm():
            return self._worker.call(fn, allowed, what, error=lambda _: BackendOverrunError(message))
        try:
            return self._alarmed(fn, allowed)
        except _Overrun:
            raise BackendOverrunError(message) from None

    def join(self, timeout: float) -> None:
        """Wait up to ``timeout`` seconds for abandoned worker threads (off the main thread only)."""
        self._worker.join(timeout)

    def _can_alarm(self) -> bool:
        """Whether a SIGALRM timer can guard this call: main thread, POSIX, no timer of someone else running."""
        import signal

        if self._armed or threading.current_thread() is not threading.main_thread():
            return False
        if not hasattr(signal, "setitimer"):
            return False
        return signal.getitimer(signal.ITIMER_REAL)[0] == 0.0

    def _alarmed(self, fn: Callable[[], T], allowed: float) -> T:
        import signal

        def on_alarm(signum: int, frame: object) -> None:
            if self._armed:               # a late signal after the call returned is ignored
                raise _Overrun

        previous = signal.signal(signal.SIGALRM, on_alarm)
        try:
            self._armed = True
            signal.setitimer(signal.ITIMER_REAL, allowed, self.REFIRE_S)
            try:
                return fn()
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0.0)
                self._armed = False
        finally:
            signal.signal(signal.SIGALRM, previous)
