"""One request/reply transaction at a time over the xArm's TCP control port (502).

Same policy as the serial transport (ADR 0016): only idempotent reads
(:data:`~.registers.READ_REGISTERS`) are sent again after a bad, missing or lost reply;
every other request goes out once. TCP adds what the serial line lacks: every request
carries a fresh transaction id and the reply echoes it with the register, so a late
reply to an earlier request (a *stale* one) is recognised, counted and dropped instead of
being taken for the current one. A dead connection is opened again, with backoff,
before a request is sent — never to repeat one that was sent.
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections import deque

from cellcal.devices.errors import DeviceConnectionError, DeviceTimeoutError, ProtocolError

from .protocol import Reply
from .registers import READ_REGISTERS
from .tcp_protocol import (
    FEEDBACK_REGISTER,
    PROTOCOL_ID,
    TcpFrameSplitter,
    TcpReply,
    encode_tcp_request,
    next_transaction_id,
    parse_tcp_reply,
)
from .transport import register_name

#: First and largest pause between connection attempts, s (doubling in between).
BACKOFF_S = (0.05, 1.0)
_RECV_BYTES = 4096


class TcpTransport:
    """Request/reply link to an xArm controller over TCP.

    Args:
        host: Controller address.
        port: Control port (502 on a real controller).
        reply_timeout_s: Wait for each reply of a read before trying again, and the default
            wait for the one reply of any other request, s.
        retries: Extra attempts of a read after a failed one; other requests are never retried.
        connect_timeout_s: Bound of one connection attempt, s.

    Attributes:
        stats: Counters of ``requests``, ``retries``, ``timeouts``, ``stale_replies`` (replies
            carrying another request's transaction id, dropped), ``bad_frames``,
            ``feedback`` (unsolicited feedback messages, ignored), ``connects`` and
            ``connect_failures``.
    """

    def __init__(self, host: str, port: int = 502, *, reply_timeout_s: float = 0.5, retries: int = 2,
                 connect_timeout_s: float = 2.0):
        self.host = host
        self.port = port
        self.reply_timeout_s = reply_timeout_s
        self.retries = retries
        self.connect_timeout_s = connect_timeout_s
        self._sock: socket.socket | None = None
        self._splitter = TcpFrameSplitter()
        self._frames: deque[bytes] = deque()
        self._lock = threading.Lock()
        self._tid = 0
        self._opened = False
        self.stats = {"requests": 0, "retries": 0, "timeouts": 0, "stale_replies": 0, "bad_frames": 0,
                      "feedback": 0, "connects": 0, "connect_failures": 0}

    @property
    def where(self) -> str:
        """``host:port`` for messages."""
        return f"{self.host}:{self.port}"

    @property
    def is_open(self) -> bool:
        """Whether :meth:`open` was called (the socket itself may be re-opened on demand)."""
        return self._opened

    @property
    def last_transaction_id(self) -> int:
        """Id of the last request sent (0 before the first)."""
        return self._tid

    def open(self, timeout: float | None = None) -> None:
        """Connect, retrying with backoff until ``timeout`` (default ``connect_timeout_s``) passes.

        Raises:
            DeviceConnectionError: If no connection could be made in time.
        """
        with self._lock:
            self._opened = True
            self._ensure(time.monotonic() + (self.connect_timeout_s if timeout is None else timeout))

    def close(self) -> None:
        """Close the connection; safe to call more than once."""
        with self._lock:
            self._opened = False
            self._drop()

    # ------------------------------------------------------------------ connection
    def _drop(self) -> None:
        sock, self._sock = self._sock, None
        self._splitter.clear()
        self._frames.clear()
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.close()

    def _ensure(self, deadline: float) -> socket.socket:
        """The open socket, connecting (with backoff between attempts) until ``deadline``."""
        if self._sock is not None:
            return self._sock
        pause, last = BACKOFF_S[0], ""
        while True:
            budget = min(self.connect_timeout_s, deadline - time.monotonic())
            if budget > 0:
                try:
                    sock = socket.create_connection((self.host, self.port), timeout=budget)
                except OSError as exc:
                    self.stats["connect_failures"] += 1
                    last = str(exc) or type(exc).__name__
                else:
                    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                    self.stats["connects"] += 1
                    self._sock = sock
                    return sock
            if time.monotonic() + pause >= deadline:
                raise DeviceConnectionError(f"xarm: cannot connect to {self.where}: {last or 'no time left'}")
            time.sleep(pause)
            pause = min(2 * pause, BACKOFF_S[1])

    # ------------------------------------------------------------------ one attempt
    def _receive(self, register: int, tid: int, expect_len: int | None, deadline: float) -> Reply | None:
        """The reply carrying ``tid``, or None if the deadline passes; stale replies are dropped.

        Raises:
            ProtocolError: On a frame the stream cannot be read past, or a reply with this
                id that echoes another register or protocol or has the wrong data length.
            OSError: If the connection fails or the peer closes it.
        """
        sock = self._sock
        assert sock is not None
        while True:
            while self._frames:
                reply = self._match(parse_tcp_reply(self._frames.popleft()), register, tid, expect_len)
                if reply is not None:
                    return reply
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            sock.settimeout(remaining)
            try:
                chunk = sock.recv(_RECV_BYTES)
            except TimeoutError:
                return None
            if not chunk:
                raise ConnectionResetError("the controller closed the connection")
            self._frames.extend(self._splitter.feed(chunk))

    def _match(self, frame: TcpReply, register: int, tid: int, expect_len: int | None) -> Reply | None:
        """``frame``'s reply if it answers request ``tid``; None for a stale reply or a feedback message."""
        if frame.register == FEEDBACK_REGISTER and frame.transaction_id != tid:
            self.stats["feedback"] += 1
            return None
        if frame.transaction_id != tid:
            self.stats["stale_replies"] += 1  # a late reply to an earlier request: never this one's
            return None
        if frame.protocol != PROTOCOL_ID or frame.register != register:
            raise ProtocolError(f"xarm: reply {tid} echoes register {frame.register} / protocol {frame.protocol}, "
                                f"not {register_name(register)} / {PROTOCOL_ID}", offset=2)
        if expect_len is not None and len(frame.reply.data) != expect_len:
            raise ProtocolError(f"xarm: reply {tid} to {register_name(register)} carries {len(frame.reply.data)} "
                                f"data bytes, not {expect_len}", offset=4)
        return frame.reply

    # ------------------------------------------------------------------ transactions
    def transact(self, register: int, params: bytes = b"", *, expect_len: int | None = None,
                 timeout: float | None = None) -> Reply:
        """Send one request and return its reply; reads are retried on a bad, missing or lost reply.

        Args:
            register: Register number.
            params: Parameter bytes.
            expect_len: Number of data bytes the reply must carry (None: any).
            timeout: Overall seconds: for a read, all attempts (and reconnections) together,
                None meaning ``reply_timeout_s * (retries + 1)``; for any other request the
                connection (if needed) and its one reply, None meaning ``reply_timeout_s``.

        Raises:
            DeviceConnectionError: If the transport is closed, no connection could be made, or
                the connection failed while a non-read was under way (it is not sent again).
            ProtocolError: If the (last) reply was malformed or did not fit the request.
            DeviceTimeoutError: If no reply came.
        """
        is_read = register in READ_REGISTERS
        attempts = self.retries + 1 if is_read else 1
        total = self.reply_timeout_s * attempts if timeout is None else timeout
        started = time.monotonic()
        overall = started + total
        sent = "not retried" if not is_read else f"up to {attempts} attempts"
        with self._lock:
            if not self._opened:
                raise DeviceConnectionError(f"xarm: connection to {self.where} is not open")
            self.stats["requests"] += 1
            last: Exception | None = None
            attempt = 0
            while True:
                attempt += 1
                outcome = self._attempt(register, params, expect_len, is_read, attempt, attempts, overall, total)
                if isinstance(outcome, Reply):
                    return outcome
                last = outcome
                if attempt >= attempts or time.monotonic() >= overall:
                    break
                self.stats["retries"] += 1
        name = register_name(register)
        if isinstance(last, ProtocolError):
            raise ProtocolError(f"xarm register {name} at {self.where}: {last} ({sent})")
        if isinstance(last, DeviceConnectionError):
            raise DeviceConnectionError(f"xarm register {name} at {self.where}: {last} ({sent})")
        raise DeviceTimeoutError(f"xarm register {name} at {self.where}: no reply within "
                                 f"{time.monotonic() - started:.2g} s ({sent})")

    def _attempt(self, register: int, params: bytes, expect_len: int | None, is_read: bool, attempt: int,
                 attempts: int, overall: float, total: float) -> Reply | Exception:
        """One send and wait; returns the reply, or the error of this attempt (a read may try again).

        Raises:
            DeviceConnectionError: If a non-read may have reached the controller and its
                connection failed (it must not be sent again).
            ProtocolError: If a non-read's reply was malformed.
        """
        self._tid = next_transaction_id(self._tid)
        frame = encode_tcp_request(self._tid, register, params)
        now = time.monotonic()
        # The last attempt may use what is left; earlier ones get one reply's wait each.
        deadline = overall if attempt == attempts else min(overall, now + self.reply_timeout_s)
        if attempts == 1:
            deadline = max(overall, now + min(total, self.reply_timeout_s))
        try:
            sock = self._ensure(deadline)
        except DeviceConnectionError as exc:
            return DeviceConnectionError(f"{exc} (request not sent)")
        try:
            sock.settimeout(max(deadline - time.monotonic(), 0.001))
            sock.sendall(frame)
            reply = self._receive(register, self._tid, expect_len, deadline)
        except ProtocolError as exc:
            self.stats["bad_frames"] += 1
            self._drop()  # a byte stream out of step cannot be trusted again: new connection
            if not is_read:
                raise ProtocolError(f"xarm register {register_name(register)} at {self.where}: {exc} "
                                    "(not retried)") from None
            return exc
        except OSError as exc:
            self._drop()
            error = DeviceConnectionError(f"connection failed: {exc or type(exc).__name__}")
            if not is_read:
                raise DeviceConnectionError(f"xarm register {register_name(register)} at {self.where}: {error}; "
                                            "it may have reached the controller and is not sent again") from None
            return error
        if reply is None:
            self.stats["timeouts"] += 1
            partial = self._splitter.pending
            if partial:
                self._drop()  # part of a frame came and stopped: the stream is out of step
                return DeviceTimeoutError(f"no whole reply ({partial} bytes of one came)")
            return DeviceTimeoutError("no reply")
        return reply
