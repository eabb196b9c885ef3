"""The worker process of a :class:`~cellcal.devices.isolation.NativeHost`: ``python -m`` this module ``FD``.

It holds the native library's objects and runs the parent's requests one at a time on its
main thread. Objects the parent drops go to one reaper thread that alone owns them from then
on (their ``disconnect()`` can block for seconds), so no two threads ever touch one object.
The worker ignores Ctrl-C (the parent stops it in order) and dies with its parent (Linux).
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib
import os
import pickle
import queue
import signal
import sys
import threading
from multiprocessing.connection import Connection
from typing import Any

from . import protocol as p

#: Seconds the worker gives dropped objects' teardown before it exits anyway.
REAP_AT_EXIT_S = 3.0
_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    """Ask Linux to SIGKILL this process when its parent dies (no orphan holding the device's sockets)."""
    with contextlib.suppress(Exception):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)


class _Reaper:
    """One thread that frees the objects handed to it, in order.

    An object dropped while the worker serves is disconnected first (``disconnect()``, which in
    ur_rtde releases the GIL while it waits out a dead stream, so the main thread goes on), then
    freed. At close objects are only freed: their destructors disconnect (ur_rtde's do, joining
    their threads; a ``disconnect()`` first would cost that time twice). Whatever a destructor
    leaves open closes with the process.
    """

    def __init__(self) -> None:
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="reaper", daemon=True)
        self._thread.start()

    def put(self, obj: Any, *, disconnect: bool) -> None:
        self._queue.put((obj, disconnect))

    def finish(self, timeout: float) -> None:
        self._queue.put(None)
        self._thread.join(timeout)

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            obj, disconnect = item
            del item
            if disconnect and callable(getattr(obj, "disconnect", None)):
                with contextlib.suppress(Exception):
                    obj.disconnect()
            del obj  # the last reference: the native destructor runs here, on this thread


class Worker:
    """The request loop over one connection."""

    def __init__(self, conn: Connection) -> None:
        self.conn = conn
        self.objects: dict[int, Any] = {}
        self.next_handle = 1
        self.reaper = _Reaper()

    def serve(self) -> None:
        """Answer requests until the parent says close or goes away; then tear everything down."""
        self._send((0, p.VALUE, os.getpid()))  # ready
        while True:
            try:
                seq, op, handle, name, args, kwargs = pickle.loads(self.conn.recv_bytes(p.MAX_MESSAGE_BYTES))
            except (EOFError, OSError):
                break  # the parent is gone
            if op == p.CLOSE:
                break
            if op == p.DROP:
                obj = self.objects.pop(handle, None)
                if obj is not None:
                    self.reaper.put(obj, disconnect=name == "disconnect")
                del obj
                continue
            self._send(self._answer(seq, op, handle, name, args, kwargs))
        for handle in sorted(self.objects, reverse=True):  # newest first, each on the reaper thread
            self.reaper.put(self.objects.pop(handle), disconnect=False)
        self.reaper.finish(REAP_AT_EXIT_S)

    def _answer(self, seq: int, op: str, handle: int, name: str, args: tuple[Any, ...],
                kwargs: dict[str, Any]) -> tuple[int, str, Any]:
        try:
            if op == p.IMPORT:
                value: Any = importlib.import_module(name)
            elif op == p.CALL:
                value = getattr(self.objects[handle], name)(*args, **kwargs)
            else:
                raise ValueError(f"unknown operation {op!r}")
        except Exception as exc:  # everything the library raises goes back to the caller, typed by name
            return seq, p.ERROR, p.error_payload(exc)
        if p.is_plain(value):
            return seq, p.VALUE, value
        new = self.next_handle
        self.next_handle += 1
        self.objects[new] = value
        return seq, p.REF, (new, type(value).__name__)

    def _send(self, reply: tuple[int, str, Any]) -> None:
        try:
            data = pickle.dumps(reply)
        except Exception as exc:  # a value that looked plain but does not pickle: an error reply, not an exit
            text = f"the reply could not be pickled: {exc}"[:p.MAX_ERROR_CHARS]
            data = pickle.dumps((reply[0], p.ERROR, (type(exc).__name__, text)))
        with contextlib.suppress(OSError):
            self.conn.send_bytes(data)


def main(argv: list[str]) -> int:
    """Serve on the inherited socket whose descriptor is ``argv[0]``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with_parent()
    fd = int(argv[0])
    os.set_blocking(fd, True)  # whatever the parent's socket defaults were
    conn = Connection(fd)
    Worker(conn).serve()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)  # no interpreter teardown: the native destructors already ran on the reaper


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
