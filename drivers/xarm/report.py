"""The xArm's pushed state report (TCP port 30002, "rich"): parser and a bounded reader thread.

Layout (``shared/spec/protocols.md`` D2; offsets as the installed ``xarm-python-sdk``
reads them): u32 BE total length; byte 4 state (low nibble) and mode (high nibble);
u16 BE command count; 7 joint angles (f32 LE, rad); TCP pose x, y, z (mm), roll, pitch,
yaw (rad); 7 joint torques; bytes 87-90 brake bits, enable bits, error, warning; pose
offset, TCP load; bytes 131-132 collision and teach sensitivity (0-5); ... The rich
report is at least 245 bytes; later firmware appends fields, which are not read here.
Every value is checked before it is believed.
"""

from __future__ import annotations

import contextlib
import logging
import math
import socket
import struct
import threading
import time
from dataclasses import dataclass

from cellcal.devices.errors import CellcalError, DeviceConnectionError, DeviceTimeoutError, ProtocolError

log = logging.getLogger(__name__)

RICH_MIN_BYTES = 245
"""Shortest rich report."""
MAX_REPORT_BYTES = 4096
"""Longest report accepted (the newest firmware sends under 1 KiB); a longer length is noise."""
MAX_POSE_MM = 10_000.0
MAX_ANGLE_RAD = 4.0 * math.pi
_BACKOFF_S = (0.05, 1.0)


@dataclass(frozen=True)
class ArmReport:
    """One checked report.

    Attributes:
        state: 1 moving, 2 sleeping (idle), 3 suspended, 4 stopped, 5 stopping (0 and 6 also occur).
        mode: Control mode (0 position).
        cmdnum: Commands queued.
        joints_rad: 7 joint angles, rad.
        pose_mm_rad: ``[x, y, z]`` mm, ``[roll, pitch, yaw]`` rad.
        error: Controller error code (0 none).
        warning: Controller warning code.
        enabled_bits: Motor enable bits (bit i: joint i + 1).
        received: ``time.monotonic()`` at arrival.
        seq: Running number of the report on this stream (1 = first).
    """

    state: int
    mode: int
    cmdnum: int
    joints_rad: tuple[float, ...]
    pose_mm_rad: tuple[float, ...]
    error: int
    warning: int
    enabled_bits: int
    received: float
    seq: int

    @property
    def idle(self) -> bool:
        """Sleeping with an empty queue and no error."""
        return self.state == 2 and self.cmdnum == 0 and self.error == 0

    @property
    def moving(self) -> bool:
        """Moving or with commands queued, and no error."""
        return self.error == 0 and (self.state == 1 or (self.state in (0, 2) and self.cmdnum > 0))


def check_length(value: int) -> int:
    """The length field of a report, if plausible.

    Raises:
        ProtocolError: If it is outside ``RICH_MIN_BYTES..MAX_REPORT_BYTES``.
    """
    if not RICH_MIN_BYTES <= value <= MAX_REPORT_BYTES:
        raise ProtocolError(f"xarm report length field {value} is not {RICH_MIN_BYTES}..{MAX_REPORT_BYTES} "
                            "(not a rich report, or the stream is out of step)", offset=0)
    return value


def parse_report(packet: bytes, *, received: float = 0.0, seq: int = 0) -> ArmReport:
    """Decode and check one report (the whole packet, length field included).

    Raises:
        ProtocolError: On a wrong length, an impossible state/mode/sensitivity, or a joint
            angle or pose that is not finite or out of an xArm's range.
    """
    length = check_length(struct.unpack_from(">I", packet)[0]) if len(packet) >= 4 else -1
    if length != len(packet):
        raise ProtocolError(f"xarm report is {len(packet)} bytes but says {length}", offset=0)
    state, mode = packet[4] & 0x0F, packet[4] >> 4
    cmdnum = struct.unpack_from(">H", packet, 5)[0]
    joints = struct.unpack_from("<7f", packet, 7)
    pose = struct.unpack_from("<6f", packet, 35)
    _brakes, enabled, error, warning = packet[87:91]
    collision, teach = packet[131], packet[132]
    if state > 6 or mode > 11 or collision > 5 or teach > 5:
        raise ProtocolError(f"xarm report: state {state}, mode {mode}, sensitivities {collision}/{teach} "
                            "are not a controller's", offset=4)
    if not all(math.isfinite(v) and abs(v) <= MAX_ANGLE_RAD for v in (*joints, *pose[3:])):
        raise ProtocolError(f"xarm report: angles {[*joints, *pose[3:]]} are not radians of an xArm", offset=7)
    if not all(math.isfinite(v) and abs(v) <= MAX_POSE_MM for v in pose[:3]):
        raise ProtocolError(f"xarm report: position {list(pose[:3])} is not millimetres of an xArm", offset=35)
    return ArmReport(state, mode, cmdnum, tuple(joints), tuple(pose), error, warning, enabled, received, seq)


class ReportStream:
    """Read the report port in a thread and keep the newest checked report.

    A malformed report, a stall longer than ``stale_after_s`` or a dropped connection is
    kept as :attr:`error` (until the next good report), the connection is closed and opened
    again with backoff. Memory is bounded: one report buffer of at most
    :data:`MAX_REPORT_BYTES`, one report kept.

    Args:
        host: Controller address.
        port: Report port (30002 rich).
        stale_after_s: Silence after which the stream counts as stalled, s.
        connect_timeout_s: Bound of one connection attempt, s.

    Attributes:
        stats: ``reports``, ``bad_reports``, ``stalls``, ``connects``, ``connect_failures``.
    """

    def __init__(self, host: str, port: int, *, stale_after_s: float = 1.0, connect_timeout_s: float = 2.0):
        self.host = host
        self.port = port
        self.stale_after_s = stale_after_s
        self.connect_timeout_s = connect_timeout_s
        self.stats = {"reports": 0, "bad_reports": 0, "stalls": 0, "connects": 0, "connect_failures": 0}
        self._cond = threading.Condition()
        self._latest: ArmReport | None = None
        self._error: CellcalError | None = None
        self._stop = threading.Event()
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ life cycle
    def start(self) -> None:
        """Start the reader thread (wait for the first report with :meth:`wait_newer`)."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"xarm-report {self.host}:{self.port}", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop the reader and join it (bounded); safe to call twice."""
        self._stop.set()
        sock = self._sock
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(self.connect_timeout_s + 1.0)
        with self._cond:
            self._cond.notify_all()

    # ------------------------------------------------------------------ readers' side
    @property
    def error(self) -> CellcalError | None:
        """Why the stream is not delivering, or None while it is healthy."""
        with self._cond:
            return self._error

    def latest(self, max_age_s: float | None = None) -> ArmReport | None:
        """The newest report if the stream is healthy (and it is younger than ``max_age_s``)."""
        with self._cond:
            report = self._latest
            if self._error is not None or report is None:
                return None
            if max_age_s is not None and time.monotonic() - report.received > max_age_s:
                return None
            return report

    def wait_newer(self, seq: int, deadline: float) -> ArmReport:
        """The first good report with a sequence number above ``seq``, waiting until ``deadline``.

        Raises:
            ProtocolError / DeviceConnectionError / DeviceTimeoutError: The stream's own error
                if it is failing when the deadline passes, else :class:`DeviceTimeoutError`.
        """
        with self._cond:
            while True:
                report = self._latest
                if report is not None and report.seq > seq and self._error is None:
                    return report
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self._stop.is_set():
                    if self._error is not None:
                        raise type(self._error)(f"xarm report stream {self.host}:{self.port}: {self._error}")
                    raise DeviceTimeoutError(f"xarm report stream {self.host}:{self.port}: no new report "
                                             f"within the deadline")
                self._cond.wait(min(remaining, 0.1))

    # ------------------------------------------------------------------ reader thread
    def _fail(self, error: CellcalError, counter: str) -> None:
        if self._stop.is_set():
            return  # closing: the reader's own shutdown is no failure
        self.stats[counter] += 1
        with self._cond:
            if self._error is None or str(self._error) != str(error):
                log.warning("%s", error)
            self._error = error
            self._cond.notify_all()

    def _run(self) -> None:
        pause = _BACKOFF_S[0]
        while not self._stop.is_set():
            try:
                sock = socket.create_connection((self.host, self.port), timeout=self.connect_timeout_s)
            except OSError as exc:
                self._fail(DeviceConnectionError(f"xarm: cannot connect to report port {self.host}:{self.port}: "
                                                 f"{exc}"), "connect_failures")
                self._stop.wait(pause)
                pause = min(2 * pause, _BACKOFF_S[1])
                continue
            self.stats["connects"] += 1
            self._sock = sock
            try:
                self._read_reports(sock)
                pause = _BACKOFF_S[0]
            except ProtocolError as exc:
                self._fail(exc, "bad_reports")
            except TimeoutError:
                self._fail(DeviceTimeoutError(f"xarm: no report within {self.stale_after_s} s"), "stalls")
            except OSError as exc:
                self._fail(DeviceConnectionError(f"xarm: report connection lost: {exc or 'closed'}"), "stalls")
            finally:
                self._sock = None
                with contextlib.suppress(OSError):
                    sock.close()
            self._stop.wait(pause)
            pause = min(2 * pause, _BACKOFF_S[1])

    def _read_exact(self, sock: socket.socket, n: int) -> bytes:
        buf = bytearray()
        while len(buf) < n:
            chunk = sock.recv(n - len(buf))
            if not chunk:
                raise ConnectionResetError("closed by the controller")
            buf += chunk
        return bytes(buf)

    def _read_reports(self, sock: socket.socket) -> None:
        sock.settimeout(self.stale_after_s)
        while not self._stop.is_set():
            head = self._read_exact(sock, 4)
            length = check_length(struct.unpack(">I", head)[0])
            packet = head + self._read_exact(sock, length - 4)
            with self._cond:
                seq = self._latest.seq + 1 if self._latest is not None else 1
            report = parse_report(packet, received=time.monotonic(), seq=seq)
            self.stats["reports"] += 1
            with self._cond:
                self._latest = report
                self._error = None
                self._cond.notify_all()
