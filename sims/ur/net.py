"""TCP plumbing shared by the emulator's three servers: a listener that runs one thread per connection.

The listener can drop every live connection (fault injection), turn new connections
away for a while (each is reset as soon as it is accepted) and close with every thread
joined.
"""

from __future__ import annotations

import contextlib
import logging
import select
import socket
import struct
import threading
from collections.abc import Callable

log = logging.getLogger(__name__)

#: How often blocking loops look at their stop flag, s.
POLL_S = 0.05
#: A send to a client that does not read gives up after this long, s.
SEND_TIMEOUT_S = 1.0
#: Bound on joining a connection thread at close, s.
JOIN_S = 2.0


class Connection:
    """One accepted client: its socket and a flag its handler checks to end."""

    def __init__(self, sock: socket.socket, peer: tuple[str, int], number: int) -> None:
        self.sock = sock
        self.peer = peer
        self.number = number
        self.closing = threading.Event()

    def recv(self, timeout: float, size: int = 65536) -> bytes | None:
        """Bytes received within ``timeout`` (None if none arrived yet); b"" when the peer closed."""
        if self.closing.is_set():
            return b""
        try:
            ready, _, _ = select.select([self.sock], [], [], max(0.0, timeout))
            if not ready:
                return None
            return self.sock.recv(size)
        except (OSError, ValueError):
            return b""

    def send(self, data: bytes) -> bool:
        """Send everything (bounded by :data:`SEND_TIMEOUT_S`); False if the link is gone."""
        if self.closing.is_set():
            return False
        try:
            self.sock.sendall(data)
        except (OSError, ValueError):
            self.closing.set()
            return False
        return True

    def abort(self) -> None:
        """Cut the link now (both directions); the handler sees end of stream."""
        self.closing.set()
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)


Handler = Callable[[Connection], None]


def _reset(sock: socket.socket) -> None:
    """Close with a TCP reset (SO_LINGER 0): the peer sees its connection reset, not a clean end."""
    with contextlib.suppress(OSError):
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    sock.close()


class Listener:
    """Accept TCP connections on ``(host, port)``; run ``handler(connection)`` in a thread for each.

    Args:
        host: Address to bind (a loopback address in tests).
        port: TCP port.
        handler: Serves one connection until it ends or ``connection.closing`` is set.
        name: Thread name prefix.
    """

    def __init__(self, host: str, port: int, handler: Handler, name: str) -> None:
        self.host = host
        self.port = port
        self.name = name
        self._handler = handler
        self._lock = threading.Lock()
        self._server: socket.socket | None = None
        self._stop = threading.Event()
        self._rejecting = threading.Event()
        self._accept_thread: threading.Thread | None = None
        self._live: dict[int, tuple[Connection, threading.Thread]] = {}
        self._count = 0

    @property
    def connections(self) -> list[Connection]:
        """Connections currently served."""
        with self._lock:
            return [c for c, _ in self._live.values()]

    @property
    def accepted(self) -> int:
        """Connections accepted so far."""
        return self._count

    def start(self) -> None:
        """Bind, listen and start accepting.

        Raises:
            OSError: If the address cannot be bound (in use, not local).
        """
        self._bind()
        self._stop.clear()
        self._accept_thread = threading.Thread(target=self._accept_loop, name=f"{self.name} accept", daemon=True)
        self._accept_thread.start()

    def _bind(self) -> None:
        server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            server.bind((self.host, self.port))
            server.listen(8)
        except OSError:
            server.close()
            raise
        self.port = server.getsockname()[1]  # port 0 binds a free port (tests); keep it for accept_again()
        with self._lock:
            self._server = server

    def refuse(self) -> None:
        """Turn every new connection away: it is accepted and reset at once.

        The listening socket stays open, so the address stays this emulator's: a closed
        one could be taken by another process (another emulator on the same loopback
        address) before :meth:`accept_again`.
        """
        self._rejecting.set()

    def accept_again(self) -> None:
        """Serve new connections again after :meth:`refuse`."""
        self._rejecting.clear()

    def drop_all(self) -> int:
        """Cut every live connection; returns how many."""
        live = self.connections
        for conn in live:
            conn.abort()
        return len(live)

    def close(self) -> None:
        """Stop accepting, cut every connection and join every thread (bounded)."""
        self._stop.set()
        with self._lock:
            server, self._server = self._server, None
        if server is not None:
            # close() alone leaves the socket listening while the accept thread's select() holds it
            with contextlib.suppress(OSError):
                server.shutdown(socket.SHUT_RDWR)
            server.close()
        self.drop_all()
        if self._accept_thread is not None:
            self._accept_thread.join(JOIN_S)
            self._accept_thread = None
        with self._lock:
            threads = [t for _, t in self._live.values()]
        for thread in threads:
            thread.join(JOIN_S)

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                server = self._server
            if server is None:
                self._stop.wait(POLL_S)
                continue
            try:
                ready, _, _ = select.select([server], [], [], POLL_S)
                if not ready:
                    continue
                sock, peer = server.accept()
            except (OSError, ValueError):
                continue  # closed by close() meanwhile
            if self._rejecting.is_set():
                _reset(sock)
                continue
            self._spawn(sock, peer)

    def _spawn(self, sock: socket.socket, peer: tuple[str, int]) -> None:
        sock.settimeout(SEND_TIMEOUT_S)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._count += 1
        conn = Connection(sock, peer, self._count)
        thread = threading.Thread(target=self._serve, args=(conn,), name=f"{self.name} #{conn.number}", daemon=True)
        with self._lock:
            self._live[conn.number] = (conn, thread)
        thread.start()

    def _serve(self, conn: Connection) -> None:
        try:
            self._handler(conn)
        except Exception:
            log.exception("%s: connection %d from %s failed", self.name, conn.number, conn.peer)
        finally:
            conn.closing.set()
            with contextlib.suppress(OSError):
                conn.sock.close()
            with self._lock:
                self._live.pop(conn.number, None)
