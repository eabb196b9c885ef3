"""One emulated VPU port's PCIC server (:class:`PcicPort`): a listener, a thread per client, the commands.

Commands: ``p<hex>`` output mask, ``c<9 digits><schema>`` chunk selection (unknown blob
ids refused with ``!``), ``t`` software trigger (handed to ``on_trigger``); anything
else is answered ``?``. Unframeable input drops the client, as a device does.
"""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Callable
from typing import Any

from .wire import DEFAULT_CHUNKS, message, schema_chunks


class Conn:
    """One PCIC client connection."""

    def __init__(self, sock: socket.socket, peer: Any) -> None:
        self.sock = sock
        self.peer = peer
        self.mask = 0
        self.chunks: tuple[int, ...] = DEFAULT_CHUNKS
        self.send_lock = threading.Lock()
        self.alive = True
        self.thread: threading.Thread | None = None

    def send(self, data: bytes | memoryview) -> bool:
        """Send all of ``data``; a failed send kills the connection (False)."""
        try:
            with self.send_lock:
                self.sock.sendall(data)
            return True
        except OSError:
            self.kill()
            return False

    def kill(self) -> None:
        self.alive = False
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)


class PcicPort:
    """The PCIC server of one VPU port on ``host:port`` (0: ephemeral).

    Args:
        name: VPU port name (``port2``, ``port6``, ``app0``), for thread names.
        host: Interface to bind.
        port: TCP port (0: ephemeral).
        trigger_allowed: Whether a ``t`` is accepted now (the reply is ``*``, else ``!``);
            None refuses every trigger.
        on_trigger: Called with the connection after the ``*`` reply to a ``t`` (sends the frame).
        on_mask: Called after an output mask changed (wakes the frame loop).
    """

    def __init__(self, name: str, host: str, port: int, *,
                 trigger_allowed: Callable[[], bool] | None = None,
                 on_trigger: Callable[[Conn], None] | None = None,
                 on_mask: Callable[[], None] | None = None) -> None:
        self.name = name
        self.trigger_allowed = trigger_allowed
        self.on_trigger = on_trigger
        self.on_mask = on_mask
        self.commands: list[str] = []
        self.generation = 0  # counts accepted clients and output mask changes (see connections)
        self._stop = threading.Event()
        self._conns: list[Conn] = []
        self._lock = threading.Lock()
        lst = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            lst.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            lst.bind((host, port))
            lst.listen(8)
        except OSError:
            lst.close()
            raise
        lst.settimeout(0.1)
        self._listener = lst
        self.port = int(lst.getsockname()[1])
        self._thread = threading.Thread(target=self._accept_loop, name=f"o3r-emu-{name}", daemon=True)

    def start(self) -> PcicPort:
        self._thread.start()
        return self

    def connections(self, *, mask_bit: int | None = None) -> list[Conn]:
        """Live connections (with ``mask_bit`` set in their output mask, if given).

        The answer stays right while :attr:`generation` is unchanged and each connection is alive.
        """
        with self._lock:
            return [c for c in self._conns if c.alive and (mask_bit is None or c.mask & mask_bit)]

    def go_offline(self) -> None:
        """Close every connection and refuse new ones (the listening socket is shut down)."""
        with contextlib.suppress(OSError):
            self._listener.shutdown(socket.SHUT_RDWR)
        for c in self.connections():
            c.kill()

    def close(self) -> None:
        """Stop accepting, close every connection, join every thread."""
        self._stop.set()
        with self._lock:
            conns = list(self._conns)
        for c in conns:
            c.kill()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        for c in conns:
            if c.thread is not None:
                c.thread.join(timeout=5.0)
            with contextlib.suppress(OSError):
                c.sock.close()
        self._listener.close()

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                sock, peer = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                break
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn = Conn(sock, peer)
            conn.thread = threading.Thread(target=self._conn_loop, args=(conn,), name=f"o3r-emu-{self.name}-conn",
                                           daemon=True)
            with self._lock:
                self._conns = [c for c in self._conns if c.alive or (c.thread and c.thread.is_alive())]
                self._conns.append(conn)
                self.generation += 1
            conn.thread.start()

    def _conn_loop(self, conn: Conn) -> None:
        conn.sock.settimeout(0.1)
        buf = bytearray()
        try:
            while conn.alive and not self._stop.is_set():
                try:
                    data = conn.sock.recv(65536)
                except TimeoutError:
                    continue
                except OSError:
                    break
                if not data:
                    break
                buf += data
                if not self._drain(conn, buf):
                    return
        finally:
            conn.alive = False
            with contextlib.suppress(OSError):
                conn.sock.close()

    def _drain(self, conn: Conn, buf: bytearray) -> bool:
        """Handle every complete command in ``buf``; False if the input cannot be framed (client dropped)."""
        while len(buf) >= 16:
            head = bytes(buf[:16])
            if not (head[:4].isdigit() and head[4:5] == b"L" and head[5:14].isdigit()):
                conn.kill()  # unframeable input: a real device drops the client too
                return False
            length = int(head[5:14])
            if len(buf) < 16 + length:
                break
            payload = bytes(buf[16:16 + length])
            del buf[:16 + length]
            self._command(conn, head[:4].decode(), payload[4:-2])
        return True

    def _command(self, conn: Conn, ticket: str, content: bytes) -> None:
        cmd = content[:1]
        self.commands.append(cmd.decode("ascii", "replace"))
        if cmd == b"p":
            try:
                conn.mask = int(content[1:].decode("ascii"), 16)
            except ValueError:
                conn.send(message(ticket, b"?"))
                return
            with self._lock:
                self.generation += 1
            conn.send(message(ticket, b"*"))
            if self.on_mask is not None:
                self.on_mask()
        elif cmd == b"c":
            conn.send(message(ticket, self._schema(conn, content)))
        elif cmd == b"t":
            if self.trigger_allowed is None or self.on_trigger is None or not self.trigger_allowed():
                conn.send(message(ticket, b"!"))
                return
            conn.send(message(ticket, b"*"))
            self.on_trigger(conn)
        else:
            conn.send(message(ticket, b"?"))

    @staticmethod
    def _schema(conn: Conn, content: bytes) -> bytes:
        """Apply a ``c`` command; the reply code."""
        try:
            n = int(content[1:10])
            text = content[10:].decode("utf-8")
            if n != len(content) - 10:
                return b"?"
        except (ValueError, UnicodeDecodeError):
            return b"?"
        try:
            conn.chunks = schema_chunks(text)
        except ValueError:  # not a schema, or a blob id an O3R does not know
            return b"!"
        return b"*"
