"""A relay in front of the SDK's server that also admits clients offering only ``foxglove.websocket.v1``.

foxglove-sdk speaks the protocol under the name ``foxglove.sdk.v1`` and refuses a handshake
without it; Lichtblick and Foxglove releases before the SDK offer the same protocol as
``foxglove.websocket.v1`` (ADR 0035). The relay renames it in the handshake (both ways) and
then copies bytes, with a bounded buffer each way: a client that does not read stops the
relay reading from the server, so the server's own bounded queue decides what is dropped.
"""

from __future__ import annotations

import contextlib
import selectors
import socket
import threading
import time
from dataclasses import dataclass, field

__all__ = ["LEGACY", "SDK", "SubprotocolRelay", "rename_offer", "rename_reply"]

#: The subprotocol the SDK speaks.
SDK = b"foxglove.sdk.v1"
#: The same protocol's earlier name.
LEGACY = b"foxglove.websocket.v1"
#: Largest handshake header accepted from either side, bytes.
MAX_HEADER_BYTES = 16 * 1024
#: Longest a client may take to send its handshake, s.
HANDSHAKE_TIMEOUT_S = 5.0
#: Bytes buffered toward one side before the relay stops reading from the other.
MAX_BUFFER_BYTES = 256 * 1024
#: Bytes read per receive call.
CHUNK_BYTES = 64 * 1024
_HEADER = b"sec-websocket-protocol:"


def rename_offer(request: bytes) -> tuple[bytes, bool]:
    """The client's handshake with ``foxglove.websocket.v1`` offered as ``foxglove.sdk.v1``.

    Args:
        request: The HTTP upgrade request's header, up to and including the blank line.

    Returns:
        The request to forward, and whether it was renamed (a client offering ``foxglove.sdk.v1``
        itself, or neither name, is forwarded unchanged and the server decides).
    """
    lines = request.split(b"\r\n")
    offers = [i for i, line in enumerate(lines) if line.lower().startswith(_HEADER)]
    offered = {p.strip() for i in offers for p in lines[i][len(_HEADER):].split(b",")}
    if SDK in offered or LEGACY not in offered:
        return request, False
    for i in offers:  # replace the legacy name where it was offered, keeping the other offers
        name, value = lines[i][:len(_HEADER)], lines[i][len(_HEADER):]
        lines[i] = name + b" " + b", ".join(SDK if p.strip() == LEGACY else p.strip() for p in value.split(b","))
    return b"\r\n".join(lines), True


def rename_reply(reply: bytes) -> bytes:
    """The server's handshake reply with the chosen ``foxglove.sdk.v1`` named ``foxglove.websocket.v1``."""
    lines = reply.split(b"\r\n")
    for i, line in enumerate(lines):
        if line.lower().startswith(_HEADER) and line[len(_HEADER):].strip() == SDK:
            lines[i] = line[:len(_HEADER)] + b" " + LEGACY
    return b"\r\n".join(lines)


@dataclass(eq=False)
class _Pair:
    """One client's two sockets and what each side has yet to be sent."""

    client: socket.socket
    opened_at: float
    server: socket.socket | None = None
    legacy: bool = False
    header: bytearray = field(default_factory=bytearray)  # the handshake still being read (client, then server)
    to_client: bytearray = field(default_factory=bytearray)
    to_server: bytearray = field(default_factory=bytearray)
    stage: str = "request"  # request -> reply -> open
    closing_since: float | None = None  # when one side closed: the rest is sent to the other, then both close


class SubprotocolRelay:
    """Listens on ``host:port`` and relays each connection to the SDK's server on ``host:upstream_port``.

    One thread serves every connection (non-blocking sockets, one selector); at most
    ``max_clients`` are open at once, more are closed at accept.

    Args:
        host: The address to listen on (the live view's loopback address).
        port: The user's port (0: any free port; see :attr:`port`).
        upstream_port: The SDK server's port on ``host``.
        max_clients: Most connections relayed at once.

    Raises:
        OSError: If ``host:port`` cannot be listened on.
    """

    def __init__(self, host: str, port: int, upstream_port: int, *, max_clients: int = 16) -> None:
        self._host, self._upstream = host, upstream_port
        self._max_clients = max_clients
        self._listener = socket.create_server((host, port))
        self._listener.setblocking(False)
        #: The port the relay listens on.
        self.port = int(self._listener.getsockname()[1])
        #: Connections refused because ``max_clients`` were open.
        self.refused = 0
        self._pairs: dict[socket.socket, _Pair] = {}
        self._registered: set[socket.socket] = set()  # the pairs' sockets the selector watches now
        self._selector = selectors.DefaultSelector()
        self._selector.register(self._listener, selectors.EVENT_READ)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="cellcal-liveview-relay", daemon=True)
        self._thread.start()

    @property
    def clients(self) -> int:
        """Connections open now."""
        return len({id(p) for p in self._pairs.values()})

    def close(self, timeout: float = 2.0) -> None:
        """Stop relaying, close every connection and the listener (waits at most ``timeout`` s). Idempotent."""
        self._stop.set()
        self._thread.join(timeout)

    # -------------------------------------------------------------- the loop
    def _serve(self) -> None:
        try:
            while not self._stop.is_set():
                for key, events in self._selector.select(timeout=0.05):
                    sock = key.fileobj
                    if sock is self._listener:
                        self._accept()
                    elif isinstance(sock, socket.socket) and sock in self._pairs:
                        self._service(self._pairs[sock], sock, events)
                self._expire_handshakes(time.monotonic())
        finally:
            for pair in {id(p): p for p in self._pairs.values()}.values():
                self._drop(pair)
            self._selector.close()
            self._listener.close()

    def _accept(self) -> None:
        try:
            client, _ = self._listener.accept()
        except (BlockingIOError, InterruptedError, ConnectionAbortedError):
            return
        if self.clients >= self._max_clients:
            self.refused += 1
            client.close()
            return
        client.setblocking(False)
        # the kernel's send buffer toward a client is bounded too (it grows to megabytes by itself)
        client.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, MAX_BUFFER_BYTES)
        pair = _Pair(client, time.monotonic())
        self._pairs[client] = pair
        self._selector.register(client, selectors.EVENT_READ)
        self._registered.add(client)

    def _service(self, pair: _Pair, sock: socket.socket, events: int) -> None:
        try:
            if events & selectors.EVENT_WRITE:
                self._flush(pair, sock)
            if events & selectors.EVENT_READ and sock in self._pairs:
                self._read(pair, sock)
        except OSError:  # a reset, a refused upstream: this connection ends, the others go on
            self._drop(pair)

    def _read(self, pair: _Pair, sock: socket.socket) -> None:
        data = sock.recv(CHUNK_BYTES)
        if not data:  # that side closed: the other gets what is buffered for it (e.g. an HTTP 400), then closes
            pair.closing_since = time.monotonic()
            self._interest(pair)
            return
        if pair.stage == "open" or (pair.stage == "reply" and sock is pair.client):
            # the other side's buffer: bounded, reading stops while it is full (see _interest)
            (pair.to_server if sock is pair.client else pair.to_client).extend(data)
        else:
            self._handshake(pair, sock, data)
            if pair.stage == "closed":
                return
        self._interest(pair)

    def _handshake(self, pair: _Pair, sock: socket.socket, data: bytes) -> None:
        pair.header.extend(data)
        end = pair.header.find(b"\r\n\r\n")
        if end < 0:
            if len(pair.header) > MAX_HEADER_BYTES:  # a header that never ends is not a handshake
                self._drop(pair)
            return
        head, rest = bytes(pair.header[:end + 4]), bytes(pair.header[end + 4:])
        pair.header.clear()
        if pair.stage == "request":  # the client's request (no server side exists yet)
            head, pair.legacy = rename_offer(head)
            pair.server = socket.create_connection((self._host, self._upstream), timeout=HANDSHAKE_TIMEOUT_S)
            pair.server.setblocking(False)
            self._pairs[pair.server] = pair
            self._selector.register(pair.server, selectors.EVENT_READ)
            self._registered.add(pair.server)
            pair.to_server.extend(head + rest)
            pair.stage = "reply"
        else:  # the server's reply (the client's bytes meanwhile went straight to to_server)
            pair.to_client.extend((rename_reply(head) if pair.legacy else head) + rest)
            pair.stage = "open"

    def _flush(self, pair: _Pair, sock: socket.socket) -> None:
        buf = pair.to_client if sock is pair.client else pair.to_server
        if buf:
            sent = sock.send(buf)
            del buf[:sent]
        self._interest(pair)

    def _interest(self, pair: _Pair) -> None:
        """Read a side only while the buffer toward the other side has room; write a side with data for it.

        Once a side has closed nothing more is read; the pair is dropped when what was buffered is sent.
        """
        if pair.closing_since is not None and not (pair.to_client or pair.to_server):
            self._drop(pair)
            return
        for sock, incoming, outgoing in ((pair.client, pair.to_client, pair.to_server),
                                         (pair.server, pair.to_server, pair.to_client)):
            if sock is None or sock not in self._pairs:
                continue
            mask = selectors.EVENT_WRITE if incoming else 0
            if len(outgoing) < MAX_BUFFER_BYTES and pair.closing_since is None:
                mask |= selectors.EVENT_READ
            if mask and sock in self._registered:
                self._selector.modify(sock, mask)
            elif mask:
                self._selector.register(sock, mask)
                self._registered.add(sock)
            elif sock in self._registered:  # nothing to send it, no room for what it sends: wait for the other side
                self._selector.unregister(sock)
                self._registered.discard(sock)

    def _expire_handshakes(self, now: float) -> None:
        for pair in {id(p): p for p in self._pairs.values()}.values():
            if pair.stage != "open" and now - pair.opened_at > HANDSHAKE_TIMEOUT_S:
                self._drop(pair)
            elif pair.closing_since is not None and now - pair.closing_since > HANDSHAKE_TIMEOUT_S:
                self._drop(pair)  # the rest could not be delivered in time

    def _drop(self, pair: _Pair) -> None:
        pair.stage = "closed"
        for sock in (pair.client, pair.server):
            if sock is None:
                continue
            self._pairs.pop(sock, None)
            if sock in self._registered:
                self._registered.discard(sock)
                with contextlib.suppress(KeyError, ValueError, OSError):
                    self._selector.unregister(sock)
            sock.close()
