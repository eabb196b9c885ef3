"""The parent's side of a native library in a worker process: :class:`NativeHost` and its proxies."""

from __future__ import annotations

import contextlib
import logging
import pickle
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from multiprocessing.connection import Connection
from typing import IO, Any, TypeVar

from ..errors import DeviceConnectionError, DeviceError, DeviceTimeoutError, NativeCrashError
from . import protocol as p

log = logging.getLogger(__name__)

T = TypeVar("T")
#: Longest line of the worker's own output (the library's prints) kept for the debug log, characters.
MAX_OUTPUT_LINE = 500
#: Seconds the worker gets to tear its objects down at close before it is killed.
CLOSE_TIMEOUT_S = 4.0
#: Seconds a thread other than the main one waits for the spawner thread to start its worker.
SPAWN_TIMEOUT_S = 30.0


def _spawn(start: Callable[[], T]) -> T:
    """``start()`` (a worker's ``Popen``) on a thread that lives as long as the process.

    The worker asks Linux to SIGKILL it when its parent dies (``PR_SET_PDEATHSIG``), and the parent
    Linux means is the *thread* that forked it. A worker forked by a short-lived thread (a
    ``DeadlineGuard`` call off the main thread: every run of ``cellcal serve``) was killed as soon
    as that call returned. The main thread forks its workers itself; another thread hands the
    fork to one daemon thread that ends only with the process.
    """
    global _SPAWNER
    if threading.current_thread() is threading.main_thread():
        return start()
    done = threading.Event()
    value: list[T] = []
    error: list[BaseException] = []

    def job() -> None:
        try:
            value.append(start())
        except BaseException as exc:  # handed back to the caller as it is
            error.append(exc)
        finally:
            done.set()

    with _SPAWNER_LOCK:
        if _SPAWNER is None or not _SPAWNER.is_alive():
            _SPAWNER = threading.Thread(target=_serve_spawns, name="cellcal worker spawner", daemon=True)
            _SPAWNER.start()
    _SPAWNS.put(job)
    if not done.wait(SPAWN_TIMEOUT_S):  # Popen returns in milliseconds: a stuck spawner is a failed start
        raise OSError(f"the worker spawner did not start the process within {SPAWN_TIMEOUT_S:g} s")
    if error:
        raise error[0]
    return value[0]


def _serve_spawns() -> None:
    while True:
        _SPAWNS.get()()


_SPAWNS: queue.SimpleQueue[Callable[[], None]] = queue.SimpleQueue()
_SPAWNER: threading.Thread | None = None
_SPAWNER_LOCK = threading.Lock()


class RemoteObject:
    """An object that lives in the worker; every attribute is a method called there."""

    __slots__ = ("_handle", "_host", "type_name")

    def __init__(self, host: NativeHost, handle: int, type_name: str) -> None:
        self._host = host
        self._handle = handle
        self.type_name = type_name

    def __getattr__(self, name: str) -> Callable[..., Any]:
        if name.startswith("__"):
            raise AttributeError(name)
        host, handle = self._host, self._handle

        def method(*args: Any, **kwargs: Any) -> Any:
            return host.call(handle, name, args, kwargs)

        method.__name__ = name
        return method

    def __repr__(self) -> str:
        return f"<{self.type_name} #{self._handle} in the {self._host.library} worker>"


class RemoteModule(RemoteObject):
    """A module imported in the worker; ``module.Class(...)`` builds a :class:`RemoteObject` there."""


class NativeHost:
    """A worker process running one native library for one device.

    Calls are synchronous and serialised. Each waits for its reply until the deadline of the
    enclosing :meth:`run` block, else ``default_timeout_s``; an overrun is a
    :class:`DeviceTimeoutError` (the worker keeps the call; its late reply is discarded, a
    late object is dropped). A worker that dies raises :class:`NativeCrashError` now and on
    every later call; ``on_crash`` runs once first (e.g. stop the arm over another channel)
    and what it returns ends the message.

    Args:
        name: Who this is for messages, e.g. ``"ur 10.0.0.2"``.
        library: The native library, e.g. ``"ur_rtde"``.
        backend: The backend's registered name.
        default_timeout_s: Wait for a call outside any :meth:`run` block, seconds.
        on_crash: Called once when the worker is found dead; returns a clause for the message.
    """

    isolated = True

    def __init__(self, name: str, *, library: str, backend: str, default_timeout_s: float = 5.0,
                 on_crash: Callable[[], str] | None = None) -> None:
        self.name = name
        self.library = library
        self.backend = backend
        self.default_timeout_s = float(default_timeout_s)
        self.on_crash = on_crash
        self.calls = 0
        #: Replies received to the calls made (a value, an object or an error); a call that overran has none.
        self.answered = 0
        self._proc: subprocess.Popen[bytes] | None = None
        self._conn: Connection | None = None
        self._lock = threading.Lock()
        self._seq = 0
        self._until: float | None = None
        self._budget = 0.0
        self._what = ""
        #: Once the worker is dead or stopped: the signal that ended it ("" for an exit status), else None.
        self._dead: str | None = None

    # ------------------------------------------------------------ life cycle
    @property
    def pid(self) -> int | None:
        """The worker's process id while it runs."""
        return self._proc.pid if self._proc is not None else None

    def start(self, timeout: float) -> None:
        """Start the worker and wait (at most ``timeout`` s) until it answers."""
        parent, child = socket.socketpair()
        # blocking whatever socket.setdefaulttimeout() says (xarm-python-sdk sets 1 s for the whole process):
        # a timeout makes the descriptors non-blocking, and the worker would read EAGAIN as the end
        parent.setblocking(True)
        child.setblocking(True)
        try:
            command = [sys.executable, "-m", "cellcal.devices.isolation.worker", str(child.fileno())]
            self._proc = _spawn(lambda: subprocess.Popen(command, pass_fds=(child.fileno(),), stdin=subprocess.DEVNULL,
                                                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                                         close_fds=True))
        except OSError as exc:
            parent.close()
            raise DeviceConnectionError(f"{self.name}: cannot start the {self.library} worker process: {exc}") from None
        finally:
            child.close()
        self._conn = Connection(parent.detach())
        assert self._proc.stdout is not None
        threading.Thread(target=self._log_output, args=(self._proc.stdout,), daemon=True,
                         name=f"{self.name}: {self.library} output").start()
        budget = max(0.0, timeout)
        self._wait_reply(0, time.monotonic() + budget, budget, f"start the {self.library} worker process")

    def close(self, timeout: float = CLOSE_TIMEOUT_S) -> None:
        """Ask the worker to tear down and exit; kill it if it has not within ``timeout`` s. Never raises."""
        proc, conn = self._proc, self._conn
        self._proc = self._conn = None
        if conn is not None:
            with contextlib.suppress(OSError):
                conn.send_bytes(pickle.dumps((0, p.CLOSE, 0, "", (), {})))
        if proc is not None:
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                log.warning("%s: the %s worker did not exit within %g s; killed", self.name, self.library, timeout)
                proc.kill()
                with contextlib.suppress(subprocess.TimeoutExpired):
                    proc.wait(1.0)
        if conn is not None:
            conn.close()

    def _log_output(self, stream: IO[bytes]) -> None:
        """The library's own prints (C++ ``std::cout``): to the debug log, a line at a time, bounded."""
        with contextlib.suppress(Exception):
            for raw in iter(lambda: stream.readline(4096), b""):
                line = raw.decode("utf-8", "replace").rstrip()
                if line:
                    log.debug("%s: %s: %s", self.name, self.library, line[:MAX_OUTPUT_LINE])
            stream.close()

    # ------------------------------------------------------------ calls
    def module(self, name: str) -> RemoteModule:
        """Import module ``name`` in the worker (ImportError as the worker raised it)."""
        value = self._request(p.IMPORT, 0, name, (), {}, f"import {name}")
        if not isinstance(value, RemoteObject):
            raise ImportError(f"{name} is not a module")
        return RemoteModule(self, value._handle, value.type_name)

    @contextlib.contextmanager
    def deadline(self, timeout: float, what: str) -> Iterator[None]:
        """Calls inside share one deadline ``timeout`` s from now; an overrun names ``what``."""
        outer = self._until, self._budget, self._what
        budget = max(0.0, timeout)
        self._until, self._budget, self._what = time.monotonic() + budget, budget, what
        try:
            yield
        finally:
            self._until, self._budget, self._what = outer

    def bounded(self, fn: Callable[[], T], timeout: float, what: str,
                on_late: Callable[[T], None] | None = None) -> T:
        """``fn()`` with its calls into the worker under one deadline (late objects are dropped anyway)."""
        with self.deadline(timeout, what):
            return fn()

    def call(self, handle: int, name: str, args: tuple[Any, ...], kwargs: dict[str, Any]) -> Any:
        """Call ``name`` of object ``handle`` in the worker; returns a value or a :class:`RemoteObject`."""
        return self._request(p.CALL, handle, name, args, kwargs, name)

    def drop(self, obj: Any, *, disconnect: bool = True) -> None:
        """Forget a :class:`RemoteObject`: the worker's reaper thread (alone) disconnects it and frees it.

        Args:
            obj: The object; anything else is ignored.
            disconnect: Call its ``disconnect()`` before freeing it (a stale link: the wait happens
                off the worker's main thread); False frees it only (its destructor disconnects).
        """
        if isinstance(obj, RemoteObject) and obj._host is self and self._conn is not None and self._dead is None:
            with self._lock, contextlib.suppress(OSError):
                self._conn.send_bytes(pickle.dumps((0, p.DROP, obj._handle, "disconnect" if disconnect else "",
                                                    (), {})))

    def _request(self, op: str, handle: int, name: str, args: tuple[Any, ...], kwargs: dict[str, Any],
                 what: str) -> Any:
        if self._dead is not None:
            raise NativeCrashError(f"{self.name}: the {self.library} worker process died earlier "
                                   f"({self._dead or 'exited'}); connect again",
                                   backend=self.backend, signal_name=self._dead)
        if self._conn is None:
            raise DeviceConnectionError(f"{self.name}: the {self.library} worker process is not running")
        budget = self._budget if self._until is not None else self.default_timeout_s
        until = self._until if self._until is not None else time.monotonic() + budget
        label = f"{self._what} ({what})" if self._what and self._what != what else what
        if not self._lock.acquire(timeout=max(0.0, until - time.monotonic())):
            raise DeviceTimeoutError(f"{self.name}: {label}: another call into {self.library} has not returned")
        try:
            self._seq += 1
            seq = self._seq
            # the caller's mistakes (an argument that does not pickle, or one too big for the worker to read) are
            # raised here, before anything is sent: sent, the worker would end, and that would read as a crash
            data = pickle.dumps((seq, op, handle, name, args, kwargs))
            if len(data) > p.MAX_MESSAGE_BYTES:
                raise DeviceError(f"{self.name}: {label}: the request is {len(data)} bytes, over the "
                                  f"{p.MAX_MESSAGE_BYTES} the {self.library} worker reads; nothing was sent")
            try:
                self._conn.send_bytes(data)
            except OSError:  # the worker is gone
                self._crashed(label)
            self.calls += 1
            return self._wait_reply(seq, until, budget, label)
        finally:
            self._lock.release()

    def _wait_reply(self, seq: int, until: float, budget: float, what: str) -> Any:
        """The reply to ``seq`` by ``until`` (``budget`` s, for the message); older replies are discarded.

        Older replies are those of calls that overran; an object among them is dropped.
        """
        conn = self._conn
        assert conn is not None
        while True:
            left = until - time.monotonic()
            try:
                ready = left > 0 and conn.poll(left)
            except (OSError, EOFError):
                self._crashed(what)
            if not ready:
                raise DeviceTimeoutError(f"{self.name}: {what} did not finish within {budget:.3g} s")
            try:
                got, kind, payload = pickle.loads(conn.recv_bytes(p.MAX_MESSAGE_BYTES))
            except (EOFError, ConnectionError):  # closed, reset: the worker is gone
                self._crashed(what)
            except Exception as exc:  # oversized (OSError) or garbled: the worker is not to be trusted any more
                if self._proc is not None and self._proc.poll() is not None:
                    self._crashed(what)
                self._kill()
                self._dead = ""
                stopped = self._stop_device()  # the device's connections went with the worker
                raise DeviceConnectionError(f"{self.name}: the {self.library} worker sent an unreadable reply to "
                                            f"{what} ({exc}); it was stopped{'; ' + stopped if stopped else ''}"
                                            ) from None
            if got != seq:
                if kind == p.REF:  # a late object nobody will use: let the worker free it
                    with contextlib.suppress(OSError):  # a worker gone by now is found by the next read
                        conn.send_bytes(pickle.dumps((0, p.DROP, payload[0], "", (), {})))
                continue
            self.answered += 1
            if kind == p.VALUE:
                return payload
            if kind == p.REF:
                return RemoteObject(self, int(payload[0]), str(payload[1]))
            extra = payload[2:4] if len(payload) == 4 and isinstance(payload[2], tuple) \
                and isinstance(payload[3], dict) else ()
            raise p.rebuild_error(str(payload[0]), str(payload[1]), *extra)

    # ------------------------------------------------------------ a dead worker
    def _kill(self) -> None:
        proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.kill()

    def _stop_device(self) -> str:
        """Run ``on_crash`` once (the worker is gone, with the device's connections); its clause, or ""."""
        if self.on_crash is None:
            return ""
        hook, self.on_crash = self.on_crash, None
        try:
            return hook()
        except Exception as exc:  # the hook reports; it must not mask the crash
            return f"stopping the arm failed ({exc})"

    def _crashed(self, what: str) -> Any:
        """Raise (and remember) the :class:`NativeCrashError` of a worker that went away during ``what``."""
        proc = self._proc
        code: int | None = None
        if proc is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                code = proc.wait(1.0)
        sig_name = ""
        if code is not None and code < 0:
            try:
                sig_name = signal.Signals(-code).name
            except ValueError:
                sig_name = f"signal {-code}"
            crash = sig_name in ("SIGSEGV", "SIGABRT", "SIGBUS", "SIGFPE", "SIGILL")
            how = f"{sig_name}, {'a crash in native code' if crash else 'killed from outside'}"
        else:
            how = f"exit status {code}" if code is not None else "its pipe closed"
        stopped = self._stop_device()
        message = (f"{self.name}: the {self.library} worker process died during {what} ({how}); "
                   f"cellcal is unaffected, the device's connections are gone"
                   f"{'; ' + stopped if stopped else ''}")
        self._dead = sig_name
        log.debug("%s", message)  # the exception carries it to the user, once
        raise NativeCrashError(message, backend=self.backend, signal_name=sig_name)

