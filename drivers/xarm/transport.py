"""One request/reply transaction at a time over a serial line (pyserial, imported lazily).

The transport owns the port and the retry policy and nothing else: it retries a bounded
number of times on a bad CRC, a malformed frame, a reply of the wrong length or no reply.
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


class SerialTransport:
    """Request/reply link to an xArm controller.

    Args:
        port: Serial device path (``/dev/ttyUSB0``, a pty) or a pyserial URL
            (``loop://`` in tests).
        baudrate: Line speed, baud (8N1).
        reply_timeout_s: Seconds to wait for each reply before retrying.
        retries: Extra attempts after a failed one (bad CRC, short frame, wrong
            length, no reply).

    Attributes:
        stats: Counters of ``requests``, ``retries``, ``bad_frames``, ``timeouts``.
    """

    def __init__(self, port: str, baudrate: int = 2_000_000, *, reply_timeout_s: float = 0.5,
                 retries: int = 2):
        self.port = port
        self.baudrate = baudrate
        self.reply_timeout_s = reply_timeout_s
        self.retries = retries
        self._serial: Any = None
        self._lock = threading.Lock()
        self.stats = {"requests": 0, "retries": 0, "bad_frames": 0, "timeouts": 0}

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
    def _write(self, frame: bytes) -> None:
        try:
            self._serial.reset_input_buffer()
            self._serial.write(frame)
            self._serial.flush()
        except Exception as exc:
            raise DeviceConnectionError(f"xarm: write to {self.port!r} failed: {exc}") from None

    def _read_reply(self, deadline: float, expect_len: int | None) -> Reply | None:
        """One reply, or None when the deadline passes. Raises ProtocolError on a bad one."""
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
                raise DeviceConnectionError(f"xarm: read from {self.port!r} failed: {exc}") from None
            if not chunk:
                continue
            frames = splitter.feed(chunk)
            if frames:
                reply = parse_reply(frames[0])
                if expect_len is not None and len(reply.data) != expect_len:
                    raise ProtocolError(f"xarm: reply carries {len(reply.data)} data bytes, expected {expect_len}",
                                        offset=4)
                return reply

    def _drain(self, quiet_s: float = 0.02) -> None:
        """After a retry, discard late duplicates until the line has been quiet for ``quiet_s``."""
        limit = time.monotonic() + self.reply_timeout_s
        try:
            self._serial.timeout = quiet_s
            while time.monotonic() < limit and self._serial.read(256):
                pass
        except Exception as exc:
            raise DeviceConnectionError(f"xarm: read from {self.port!r} failed: {exc}") from None

    def transact(self, register: int, params: bytes = b"", *, expect_len: int | None = None,
                 timeout: float | None = None) -> Reply:
        """Send one request and return its reply, retrying on bad or missing replies.

        Args:
            register: Register number.
            params: Parameter bytes.
            expect_len: Number of data bytes the reply must carry (None: any).
            timeout: Overall seconds for all attempts; None means
                ``reply_timeout_s * (retries + 1)``.

        Raises:
            DeviceConnectionError: If the port is closed or fails.
            ProtocolError: If every attempt got a malformed reply (the last error).
            DeviceTimeoutError: If no attempt got any reply.
        """
        frame = encode_request(register, params)
        total = self.reply_timeout_s * (self.retries + 1) if timeout is None else timeout
        overall = time.monotonic() + total
        last_error: ProtocolError | None = None
        with self._lock:
            if self._serial is None:
                raise DeviceConnectionError(f"xarm: serial port {self.port!r} is not open")
            self.stats["requests"] += 1
            for attempt in range(self.retries + 1):
                now = time.monotonic()
                if now >= overall:
                    break
                if attempt:
                    self.stats["retries"] += 1
                self._write(frame)
                deadline = min(overall, now + self.reply_timeout_s)
                try:
                    reply = self._read_reply(deadline, expect_len)
                except ProtocolError as exc:
                    self.stats["bad_frames"] += 1
                    last_error = exc
                    continue
                if reply is not None:
                    if attempt:
                        self._drain()
                    return reply
                self.stats["timeouts"] += 1
        if last_error is not None:
            raise ProtocolError(f"xarm register {register}: {last_error} (after {self.retries + 1} attempts)")
        raise DeviceTimeoutError(f"xarm register {register}: no reply within {total:.3g} s "
                                 f"({self.retries + 1} attempts)")
