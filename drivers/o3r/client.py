"""PCIC client over TCP (:class:`PcicStream`): a background reader, commands with replies, reconnect with backoff."""

from __future__ import annotations

import collections
import contextlib
import json
import socket
import sys
import threading
import time
from dataclasses import dataclass

from cellcal.devices.errors import (
    CellcalError,
    ConfigError,
    DeviceConnectionError,
    DeviceError,
    DeviceTimeoutError,
    ProtocolError,
    VendorError,
)
from cellcal.drivers.o3r_json import clip, show

from .inbox import DropLog, Inbox
from .link import Receiver, connect
from .pcic import (
    DEFAULT_MAX_PAYLOAD,
    HEADER_LEN,
    TICKET_ALGO_DEBUG,
    TICKET_ASYNC_ERROR,
    TICKET_ASYNC_NOTIFICATION,
    TICKET_C,
    TICKET_IMAGE,
    TICKET_P,
    TICKET_T,
    Chunk,
    check_payload,
    encode_message,
    parse_async_error,
    parse_header,
    parse_notification,
    walk_chunks,
)

#: Blob ids of the default O3R 3D schema.
DEFAULT_BLOBS = ("RADIAL_DISTANCE_COMPRESSED", "AMPLITUDE_COMPRESSED", "CONFIDENCE", "TOF_INFO")
#: Output mask: result data + async errors + notifications.
DEFAULT_MASK = 0x7
#: Default budget for replies and notifications held at once, bytes.
DEFAULT_MAX_BUFFERED = 1024 * 1024
#: Poll interval of the reader (how soon it notices close()), seconds.
_POLL_S = 0.05
#: Bytes kept of a message too large to hold (enough for a ticket, a code and a short text).
_KEEP_OF_SKIPPED = 512


def make_schema(blobs: tuple[str, ...] = DEFAULT_BLOBS) -> str:
    """The flexible-layouter PCIC schema selecting ``blobs`` between ``star`` and ``stop``."""
    elements = [{"type": "string", "value": "star", "id": "start_string"}]
    elements += [{"type": "blob", "id": b} for b in blobs]
    elements.append({"type": "string", "value": "stop", "id": "end_string"})
    return json.dumps({"layouter": "flexible", "format": {"dataencoding": "ascii"}, "elements": elements},
                      separators=(",", ":"))


@dataclass(frozen=True)
class RawFrame:
    """A validated image payload as received.

    Attributes:
        payload: The whole payload (ticket .. CR LF); owned by this frame.
        chunks: Its chunk table.
        offset: Stream offset of ``payload[0]`` (per connection).
        received_mono: ``time.monotonic()`` when it was complete.
        received_epoch: ``time.time()`` when it was complete.
        generation: Connection generation it arrived on.
    """

    payload: bytearray
    chunks: list[Chunk]
    offset: int
    received_mono: float
    received_epoch: float
    generation: int


class PcicStream:
    """A PCIC connection to one O3R port with a background reader.

    One reader thread owns the receiving side of the socket. It reads image messages
    into freshly allocated buffers of the (checked, capped) announced length, the only
    copy of the pixel data, validates them (:func:`walk_chunks`) and keeps the newest
    one. Everything else is bounded by ``max_buffered_bytes``: command replies are kept
    (their first bytes) only for the tickets this client sends, notifications FIFO
    within the budget, and a message larger than the budget is read through a fixed
    buffer and dropped; drops are counted (:attr:`drops`) and logged. Async errors
    (ticket 0001) and protocol violations are queued and raised by the next call that
    waits for data.

    Link faults: a dropped connection, or a message that stops arriving for longer than
    ``io_timeout_s`` (a stall), closes the socket and the reader reconnects with
    exponential backoff, re-sending the schema (``c``) and output mask (``p``). A
    protocol violation is reported once (``ProtocolError`` naming the stream offset)
    and the reader reconnects, because a byte stream cannot be re-synchronised safely.
    An unexpected exception in the reader is reported the same way as a ``DeviceError``;
    if the reader itself ends on one, every later call raises it.

    Args:
        host: VPU address.
        port: PCIC TCP port (1..65535).
        io_timeout_s: A message that makes no progress for this long is a stall; also
            the timeout of a send.
        connect_timeout_s: TCP connect timeout per attempt.
        backoff_s: First reconnect delay; doubles up to ``backoff_max_s``.
        backoff_max_s: Longest reconnect delay.
        max_payload: Cap on an announced payload length, bytes.
        max_buffered_bytes: Budget for replies and notifications together, bytes.
        schema: PCIC schema JSON sent with ``c`` after each connect.
        mask: Output mask sent with ``p``.

    Raises:
        ConfigError: If ``port`` is not an integer in 1..65535.
    """

    def __init__(self, host: str, port: int, *, io_timeout_s: float = 2.0, connect_timeout_s: float = 2.0,
                 backoff_s: float = 0.1, backoff_max_s: float = 2.0, max_payload: int = DEFAULT_MAX_PAYLOAD,
                 max_buffered_bytes: int = DEFAULT_MAX_BUFFERED, schema: str | None = None,
                 mask: int = DEFAULT_MASK) -> None:
        if not isinstance(port, int) or isinstance(port, bool) or not 1 <= port <= 65535:
            raise ConfigError(f"O3R PCIC port must be an integer in 1..65535, got {show(port)}")
        self.host = host
        self.port = port
        self.io_timeout_s = io_timeout_s
        self.connect_timeout_s = connect_timeout_s
        self.backoff_s = backoff_s
        self.backoff_max_s = backoff_max_s
        self.max_payload = max_payload
        self.schema = make_schema() if schema is None else schema
        self.mask = mask
        self.where = f"O3R PCIC {host}:{port}"
        self.drops = DropLog(self.where)
        self._inbox = Inbox(max_buffered_bytes, (TICKET_C, TICKET_T, TICKET_P), self.drops)
        self._cond = threading.Condition()
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._receiver = Receiver(self._stop, io_timeout_s)
        self._sock: socket.socket | None = None
        self._generation = 0
        self._ready_generation = 0
        self._newest: RawFrame | None = None
        self._frames_received = 0
        self._pending: collections.deque[CellcalError] = collections.deque(maxlen=16)
        self._fatal: CellcalError | None = None
        self._link_error = "not connected yet"
        self._thread: threading.Thread | None = None
        self._stream_pos = 0
        self.reconnects = 0

    # ------------------------------------------------------------------ life cycle
    def start(self, timeout: float) -> PcicStream:
        """Start the reader and wait until the first connection is set up.

        Raises:
            DeviceConnectionError: If no connection is set up within ``timeout``.
            ProtocolError: If the port answers, but not as PCIC.
            DeviceError: If the device refuses the schema or output mask.
        """
        self._thread = threading.Thread(target=self._run, name=f"o3r-pcic-{self.port}", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + timeout
        error: CellcalError | None = None
        with self._cond:
            while self._ready_generation == 0:
                if self._fatal is not None or self._pending:
                    error = self._fatal or self._pending.popleft()
                    break
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    error = DeviceConnectionError(f"{self.where}: not set up within {timeout:.3g} s "
                                                  f"({self._link_error})")
                    break
                self._cond.wait(remaining)
        if error is not None:
            self.close()
            raise error
        return self

    def close(self) -> None:
        """Stop the reader, close the socket and join the thread."""
        self._stop.set()
        sock = self._sock
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout=5.0)
        self._thread = None
        with self._cond:
            self._cond.notify_all()

    @property
    def connected(self) -> bool:
        """Whether a connection is up and set up."""
        with self._cond:
            return self._sock is not None and self._ready_generation == self._generation

    @property
    def frames_received(self) -> int:
        """Image messages received so far."""
        return self._frames_received

    @property
    def notifications(self) -> list[tuple[str, str]]:
        """Notifications held (oldest first, within the byte budget) as (9-digit id, JSON text)."""
        with self._cond:
            return self._inbox.notifications

    @property
    def buffered_bytes(self) -> int:
        """Bytes held for replies and notifications now."""
        with self._cond:
            return self._inbox.used_bytes

    # ------------------------------------------------------------------ reader
    def _run(self) -> None:
        try:
            self._loop()
        except Exception as exc:  # the reader must not end silently: every later call raises this
            error = DeviceError(f"{self.where}: the reader stopped on {type(exc).__name__}: {show(str(exc))}")
            with self._cond:
                self._fatal = error
                self._cond.notify_all()
        finally:
            self._drop("closed", None, final=True)

    def _loop(self) -> None:
        backoff = self.backoff_s
        while not self._stop.is_set():
            if self._sock is None:
                try:
                    self._open()
                    backoff = self.backoff_s
                except OSError as exc:
                    self._link_error = f"connect failed: {exc.strerror or exc}"
                    self._stop.wait(backoff)
                    backoff = min(backoff * 2.0, self.backoff_max_s)
                    continue
            try:
                self._read_one()
            except ProtocolError as exc:
                self._drop(f"protocol error: {exc}", exc)
            except DeviceTimeoutError as exc:  # a stall mid-message
                self._drop(str(exc))
            except OSError as exc:
                if not self._stop.is_set():
                    self._drop(f"connection lost: {exc.strerror or exc}")
            except EOFError:
                self._drop("connection closed by the device")
            except Exception as exc:  # an input nobody foresaw: typed, reported once, then reconnect
                self._drop(f"unexpected {type(exc).__name__}", DeviceError(
                    f"{self.where}: unexpected {type(exc).__name__} at stream offset {self._stream_pos}: "
                    f"{show(str(exc))}"))

    def _open(self) -> None:
        sock = connect(self.host, self.port, self.connect_timeout_s, self._stop, _POLL_S)
        with self._cond:
            self._sock = sock
            self._generation += 1
            self._stream_pos = 0
            self._link_error = ("the port accepted the TCP connection but gave no PCIC reply to the schema and "
                                "output mask (is it a PCIC port?)")
        if self._generation > 1:
            self.reconnects += 1
        self._send(TICKET_C, b"c%09d%s" % (len(self.schema.encode()), self.schema.encode()))
        self._send(TICKET_P, b"p%X" % self.mask)

    def _drop(self, reason: str, error: CellcalError | None = None, *, final: bool = False) -> None:
        with self._cond:
            sock, self._sock = self._sock, None
            if not final:
                self._link_error = reason
            if error is not None:
                self._pending.append(error)
            self._cond.notify_all()
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.close()
        if not final and not self._stop.is_set():
            self._stop.wait(self.backoff_s)

    def _not_pcic(self, header: bytes) -> ProtocolError:
        """The error for a port whose first answer is not a PCIC header."""
        hint = "; that is HTTP: does the PCIC port point at the XML-RPC server?" if header[:5] == b"HTTP/" else ""
        return ProtocolError(f"{self.where} does not answer as PCIC: its first bytes are {show(header)}{hint}",
                             offset=0)

    def _read_header(self, sock: socket.socket) -> tuple[str, int] | None:
        header = bytearray(HEADER_LEN)
        if not self._receiver.fill(sock, memoryview(header), at_boundary=True, stream_pos=self._stream_pos):
            return None
        try:
            return parse_header(header, offset=self._stream_pos, max_payload=self.max_payload)
        except ProtocolError:
            if self._stream_pos == 0 and self._ready_generation != self._generation:
                raise self._not_pcic(bytes(header)) from None
            raise

    def _read_one(self) -> None:
        sock = self._sock
        assert sock is not None
        parsed = self._read_header(sock)
        if parsed is None:
            return
        ticket, length = parsed
        start = self._stream_pos + HEADER_LEN
        if ticket == TICKET_IMAGE or length <= self._inbox.max_bytes:
            payload = bytearray(length)
            self._receiver.fill(sock, memoryview(payload), at_boundary=False, stream_pos=start)
            self._stream_pos = start + length
            check_payload(payload, ticket, offset=start)
            head, whole = bytes(payload[:_KEEP_OF_SKIPPED]), True
        else:  # larger than everything we may hold: read it through a fixed buffer, keep its head
            head, tail = self._receiver.skip(sock, length, _KEEP_OF_SKIPPED, start)
            self._stream_pos = start + length
            check_payload(head[:4] + tail, ticket, offset=start)
            payload, whole = bytearray(), False
        if ticket == TICKET_IMAGE:
            self._keep_frame(payload, start)
        else:
            self._dispatch(ticket, payload if whole else None, head, length, start)

    def _keep_frame(self, payload: bytearray, start: int) -> None:
        chunks = walk_chunks(payload, offset=start)
        raw = RawFrame(payload, chunks, start, time.monotonic(), time.time(), self._generation)
        with self._cond:
            self._newest = raw
            self._frames_received += 1
            self._cond.notify_all()

    def _dispatch(self, ticket: str, payload: bytearray | None, head: bytes, length: int, start: int) -> None:
        """Handle a non-image message; ``payload`` is None when it was too large to hold (``head`` has its start)."""
        content = head[4:] if payload is None else payload[4:-2]
        with self._cond:
            if ticket == TICKET_ASYNC_ERROR:
                code, text = parse_async_error(content[:_KEEP_OF_SKIPPED], offset=start + 4)
                self._pending.append(VendorError("o3r", code, clip(text) or "async error"))
            elif ticket == TICKET_ASYNC_NOTIFICATION:
                if payload is None:
                    self.drops.drop("notification", length, "larger than the whole buffer budget")
                else:
                    ident, text = parse_notification(content, offset=start + 4)
                    self._inbox.notification(ident, text, sys.getsizeof(text) + len(ident))
            elif ticket == TICKET_ALGO_DEBUG:
                self.drops.drop("algo-debug message", length)
            elif self._inbox.reply(ticket, content, length):
                self._on_reply(ticket, bytes(content[:1]))
            self._cond.notify_all()

    def _on_reply(self, ticket: str, code: bytes) -> None:
        """React to the reply code of the setup commands (called with the lock held)."""
        if ticket == TICKET_P:
            if code == b"*":
                self._ready_generation = self._generation
            else:
                self._pending.append(DeviceError(f"O3R rejected output mask 'p{self.mask:X}' with {code!r}"))
        elif ticket == TICKET_C and code != b"*":
            self._pending.append(DeviceError(f"O3R rejected the PCIC schema with {code!r}"))

    # ------------------------------------------------------------------ sending
    def _send(self, ticket: str, content: bytes) -> None:
        sock = self._sock
        if sock is None:
            raise OSError("not connected")
        data = encode_message(ticket, content)
        with self._send_lock:
            sock.settimeout(self.io_timeout_s)
            try:
                sock.sendall(data)
            finally:
                sock.settimeout(_POLL_S)

    def _raise_pending(self) -> None:
        if self._fatal is not None:
            raise self._fatal
        if self._pending:
            raise self._pending.popleft()

    def _timeout_error(self, what: str, timeout: float) -> CellcalError:
        if self._sock is None:
            return DeviceConnectionError(f"O3R PCIC {self.host}:{self.port}: {what} within {timeout:g} s; "
                                         f"link down ({self._link_error}), reconnecting")
        return DeviceTimeoutError(f"O3R PCIC {self.host}:{self.port}: {what} within {timeout:g} s")

    # ------------------------------------------------------------------ public
    def next_frame(self, timeout: float, newer_than: float) -> RawFrame:
        """The newest frame received after ``newer_than`` (monotonic s) and within ``timeout``.

        Raises:
            VendorError / ProtocolError / DeviceError: Queued async or protocol errors.
            DeviceTimeoutError: No fresh frame in time (link up).
            DeviceConnectionError: No fresh frame in time and the link is down.
        """
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                self._raise_pending()
                now = time.monotonic()
                raw = self._newest
                if raw is not None and raw.received_mono > newer_than and now - raw.received_mono <= timeout:
                    return raw
                if now >= deadline:
                    raise self._timeout_error("no fresh frame", timeout)
                self._cond.wait(deadline - now)

    def trigger(self, timeout: float) -> RawFrame:
        """Software-trigger one frame (port in IDLE) and return it.

        Re-sends the trigger after a reconnect while time remains.

        Raises:
            DeviceError: The device refused the trigger (port not in IDLE).
            VendorError / ProtocolError: Queued async or protocol errors.
            DeviceTimeoutError / DeviceConnectionError: As for :meth:`next_frame`.
        """
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                self._raise_pending()
                now = time.monotonic()
                if now >= deadline:
                    raise self._timeout_error("no triggered frame", timeout)
                if self._sock is None or self._ready_generation != self._generation:
                    self._cond.wait(deadline - now)
                    continue
                gen = self._generation
                mark = self._inbox.reply_counter
                sent_at = time.monotonic()
                try:
                    self._send(TICKET_T, b"t")
                except OSError:
                    self._cond.wait(min(0.05, max(deadline - time.monotonic(), 0)))
                    continue
                replied = False
                while True:
                    self._raise_pending()
                    reply = self._inbox.replies.get(TICKET_T)
                    if not replied and reply is not None and reply[0] > mark:
                        replied = True
                        if reply[1][:1] != b"*":
                            raise DeviceError(f"O3R refused the software trigger with {reply[1][:1]!r} "
                                              f"(is the port in IDLE?)")
                    raw = self._newest
                    if replied and raw is not None and raw.received_mono > sent_at and raw.generation == gen:
                        return raw
                    if self._generation != gen or self._sock is None:
                        break  # link went down: trigger again on the next connection
                    now = time.monotonic()
                    if now >= deadline:
                        raise self._timeout_error("no triggered frame", timeout)
                    self._cond.wait(deadline - now)
