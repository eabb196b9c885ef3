"""The real xArm driver against a hostile fake xArm written here (not cellcal.sims), on a pty.

The fake speaks the serial protocol from the wire facts alone (its own CRC, framing and
register table, no cellcal wire code) and scripts one misbehaviour per case: a garbled,
missing or late reply to MOVE_LINE, replies lagging one request behind, an arm that stops
70 mm short and says it is done, a pose read-back that jumps. Every case asserts the typed
error, the time to fail (the move's timeout + 1 s at most), that no thread is left, and
the number of motion commands the device received: exactly one per ``move_linear``.
The same faults then go through the sim arm's and the emulator's switches, in a
calibration run. ``pytest -s`` prints the figures per case.
"""

from __future__ import annotations

import contextlib
import math
import os
import random
import select
import struct
import threading
import time
import tracemalloc
import tty
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from fault_cells import all_threads, cell_document, leftovers, make_probe
from leaks import open_fds

from cellcal.core.calibration.calibrator import run_to_file
from cellcal.devices.errors import DeviceError, MotionError
from cellcal.devices.pose import Pose
from cellcal.drivers.xarm.arm import XArmArm

MOVE_TIMEOUT_S = 2.0   # what move_linear is given in every case
REPLY_TIMEOUT_S = 0.2  # the driver's reply timeout
STOP_TIMEOUT_S = 0.8   # the driver's budget to find out and stop after an unconfirmed move
MOVE_S = 0.6           # how long the fake arm takes for any move
SHORTFALL_MM = 70.0

#: Registers that move an xArm (UFACTORY's register table: MOVE_LINE, MOVE_LINEB, MOVE_JOINT,
#: MOVE_JOINTB, MOVE_HOME, MOVE_CIRCLE, MOVE_LINE_TOOL, MOVE_SERVOJ, MOVE_SERVO_CART,
#: MOVE_RELATIVE, MOVE_LINE_AA, MOVE_SERVO_CART_AA).
MOTION_REGISTERS = frozenset({21, 22, 23, 24, 25, 27, 28, 29, 30, 83, 92, 93})
MOVE_LINE, SET_STATE, GET_TCP_POSE = 21, 12, 41


#: Seconds the ``flood`` fake pours random bytes onto the line (as much as the pty takes).
FLOOD_S = 1.0
_NOISE = random.Random(7).randbytes(64 * 1024)
#: Peak memory the driver (and the fake) may trace above the start of a case, bytes.
MEMORY_BOUND = 4 * 1024 * 1024


# ---------------------------------------------------------------------- the fake, from the wire facts
def crc16_modbus(data: bytes) -> int:
    """Bit by bit: init 0xFFFF, reflected polynomial 0xA001."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def reply_frame(state: int, data: bytes = b"") -> bytes:
    """``55 AA LEN STATE data CRC_lo CRC_hi``."""
    head = bytes([0x55, 0xAA, len(data) + 1, state]) + data
    return head + struct.pack("<H", crc16_modbus(head))


@dataclass
class Motion:
    start: list[float]
    end: list[float]
    t0: float

    def at(self, now: float) -> tuple[list[float], bool]:
        """Pose (mm, rad) at ``now`` and whether the motion is over."""
        s = min(1.0, (now - self.t0) / MOVE_S)
        return [a + s * (b - a) for a, b in zip(self.start, self.end, strict=True)], s >= 1.0


@dataclass
class HostileXArm:
    """An xArm 6 controller on a pty master whose replies misbehave as ``misbehaviour`` says.

    ``healthy``, ``garbled_move_reply`` (bad CRC), ``no_move_reply``, ``late_move_reply``
    (sent 0.35 s late, after the driver's reply timeout), ``lagging`` (from MOVE_LINE on,
    every reply answers the request before), ``lagging_from_connect``, ``short`` (every
    move ends 70 mm before its target, reported done), ``jumping`` (each pose read is off
    by 20-60 mm), ``flood`` (after confirming MOVE_LINE, the line carries nothing but
    random bytes for :data:`FLOOD_S`). A move takes effect in every case.
    """

    misbehaviour: str
    requests: list[tuple[int, bytes]] = field(default_factory=list)
    pose: list[float] = field(default_factory=lambda: [300.0, 0.0, 400.0, math.pi, 0.0, 0.0])
    motion: Motion | None = None
    stopped: bool = False
    lagging: bool = False
    flooding: bool = False
    flooded: int = 0
    flood_until: float = 0.0

    def __post_init__(self) -> None:
        self.lagging = self.misbehaviour == "lagging_from_connect"
        self._held: bytes | None = None
        self._later: list[tuple[float, bytes]] = []
        self._rng = random.Random(14)
        self._stop = threading.Event()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.path = os.ttyname(self._slave)
        self._thread = threading.Thread(target=self._serve, name="hostile-xarm", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        os.close(self._master)
        os.close(self._slave)

    # -------------------------------------------------------------- counts
    def motion_commands(self) -> int:
        return sum(1 for reg, _ in self.requests if reg in MOTION_REGISTERS)

    def stops(self) -> int:
        return sum(1 for reg, p in self.requests if reg == SET_STATE and p[:1] == b"\x04")

    def runs_after_first_move(self) -> int:
        """SET_STATE 0 (run: resumes a paused queue) after the first motion command."""
        regs = [(reg, p) for reg, p in self.requests]
        first = next((i for i, (reg, _) in enumerate(regs) if reg in MOTION_REGISTERS), len(regs))
        return sum(1 for reg, p in regs[first:] if reg == SET_STATE and p[:1] == b"\x00")

    # -------------------------------------------------------------- the controller
    def _now_pose(self) -> tuple[list[float], bool]:
        if self.motion is None:
            return self.pose, False
        pose, done = self.motion.at(time.monotonic())
        if done:
            self.pose, self.motion = pose, None
        return pose, not done

    def _move_line(self, params: bytes) -> bytes:
        target = list(struct.unpack_from("<6f", params))
        end = target
        if self.misbehaviour == "short":  # 70 mm before the target along the straight path
            here = self._now_pose()[0]
            d = [t - h for t, h in zip(target[:3], here[:3], strict=True)]
            n = math.sqrt(sum(v * v for v in d)) or 1.0
            end = [t - SHORTFALL_MM * v / n for t, v in zip(target[:3], d, strict=True)] + target[3:]
        self.motion = Motion(self._now_pose()[0], end, time.monotonic())
        return bytes(3) if len(params) == 43 else b""

    def _pose_reply(self) -> bytes:
        pose = list(self._now_pose()[0])
        if self.misbehaviour == "jumping":
            pose[:3] = [v + self._rng.choice((-1, 1)) * self._rng.uniform(20.0, 60.0) for v in pose[:3]]
        return struct.pack("<6f", *pose)

    def _answer(self, reg: int, params: bytes) -> bytes:
        moving = self._now_pose()[1]
        if reg == 1:
            return reply_frame(0, b"6,6,XSHOSTILE0001,ACHOSTILE0001,v2.5.0".ljust(40, b"\0"))
        if reg == 2:
            return reply_frame(0, b"XSHOSTILE0001\0ACHOSTILE0001\0".ljust(40, b"\0"))
        if reg == SET_STATE and params[:1] == b"\x04":
            if self.motion is not None:
                self.pose, self.motion = self._now_pose()[0], None  # halts where it is
            self.stopped = True
        elif reg == SET_STATE and params[:1] == b"\x00":
            self.stopped = False
        if reg in (11, SET_STATE, 16, 17, 19):
            return reply_frame(0)
        if reg == 13:
            return reply_frame(0, bytes([4 if self.stopped else 1 if moving else 2]))
        if reg == 14:
            return reply_frame(0, struct.pack(">H", 1 if moving else 0))
        if reg == 15:
            return reply_frame(0, b"\0\0")
        if reg == MOVE_LINE:
            return reply_frame(0, self._move_line(params))
        if reg == GET_TCP_POSE:
            return reply_frame(0, self._pose_reply())
        if reg == 42:
            return reply_frame(0, bytes(28))
        return reply_frame(0x08)

    def _misbehave(self, reg: int, frame: bytes) -> bytes:
        """What actually goes on the wire in answer to ``reg``."""
        m = self.misbehaviour
        if reg == MOVE_LINE:
            if m == "garbled_move_reply":
                return frame[:-1] + bytes([frame[-1] ^ 0xFF])
            if m == "no_move_reply":
                return b""
            if m == "late_move_reply":
                self._later.append((time.monotonic() + 0.35, frame))
                return b""
            if m == "lagging":
                self.lagging = True
            if m == "flood":
                self.flooding, self.flood_until = True, time.monotonic() + FLOOD_S
                os.set_blocking(self._master, False)
        if self.lagging:
            frame, self._held = (self._held or b""), frame
        return frame

    # -------------------------------------------------------------- serving
    def _flood(self) -> None:
        """As many random bytes as the line takes now (never blocking the fake)."""
        with contextlib.suppress(BlockingIOError):
            self.flooded += os.write(self._master, _NOISE)

    def _write_all(self, data: bytes) -> None:
        """A reply goes out whole even once the flood made the line non-blocking and full.

        The driver drains the noise, so the line has room again within milliseconds; a reply
        that cannot go out within a second is dropped (the driver's own timeouts then decide).
        """
        deadline = time.monotonic() + 1.0
        view = memoryview(data)
        while view and time.monotonic() < deadline and not self._stop.is_set():
            try:
                view = view[os.write(self._master, view):]
            except BlockingIOError:
                select.select([], [self._master], [], 0.01)

    def _requests(self, buf: bytearray) -> Iterator[tuple[int, bytes]]:
        while True:
            start = buf.find(b"\xaa\x55")
            if start < 0:
                del buf[:-1]
                return
            del buf[:start]
            if len(buf) < 3 or len(buf) < 5 + buf[2]:
                return
            frame = bytes(buf[: 5 + buf[2]])
            if struct.unpack("<H", frame[-2:])[0] != crc16_modbus(frame[:-2]):
                del buf[:1]
                continue
            del buf[: len(frame)]
            yield frame[3], frame[4:-2]

    def _serve(self) -> None:
        buf = bytearray()
        while not self._stop.is_set():
            due = [f for t, f in self._later if t <= time.monotonic()]
            self._later = [(t, f) for t, f in self._later if t > time.monotonic()]
            for frame in due:
                self._write_all(frame)
            if self.flooding and time.monotonic() < self.flood_until:
                self._flood()
            ready, _, _ = select.select([self._master], [], [], 0.01)
            if not ready:
                continue
            buf += os.read(self._master, 4096)
            for reg, params in self._requests(buf):
                self.requests.append((reg, params))
                out = self._misbehave(reg, self._answer(reg, params))
                if out:
                    self._write_all(out)


# ---------------------------------------------------------------------- the cases
@dataclass(frozen=True)
class Case:
    misbehaviour: str
    expected: str  # a phrase of the MotionError's message
    fails_at_connect: bool = False


CASES = [
    Case("garbled_move_reply", "MOVE_LINE to .* was not confirmed \\(.*CRC"),
    Case("no_move_reply", "MOVE_LINE to .* was not confirmed \\(.*no reply"),
    Case("late_move_reply", "MOVE_LINE to .* was not confirmed \\(.*no reply"),
    Case("lagging", "MOVE_LINE to .* was not confirmed"),
    Case("short", "reported done, but pose read 1 of 2 is 70.0\\d\\d mm"),
    Case("jumping", "reported done, but pose reads 1 and 2 of 2 at rest differ by .*not steady"),
    Case("lagging_from_connect", "", fails_at_connect=True),
]


def _driver(path: str) -> XArmArm:
    return XArmArm(XArmArm.Config(port=path, axes=6, reply_timeout_s=REPLY_TIMEOUT_S, retries=2,
                                  stop_timeout_s=STOP_TIMEOUT_S, poll_interval_s=0.01))


def _target() -> Pose:  # 120 mm from the fake's start pose, flange down
    return Pose.from_xyz_rpy([0.42, 0.0, 0.40], [math.pi, 0.0, 0.0])


def test_healthy_fake_moves_once_and_arrives() -> None:
    fake = HostileXArm("healthy")
    try:
        with _driver(fake.path) as drv:
            drv.move_linear(_target(), speed=0.2, acceleration=2.0, timeout=MOVE_TIMEOUT_S)
            assert drv.get_pose().distance_to(_target()) < 1e-6
        assert fake.motion_commands() == 1 and fake.stops() == 0
    finally:
        fake.close()


@pytest.mark.parametrize("case", CASES, ids=[c.misbehaviour for c in CASES])
def test_hostile_xarm(case: Case) -> None:
    threads, fds = all_threads(), open_fds()
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    fake = HostileXArm(case.misbehaviour)
    drv = _driver(fake.path)
    t0 = time.monotonic()
    try:
        if case.fails_at_connect:
            with pytest.raises(DeviceError) as err:
                drv.connect(1.0)
                drv.move_linear(_target(), speed=0.2, acceleration=2.0, timeout=MOVE_TIMEOUT_S)
        else:
            drv.connect(2.0)
            t0 = time.monotonic()
            with pytest.raises(MotionError, match=case.expected) as err:
                drv.move_linear(_target(), speed=0.2, acceleration=2.0, timeout=MOVE_TIMEOUT_S)
        elapsed = time.monotonic() - t0
        busy = [t for t in threading.enumerate() if t not in threads and t.name != "hostile-xarm"]
    finally:
        drv.close()
        fake.close()
        peak = tracemalloc.get_traced_memory()[1] - base
        tracemalloc.stop()
    print(f"\n{case.misbehaviour}: {type(err.value).__name__} after {elapsed:.2f} s, "
          f"{fake.motion_commands()} motion command(s), {fake.stops()} stop(s), peak {peak / 1e6:.2f} MB, "
          f"{fake.flooded / 1e6:.1f} MB of noise: {err.value}")
    assert peak < MEMORY_BOUND, f"peak traced memory {peak / 1e6:.1f} MB"
    assert "\n" not in str(err.value)
    assert elapsed <= MOVE_TIMEOUT_S + 1.0, f"took {elapsed:.2f} s"
    assert not busy, f"the driver left threads running: {busy}"
    assert fake.runs_after_first_move() == 0, "SET_STATE 0 (resume) sent after a motion command"
    if case.fails_at_connect:
        assert fake.motion_commands() <= 1
    else:
        assert fake.motion_commands() == 1, f"{fake.motion_commands()} motion commands for one move_linear"
        assert fake.stops() >= 1, "the arm was never told to stop"
    leaked_threads, leaked_fds = leftovers(threads, fds)
    assert not leaked_threads and not leaked_fds


def test_noise_flood_costs_no_memory_and_no_second_move() -> None:
    """Random bytes pouring in between replies: CRC-checked frames still get through, memory stays flat."""
    threads, fds = all_threads(), open_fds()
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    fake = HostileXArm("flood")
    try:
        with _driver(fake.path) as drv:
            t0 = time.monotonic()
            drv.move_linear(_target(), speed=0.2, acceleration=2.0, timeout=MOVE_TIMEOUT_S)
            elapsed = time.monotonic() - t0
            # the arrival check read the pose through the noise: the fake really is there
            assert fake.pose == pytest.approx([420.0, 0.0, 400.0, math.pi, 0.0, 0.0], abs=1e-3)
    finally:
        fake.close()
        peak = tracemalloc.get_traced_memory()[1] - base
        tracemalloc.stop()
    print(f"\nflood: arrived after {elapsed:.2f} s through {fake.flooded / 1e6:.1f} MB of noise, "
          f"peak {peak / 1e6:.2f} MB")
    assert fake.flooded > 256 * 1024, "the fake did not get its noise onto the line"
    assert peak < MEMORY_BOUND, f"peak traced memory {peak / 1e6:.1f} MB"
    assert elapsed <= MOVE_TIMEOUT_S + 1.0
    assert fake.motion_commands() == 1 and fake.stops() == 0
    leaked_threads, leaked_fds = leftovers(threads, fds)
    assert not leaked_threads and not leaked_fds


# ---------------------------------------------------------------------- the same faults through the sims, in a run
#: The emulator's switches for the wire faults: (kind, count, register).
WIRE_FAULTS = {"lost_reply": ("drop", 1, MOVE_LINE), "garbled_reply": ("corrupt_crc", 1, MOVE_LINE),
               "lagging": ("lag", 10_000, None)}
RUN_MOVE_TIMEOUT_S = 1.0  # plan.move_timeout_s of the run (its longest move needs 0.6 s)
RUN_STOP_TIMEOUT_S = 2.0  # the xArm driver's default stop_timeout_s


ARM_FAULTS = ["stop_short", "jumping_pose", "stale_reads"]
RUN_CASES = [("sim", f) for f in ARM_FAULTS] + [("xarm-emulated", f) for f in [*WIRE_FAULTS, *ARM_FAULTS]]


@pytest.mark.parametrize(("arm", "fault"), RUN_CASES, ids=[f"{a}-{f}" for a, f in RUN_CASES])
def test_calibration_stops_on_a_motion_fault(arm: str, fault: str, tmp_path: Path) -> None:
    """A fault that spoils move 2: MotionError, the arm told to stop, one motion command per move."""
    probe = make_probe(cell_document(arm=arm, plan={"move_timeout_s": RUN_MOVE_TIMEOUT_S}))
    sim = probe.sim_arm

    def hook(event: str, n: int) -> None:
        # an arm fault is switched on as move 1 starts (it shapes the next motion), a wire fault as
        # MOVE_LINE 2 is being answered (it spoils that reply)
        if event != "move" or n != (1 if fault == "stop_short" else 2):
            return
        if fault in WIRE_FAULTS:
            kind, count, register = WIRE_FAULTS[fault]
            probe.xarm[-1].inject(kind, count=count, register=register)
        elif fault == "stop_short":
            sim.faults.stop_short_m = 0.07
        elif fault == "jumping_pose":
            sim.faults.pose_jump_m = 0.05
        else:
            sim.faults.stale_reads = True

    sim.fault_hook = hook
    threads, fds = all_threads(), open_fds()
    out = tmp_path / "result.json"
    t0 = time.monotonic()
    with pytest.raises(MotionError) as err:
        run_to_file(probe.calibrator, out)
    elapsed = time.monotonic() - t0
    print(f"\n{arm}/{fault}: MotionError after {elapsed:.2f} s: {err.value}")
    assert elapsed <= 2 * RUN_MOVE_TIMEOUT_S + RUN_STOP_TIMEOUT_S + 1.0  # two moves, the stop budget, 1 s
    assert not out.exists()
    if probe.xarm:
        assert probe.xarm[-1].stop_requests >= 1
        assert probe.xarm[-1].requests.get(MOVE_LINE, 0) == 2, "a motion command was sent twice"
    else:
        assert sim.stops >= 1
    assert sim.moves_started == 2
    assert not sim.is_moving()
    leaked_threads, leaked_fds = leftovers(threads, fds)
    assert not leaked_threads and not leaked_fds
