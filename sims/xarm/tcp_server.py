"""The xArm emulator over TCP: the control port (register protocol) and the rich report port.

Anything that speaks to an xArm over Ethernet (cellcal's ``xarm`` driver with ``host``,
UFACTORY's ``XArmAPI("127.0.0.1")`` with its port constants pointed here) talks to it as
to a real controller::

    server = XArmTcpServer(XArmEmulator(SimArm().connect()))
    control_port, report_port = server.start()     # free ports on 127.0.0.1
"""

from __future__ import annotations

import contextlib
import select
import selectors
import socket
import threading
import time
from typing import Literal

from .emulator import XArmEmulator
from .tcp_wire import TcpCommand, read_requests, reply_bytes, rich_report
from .wire import FLAG_INVALID

ReportFault = Literal["garbage", "stall", "bad_values"]

#: Most control or report clients served at once (a real controller takes a few).
MAX_CLIENTS = 8
#: Bytes buffered per control client before it counts as flooding and is cut.
MAX_PENDING = 64 * 1024
#: A send to a client that does not read gives up after this long, s.
SEND_TIMEOUT_S = 1.0
_POLL_S = 0.05


def _listen(host: str, port: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(MAX_CLIENTS)
    except OSError:
        sock.close()
        raise
    return sock


def _accept(server: socket.socket) -> socket.socket | None:
    """Accept one client (blocking sends bounded by :data:`SEND_TIMEOUT_S`); None if it went away."""
    try:
        client, _peer = server.accept()
    except OSError:
        return None
    client.settimeout(SEND_TIMEOUT_S)
    client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return client


class XArmTcpServer:
    """Serve an :class:`XArmEmulator` on a TCP control port and a rich report port.

    Two threads: one answers every control connection (requests in order, faults from
    :meth:`XArmEmulator.inject` applied to the replies), one pushes the rich report to
    every report connection ``report_hz`` times a second.

    Args:
        emulator: The emulated controller (its pty need not be started).
        host: Address to bind (loopback in tests).
        tcp_port: Control port; 0 picks a free one.
        report_port: Report port; 0 picks a free one.
        report_hz: Reports per second.

    Attributes:
        tcp_port: The bound control port (after :meth:`start`).
        report_port: The bound report port (after :meth:`start`).
        reports_sent: Reports sent (over all report clients).
        transactions: Transaction ids received, in order (the last 1000).
    """

    def __init__(self, emulator: XArmEmulator, *, host: str = "127.0.0.1", tcp_port: int = 0, report_port: int = 0,
                 report_hz: float = 20.0):
        if not 0.5 <= report_hz <= 1000.0:
            raise ValueError(f"xarm emulator: report_hz must be within [0.5, 1000], got {report_hz}")
        self.emulator = emulator
        self.host = host
        self.tcp_port = tcp_port
        self.report_port = report_port
        self.report_hz = report_hz
        self.reports_sent = 0
        self.transactions: list[int] = []
        self._report_faults: list[ReportFault] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._servers: list[socket.socket] = []
        self._clients: list[socket.socket] = []

    # ------------------------------------------------------------------ life cycle
    def start(self) -> tuple[int, int]:
        """Bind both ports and start serving; returns ``(tcp_port, report_port)``.

        Raises:
            OSError: If a port cannot be bound.
        """
        if self._threads:
            return self.tcp_port, self.report_port
        control = _listen(self.host, self.tcp_port)
        try:
            report = _listen(self.host, self.report_port)
        except OSError:
            control.close()
            raise
        self._servers = [control, report]
        self.tcp_port, self.report_port = control.getsockname()[1], report.getsockname()[1]
        self._stop.clear()
        for target, server, name in ((self._serve_control, control, "control"),
                                     (self._serve_reports, report, "report")):
            thread = threading.Thread(target=target, args=(server,), name=f"xarm-emulator {name}", daemon=True)
            thread.start()
            self._threads.append(thread)
        return self.tcp_port, self.report_port

    def close(self) -> None:
        """Stop serving, close every socket and join both threads; safe to call twice."""
        self._stop.set()
        threads, self._threads = self._threads, []
        for thread in threads:
            thread.join(5.0)
        for sock in [*self._servers, *self._clients]:
            with contextlib.suppress(OSError):
                sock.close()
        self._servers, self._clients = [], []

    def __enter__(self) -> XArmTcpServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ fault injection
    def inject_report(self, kind: ReportFault, count: int = 1) -> None:
        """Spoil the next ``count`` reports: ``garbage`` sends random-looking bytes with an
        impossible length field, ``bad_values`` a well-framed report with a NaN pose,
        ``stall`` skips the report (a silent stream)."""
        with self._lock:
            self._report_faults.extend([kind] * count)

    def drop_clients(self) -> int:
        """Cut every control and report connection (a network glitch); returns how many."""
        with self._lock:
            clients = list(self._clients)
        for sock in clients:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
        return len(clients)

    # ------------------------------------------------------------------ control port
    def _track(self, sock: socket.socket | None) -> bool:
        if sock is None:
            return False
        with self._lock:
            if len(self._clients) >= 2 * MAX_CLIENTS:
                sock.close()
                return False
            self._clients.append(sock)
        return True

    def _forget(self, sock: socket.socket) -> None:
        with self._lock:
            if sock in self._clients:
                self._clients.remove(sock)
        with contextlib.suppress(OSError):
            sock.close()

    def _serve_control(self, server: socket.socket) -> None:
        sel = selectors.DefaultSelector()
        sel.register(server, selectors.EVENT_READ)
        buffers: dict[socket.socket, bytearray] = {}
        held: dict[socket.socket, bytes] = {}
        try:
            while not self._stop.is_set():
                for key, _ in sel.select(_POLL_S):
                    sock = key.fileobj
                    assert isinstance(sock, socket.socket)
                    if sock is server:
                        client = _accept(server)
                        if self._track(client) and client is not None:
                            buffers[client] = bytearray()
                            sel.register(client, selectors.EVENT_READ)
                        continue
                    if not self._serve_client(sock, buffers[sock], held):
                        sel.unregister(sock)
                        buffers.pop(sock, None)
                        held.pop(sock, None)
                        self._forget(sock)
        finally:
            sel.close()

    def _serve_client(self, sock: socket.socket, buffer: bytearray, held: dict[socket.socket, bytes]) -> bool:
        """Read and answer what one control client sent; False when the connection is over."""
        try:
            data = sock.recv(4096)
        except OSError:
            return False
        if not data or len(buffer) + len(data) > MAX_PENDING:
            return False
        buffer += data
        try:
            requests = read_requests(buffer)
        except ValueError:
            return False  # a stream out of step cannot be followed: end the connection
        return all(self._answer(sock, request, held) for request in requests)

    def _answer(self, sock: socket.socket, request: TcpCommand, held: dict[socket.socket, bytes]) -> bool:
        register = request.command.register
        self.transactions = [*self.transactions[-999:], request.transaction_id]
        try:
            flags, data = self.emulator.execute(request.command)
        except Exception:
            self.emulator.bad_requests += 1
            flags, data = FLAG_INVALID, b""
        frame = reply_bytes(request.transaction_id, request.protocol, register, flags, data)
        fault = self.emulator.take_fault(register)
        late = held.pop(sock, b"")
        if fault is not None and fault.kind == "lag":
            held[sock] = frame
            return self._send(sock, late) if late else True
        if fault is not None:
            frame = self._spoil(frame, fault.kind, fault.stall_s, request)
        return self._send(sock, late + frame) if late + frame else True

    def _spoil(self, frame: bytes, kind: str, stall_s: float, request: TcpCommand) -> bytes:
        """``frame`` as fault ``kind`` makes it (b"" = nothing is sent)."""
        if kind == "drop":
            return b""
        if kind == "stale_id":
            return reply_bytes(request.transaction_id - 1, request.protocol, frame[6], frame[7], frame[8:])
        if kind == "corrupt_crc":
            return frame[:2] + b"\x00\x07" + frame[4:]
        if kind == "truncate":
            return frame[: max(1, len(frame) // 2)]
        if kind == "stall" and self._stop.wait(stall_s):
            return b""
        return frame

    @staticmethod
    def _send(sock: socket.socket, data: bytes) -> bool:
        try:
            sock.sendall(data)
        except OSError:
            return False
        return True

    # ------------------------------------------------------------------ report port
    def _next_report(self) -> bytes:
        with self._lock:
            fault = self._report_faults.pop(0) if self._report_faults else None
        packet = rich_report(self.emulator.report_values())
        if fault == "stall":
            return b""
        if fault == "garbage":
            return b"\xde\xad\xbe\xef" + bytes(range(64))
        if fault == "bad_values":
            return packet[:35] + b"\x00\x00\xc0\x7f" + packet[39:]  # x = NaN (float32 LE)
        return packet

    def _serve_reports(self, server: socket.socket) -> None:
        period = 1.0 / self.report_hz
        clients: list[socket.socket] = []
        next_at = time.monotonic()
        while not self._stop.is_set():
            with contextlib.suppress(OSError, ValueError):
                ready, _, _ = select.select([server], [], [], max(0.0, next_at - time.monotonic()))
                if ready:
                    client = _accept(server)
                    if self._track(client) and client is not None:
                        clients.append(client)
            if time.monotonic() < next_at:
                continue
            next_at = max(next_at + period, time.monotonic() - period)  # fall behind by one period at most
            packet = self._next_report() if clients else b""
            for client in list(clients):
                if packet and not self._send(client, packet):
                    clients.remove(client)
                    self._forget(client)
            self.reports_sent += len(clients) if packet else 0
        for client in clients:
            self._forget(client)
