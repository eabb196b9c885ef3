"""One request/reply transaction at a time over a serial line (pyserial, imported lazily).

The transport owns the port and the retry policy: only idempotent reads
(:data:`~.registers.READ_REGISTERS`) are sent again after a bad, foreign or missing reply;
every other request, above all a motion command, is sent exactly once (ADR 0016). The
serial protocol echoes no register and carries no transaction id, so a reply belongs to
its request only if it comes in time, alone, and with the data length that register
answers with; anything else puts the line out of step, and the transport resynchronises
(waits for a quiet line, flushes) before it sends again.
"""

from __future__ import annotations

import contextlib
import threading
import time
from typing import Any

from cellcal.devices.errors import (
    DeviceConnectionError,
    DeviceTimeoutError,
    MissingDependencyError,
    ProtocolError,
)

from .protocol import FrameSplitter, Reply, encode_request, parse_reply
from .registers import READ_REGISTERS, Reg


def register_name(register: int) -> str:
    """``21 (MOVE_LINE)`` for messages."""
    try:
        return f"{register} ({Reg(register).name})"
    except ValueError:
        return str(register)


class SerialTransport:
    """Request/reply link to an xArm controller.

    Args:
        port: Serial device path (``/dev/ttyUSB0``, a pty) or a pyserial URL
            (``loop://`` in tests).
        baudrate: Line speed, baud (8N1).
        reply_timeout_s: Seconds to wait for each reply of a read before trying again,
            and the default wait for the one reply of any other request.
        retries: Extra attempts of a read after a failed one (bad CRC, foreign reply,
            no reply); other requests are never retried.

    Attributes:
        stats: Counters of ``requests``, ``retries``, ``bad_frames`` (garbled or foreign
            replies), ``timeouts``, ``resyncs`` and ``stale_bytes`` (bytes that came
            when no request was waiting).
    """

    def __init__(self, port: str, baudrate: int = 2_000_000, *, reply_timeout_s: float = 0.5,
                 retries: int = 2):
        self.port = port
        self.baudrate = baudrate
        self.reply_timeout_s = reply_timeout_s
        self.retries = retries
        self.quiet_s = min(reply_timeout_s, 0.05)  # a line silent this long is taken as in step
        self._serial: Any = None
        self._lock = threading.Lock()
        self._out_of_step = False
        self.stats = {"requests": 0, "retries": 0, "bad_frames": 0, "timeouts": 0, "resyncs": 0, "stale_bytes": 0}

    @property
    def is_open(self) -> bool:
        """Whether the port is open."""
        return self._serial is not None

    def open(self) -> None:
        """Open the port.

        Raises:
            MissingDependencyError: If pyserial is not installed.
            DeviceConnectionError: If the port cannot be opened.
        """
        try:
            import serial
        except ImportError as exc:  # pragma: no cover - pyserial is a declared extra
            raise MissingDependencyError("pyserial", "xarm") from exc
        if self._serial is not None:
            return
        try:
            self._serial = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=0.01,
                                                 write_timeout=max(self.reply_timeout_s, 0.1))
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceConnectionError(f"xarm: cannot open serial port {self.port!r}: {exc}") from None

    def close(self) -> None:
        """Close the port; safe to call more than once."""
        ser, self._serial = self._serial, None
        if ser is not None:
            with contextlib.suppress(Exception):  # closing must not raise
                ser.close()

    # ------------------------------------------------------------------ I/O
    def _io_error(self, what: str, exc: Exception) -> DeviceConnectionError:
        return DeviceConnectionError(f"xarm: {what} {self.port!r} failed: {exc}")

    def _write(self, frame: bytes, limit: float) -> None:
        """Send one request on a line in step: stray input first makes the line resynchronise."""
        try:
            stray = int(self._serial.in_waiting)
        except Exception as exc:
            raise self._io_error("read from", exc) from None
        if stray:
            self.stats["stale_bytes"] += stray
            self._out_of_step = True
        if self._out_of_step:
            self._resync(limit)
        try:
            self._serial.reset_input_buffer()
            self._serial.write(frame)
            self._serial.flush()
        except Exception as exc:
            raise self._io_error("write to", exc) from None

    def _resync(self, limit: float) -> None:
        """Discard input until the line has been quiet for :attr:`quiet_s` (or ``limit`` passes), then flush."""
        self.stats["resyncs"] += 1
        try:
            while True:
                remaining = limit - time.monotonic()
                if remaining <= 0:
                    break
                self._serial.timeout = min(self.quiet_s, remaining)
                if not self._serial.read(256):
                    self._out_of_step = False
                    break
            self._serial.reset_input_buffer()
        except Exception as exc:
            raise self._io_error("read from", exc) from None

    def _read_reply(self, deadline: float, expect_len: int | None, register: int) -> Reply | None:
        """The one reply to ``register``, or None when the deadline passes.

        Raises:
            ProtocolError: On a garbled frame, a reply of another length than ``register``
                answers with (a stale or foreign reply), or more than one frame.
        """
        splitter = FrameSplitter.for_replies()
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                if splitter.pending or splitter.skipped:
                    raise ProtocolError(f"xarm: incomplete or garbled reply ({splitter.pending} bytes pending, "
                                        f"{splitter.skipped} skipped)", offset=splitter.pending)
                return None
            try:
                self._serial.timeout = min(remaining, 0.05)
                waiting = self._serial.in_waiting
                chunk = self._serial.read(max(1, min(waiting, 64)))
            except Exception as exc:
                raise self._io_error("read from", exc) from None
            if not chunk:
                continue
            frames = splitter.feed(chunk)
            if frames:
                reply = parse_reply(frames[0])
                if len(frames) > 1 or splitter.pending:
                    raise ProtocolError("xarm: more than one reply frame came for one request (a stale reply "
                                        "is on the line)")
                if expect_len is not None and len(reply.data) != expect_len:
                    raise ProtocolError(f"xarm: a reply of {len(reply.data)} data bytes does not belong to register "
                                        f"{register_name(register)}, which answers with {expect_len} (stale or "
                                        "foreign reply)", offset=4)
                return reply

    def _reply_deadline(self, attempts: int, overall: float, total: float) -> float:
        """When to give up waiting for the reply just sent (a resynchronisation before it does not count)."""
        sent_at = time.monotonic()
        if attempts > 1:
            return min(overall, sent_at + self.reply_timeout_s)
        return max(overall, sent_at + min(total, self.reply_timeout_s))

    def transact(self, register: int, params: bytes = b"", *, expect_len: int | None = None,
                 timeout: float | None = None) -> Reply:
        """Send one request and return its reply; reads are retried on a bad or missing reply.

        Args:
            register: Register number.
            params: Parameter bytes.
            expect_len: Number of data bytes the reply must carry (None: any).
            timeout: Overall seconds. For a read, all attempts together; None means
                ``(reply_timeout_s + quiet_s) * (retries + 1)`` (each attempt may need a
                resynchronisation). For any other request, the wait for its one reply
                and a resynchronisation; None means ``reply_timeout_s + quiet_s``.

        Raises:
            DeviceConnectionError: If the port is closed or fails.
            ProtocolError: If the (last) reply was garbled, foreign or stale.
            DeviceTimeoutError: If no reply came.
        """
        frame = encode_request(register, params)
        attempts = self.retries + 1 if register in READ_REGISTERS else 1
        total = (self.reply_timeout_s + self.quiet_s) * attempts if timeout is None else timeout
        started = time.monotonic()
        overall = started + total
        last_error: ProtocolError | None = None
        made = 0
        timed_out = False  # an attempt of this request got no reply in time
        with self._lock:
            if self._serial is None:
                raise DeviceConnectionError(f"xarm: serial port {self.port!r} is not open")
            self.stats["requests"] += 1
            for attempt in range(attempts):
                now = time.monotonic()
                if attempt and now >= overall:
                    break
                if attempt:
                    self.stats["retries"] += 1
                made += 1
                self._write(frame, min(overall, now + self.reply_timeout_s))
                try:
                    reply = self._read_reply(self._reply_deadline(attempts, overall, total), expect_len, register)
                except ProtocolError as exc:
                    self.stats["bad_frames"] += 1
                    last_error = exc
                    self._out_of_step = True
                    self._resync(overall)
                    continue
                if reply is not None:
                    if timed_out:
                        # an earlier attempt timed out: its reply may still come after this one, so the
                        # next request first waits for a quiet line instead of meeting it as its own reply
                        self._out_of_step = True
                    return reply
                self.stats["timeouts"] += 1
                timed_out = True
                self._out_of_step = True  # a late reply may still be on its way
        sent = f"{made} attempts" if attempts > 1 else "sent once, not retried"
        if last_error is not None:
            raise ProtocolError(f"xarm register {register_name(register)}: {last_error} ({sent})")
        raise DeviceTimeoutError(f"xarm register {register_name(register)}: no reply within "
                                 f"{time.monotonic() - started:.2g} s ({sent})")
