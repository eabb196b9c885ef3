"""One HTTP POST bounded as a whole: connect, send and the full response within one deadline, capped in size.

The stdlib's per-read socket timeout lets a server that trickles bytes hold a call forever;
here every read gets the time left until one deadline and every byte counts against one cap.
``http.client`` still parses the status line, headers and chunked bodies (ADR 0015).
"""

from __future__ import annotations

import http.client
import io
import socket
import time
from dataclasses import dataclass

from cellcal.devices.errors import CellcalError, DeviceConnectionError, DeviceTimeoutError, ProtocolError

#: Bytes allowed for the status line and headers on top of the body cap.
HEADER_ALLOWANCE = 64 * 1024


@dataclass(frozen=True)
class _Limits:
    """The bounds of one exchange and the words for breaking them."""

    where: str
    timeout_s: float
    deadline: float
    max_bytes: int

    def expired(self) -> DeviceTimeoutError:
        return DeviceTimeoutError(f"{self.where}: no complete answer within {self.timeout_s:g} s")

    def too_large(self) -> ProtocolError:
        return ProtocolError(f"{self.where}: the reply exceeds the cap of {self.max_bytes} bytes")

    def remaining(self) -> float:
        """Seconds left; raises the timeout error when none are."""
        left = self.deadline - time.monotonic()
        if left <= 0:
            raise self.expired()
        return left


class _BoundedRaw(io.RawIOBase):
    """Socket reads that stop at the deadline and after the byte budget (body cap + header allowance)."""

    def __init__(self, sock: socket.socket, limits: _Limits) -> None:
        super().__init__()
        self._sock = sock
        self._limits = limits
        self._budget = limits.max_bytes + HEADER_ALLOWANCE
        self.received = 0

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: memoryview) -> int:  # type: ignore[override]
        self._sock.settimeout(self._limits.remaining())
        # never read more than one byte past the budget: the cap bounds memory, not just the result
        want = min(len(buffer), self._budget + 1 - self.received)
        if want <= 0:
            raise self._limits.too_large()
        try:
            n = self._sock.recv_into(buffer, want)
        except TimeoutError:
            raise self._limits.expired() from None
        self.received += n
        if self.received > self._budget:
            raise self._limits.too_large()
        return n


class _SocketShim:
    """What :class:`http.client.HTTPResponse` needs from a socket: ``makefile('rb')``."""

    def __init__(self, raw: _BoundedRaw) -> None:
        self._raw = raw

    def makefile(self, mode: str) -> io.BufferedReader:
        return io.BufferedReader(self._raw, buffer_size=8192)


def _read_body(resp: http.client.HTTPResponse, limits: _Limits) -> bytes:
    """The body, at most ``max_bytes`` (chunked, length-delimited or until close)."""
    if resp.length is not None and resp.length > limits.max_bytes:
        raise limits.too_large()
    body = resp.read(limits.max_bytes + 1)
    if len(body) > limits.max_bytes:
        raise limits.too_large()
    return body


def post(host: str, port: int, path: str, body: bytes, *, timeout_s: float, max_bytes: int, where: str,
         content_type: str = "text/xml") -> tuple[int, str, bytes]:
    """POST ``body`` and return ``(status, reason, response body)``, all within ``timeout_s``.

    Args:
        host: Server address.
        port: TCP port.
        path: Request path.
        body: Request body.
        timeout_s: Deadline of the whole exchange (connect + send + full response), seconds.
        max_bytes: Cap on the response body, bytes (headers get :data:`HEADER_ALLOWANCE` more).
        where: Names the call in error messages.
        content_type: Request content type.

    Raises:
        DeviceTimeoutError: The exchange did not finish in time.
        ProtocolError: The response exceeded the cap (nothing beyond it was read), or its status
            line, headers, chunking or content encoding are malformed.
        DeviceConnectionError: Connection refused, reset or unreachable.
    """
    limits = _Limits(where, timeout_s, time.monotonic() + timeout_s, max_bytes)
    try:
        return _exchange(host, port, path, body, limits, content_type)
    except CellcalError:
        raise
    except http.client.RemoteDisconnected:
        raise DeviceConnectionError(f"{where}: the device closed the connection without an answer") from None
    except (http.client.HTTPException, ValueError) as exc:
        detail = str(exc).encode("unicode_escape").decode("ascii")[:80]
        raise ProtocolError(f"{where}: malformed HTTP answer ({type(exc).__name__}: {detail})") from None
    except TimeoutError:
        raise limits.expired() from None
    except OSError as exc:
        raise DeviceConnectionError(f"{where}: cannot reach the device ({exc.strerror or exc})") from None


def _exchange(host: str, port: int, path: str, body: bytes, limits: _Limits,
              content_type: str) -> tuple[int, str, bytes]:
    head = (f"POST {path} HTTP/1.1\r\nHost: {host}:{port}\r\nUser-Agent: cellcal\r\n"
            f"Content-Type: {content_type}\r\nContent-Length: {len(body)}\r\nAccept-Encoding: identity\r\n"
            f"Connection: close\r\n\r\n").encode("ascii")
    sock = socket.create_connection((host, port), timeout=limits.remaining())
    try:
        sock.settimeout(limits.remaining())  # since Python 3.5 the timeout bounds the whole sendall
        sock.sendall(head + body)
        resp = http.client.HTTPResponse(_SocketShim(_BoundedRaw(sock, limits)))  # type: ignore[arg-type]
        resp.begin()
        encoding = (resp.getheader("Content-Encoding") or "identity").strip().lower()
        if encoding != "identity":
            raise http.client.HTTPException(f"unsupported Content-Encoding {encoding[:40]!r}")
        return resp.status, resp.reason[:80], _read_body(resp, limits)
    finally:
        sock.close()
