"""The wire emulators as servers for tests: :func:`o3r_emulator`, :func:`xarm_emulator`, :func:`ur_emulator`.

Each yields the address a real client connects to (ifm3dpy, xarm-python-sdk, ur_rtde or cellcal's own
drivers). The O3R and UR emulators run as child processes, because ifm3dpy's and ur_rtde's calls hold
the GIL; the xArm one runs in threads of this process, so its simulated arm can be faulted. ADR 0033.
"""

from __future__ import annotations

import contextlib
import os
import re
import selectors
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cellcal.devices.base import BackendContext
from cellcal.devices.errors import CellcalError, DeviceConnectionError, DeviceTimeoutError
from cellcal.sims.arm import SimArm, SimArmConfig
from cellcal.sims.ur.dashboard import DASHBOARD_PORT
from cellcal.sims.ur.process import UREmulatorProcess
from cellcal.sims.ur.rtde_server import RTDE_PORT
from cellcal.sims.ur.script_role import SCRIPT_PORT
from cellcal.sims.xarm.emulator import XArmEmulator
from cellcal.sims.xarm.tcp_server import XArmTcpServer

__all__ = ["XARM_SDK_REPORT_PORT", "O3RAddress", "URAddress", "XArmAddress", "o3r_emulator", "ur_emulator",
           "xarm_emulator"]

#: The rich-report port xarm-python-sdk decodes reports from (it picks its decoder by this literal number).
XARM_SDK_REPORT_PORT = 30002
#: Longest first line read from an emulator child, bytes.
_MAX_LINE_BYTES = 4096
_O3R_READY = re.compile(r"xmlrpc=(?P<host>[\d.]+):(?P<xmlrpc>\d+) pcic=[\d.]+:(?P<pcic>\d+)")


@dataclass(frozen=True)
class O3RAddress:
    """Where an O3R emulator listens.

    Attributes:
        host: Loopback address (``127.0.0.1``).
        xmlrpc_port: XML-RPC port (the VPU's port 80): ``ifm3dpy.device.O3R(host, xmlrpc_port)``.
        pcic_port: PCIC port of the 3D head (``port2``): ``FrameGrabber(o3r, pcic_port=pcic_port)``.
        pid: Process id of the emulator's child process.
    """

    host: str
    xmlrpc_port: int
    pcic_port: int
    pid: int

    def cellcal_camera(self) -> dict[str, Any]:
        """The ``[camera]`` table of cellcal's ``o3r`` backend pointing at this emulator."""
        return {"backend": "o3r", "host": self.host, "xmlrpc_port": self.xmlrpc_port}


@dataclass(frozen=True)
class XArmAddress:
    """Where an xArm emulator listens, and the simulation behind it (for faults).

    Attributes:
        host: Loopback address (``127.0.0.1``).
        tcp_port: Control port (502 on a real controller).
        report_port: Rich report port (30002 on a real controller).
        sim_arm: The simulated arm the emulator drives (``fault_hook``, ``set_error``, ``freeze_motion``).
        emulator: The emulated controller (``inject`` spoils replies: ``drop``, ``stall``, ``corrupt_crc``…).
        server: The TCP server (``drop_clients``, ``inject_report``).
    """

    host: str
    tcp_port: int
    report_port: int
    sim_arm: SimArm
    emulator: XArmEmulator
    server: XArmTcpServer

    def cellcal_arm(self) -> dict[str, Any]:
        """The ``[arm]`` table of cellcal's ``xarm`` backend pointing at this emulator."""
        return {"backend": "xarm", "host": self.host, "tcp_port": self.tcp_port, "report_port": self.report_port,
                "axes": self.emulator.axes}


@dataclass(frozen=True)
class URAddress:
    """Where a UR emulator listens (a loopback address of its own, the controller's fixed ports).

    Attributes:
        host: Loopback address ``127.0.0.N`` chosen by the emulator (ur_rtde cannot change ports).
        rtde_port: RTDE port: ``rtde_receive.RTDEReceiveInterface(host)``.
        script_port: Script (secondary) port.
        dashboard_port: Dashboard port.
        process: The child process: ``process.call("safety_stop")``, ``"drop_connections"``,
            ``"freeze_stream"``, ``"snapshot"`` … (:mod:`cellcal.sims.ur.process`).
    """

    host: str
    rtde_port: int
    script_port: int
    dashboard_port: int
    process: UREmulatorProcess

    def cellcal_arm(self) -> dict[str, Any]:
        """The ``[arm]`` table of cellcal's ``ur`` backend pointing at this emulator."""
        return {"backend": "ur", "host": self.host}


# ---------------------------------------------------------------------- O3R


def _first_line(proc: subprocess.Popen[bytes], timeout_s: float, what: str) -> str:
    """The child's first stdout line within ``timeout_s``."""
    assert proc.stdout is not None
    fd = proc.stdout.fileno()
    buf = b""
    deadline = time.monotonic() + timeout_s
    with selectors.DefaultSelector() as sel:
        sel.register(fd, selectors.EVENT_READ)
        while b"\n" not in buf:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise DeviceTimeoutError(f"{what}: not ready within {timeout_s:g} s")
            if sel.select(min(remaining, 0.5)):
                chunk = os.read(fd, _MAX_LINE_BYTES)
                if not chunk:
                    raise DeviceConnectionError(f"{what}: the child process exited (status {proc.wait(5.0)})")
                buf += chunk
                if len(buf) > _MAX_LINE_BYTES:
                    raise DeviceConnectionError(f"{what}: first line longer than {_MAX_LINE_BYTES} bytes")
    return buf.split(b"\n", 1)[0].decode("utf-8", "replace").strip()


def _end(proc: subprocess.Popen[bytes], timeout_s: float) -> None:
    """Ask the child to stop (SIGTERM), kill it after ``timeout_s``, close its pipe."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout_s)
    if proc.stdout is not None:
        proc.stdout.close()


@contextlib.contextmanager
def o3r_emulator(*, noise: bool = True, frame_rate_hz: float = 20.0, seed: int = 0, state: str = "RUN",
                 extra_args: tuple[str, ...] = (), startup_timeout_s: float = 60.0) -> Iterator[O3RAddress]:
    """An O3R VPU with one 3D head (``python -m cellcal.sims.o3r``) on free ports of 127.0.0.1.

    Args:
        noise: Add the simulated camera's noise (False: every frame of the static scene is the same).
        frame_rate_hz: Frames per second in ``RUN``.
        seed: Seed of the simulated world.
        state: Initial state of the 3D port: ``RUN``, ``IDLE`` or ``CONF``.
        extra_args: More arguments of ``python -m cellcal.sims.o3r`` (``--mode``, ``--confidence-bits`` …).
        startup_timeout_s: Seconds the child may take to listen.

    Raises:
        DeviceTimeoutError: If it does not listen in time.
        DeviceConnectionError: If it exits instead (its stderr says why).
    """
    if state not in ("RUN", "IDLE", "CONF"):
        raise CellcalError(f"o3r_emulator: state must be RUN, IDLE or CONF, got {state!r}")
    if not 0.0 < frame_rate_hz <= 1000.0:
        raise CellcalError(f"o3r_emulator: frame_rate_hz must be within (0, 1000] Hz, got {frame_rate_hz!r}")
    argv = [sys.executable, "-m", "cellcal.sims.o3r", "--xmlrpc-port", "0", "--pcic-port", "0", "--state", state,
            "--frame-rate", repr(float(frame_rate_hz)), "--seed", str(int(seed)), *extra_args]
    if not noise:
        argv.append("--no-noise")
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stdin=subprocess.DEVNULL)
    try:
        line = _first_line(proc, startup_timeout_s, "o3r emulator")
        found = _O3R_READY.search(line)
        if "ready" not in line or found is None:
            raise DeviceConnectionError(f"o3r emulator: unexpected first line {line!r}")
        yield O3RAddress(found["host"], int(found["xmlrpc"]), int(found["pcic"]), proc.pid)
    finally:
        _end(proc, 10.0)


# ---------------------------------------------------------------------- xArm


@contextlib.contextmanager
def _report_port_lock(port: int, timeout_s: float) -> Iterator[None]:
    """Hold an inter-process lock on ``port`` (the same file other cellcal test processes use)."""
    try:
        import fcntl
    except ImportError:  # no fcntl (Windows): no lock; a taken port then fails the bind with a clear error
        yield
        return
    path = Path(tempfile.gettempdir()) / f"cellcal-xarm-sdk-report-{port}.lock"
    with open(path, "a+") as lock:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    raise DeviceTimeoutError(f"xarm emulator: port {port} stayed in use by another test process "
                                             f"for {timeout_s:g} s") from None
                time.sleep(0.05)
        yield  # released when the file closes


@contextlib.contextmanager
def xarm_emulator(*, axes: int = 5, time_scale: float = 0.05, ready: bool = False, sdk_report_port: bool = False,
                  report_hz: float = 20.0, seed: int = 0, lock_timeout_s: float = 120.0) -> Iterator[XArmAddress]:
    """An xArm controller over TCP on 127.0.0.1 (control port free, report port free or 30002).

    Args:
        axes: Axis count the controller reports (5, 6 or 7).
        time_scale: Wall seconds per simulated second of motion (1 = real time).
        ready: Start enabled and ready (a real arm starts stopped; clients enable it).
        sdk_report_port: Serve the report on :data:`XARM_SDK_REPORT_PORT` (30002), the only report port
            xarm-python-sdk decodes; an inter-process lock makes parallel tests take turns on it. The SDK's
            control port is then pointed at ``tcp_port`` by the test (``XCONF.SocketConf.TCP_CONTROL_PORT``).
        report_hz: Reports per second.
        seed: Seed of the simulated arm's read-back noise.
        lock_timeout_s: Seconds to wait for the report port's lock.

    Raises:
        DeviceConnectionError: If a port cannot be bound.
    """
    if not 0.0 <= time_scale <= 10.0:
        raise CellcalError(f"xarm_emulator: time_scale must be within [0, 10], got {time_scale!r}")
    with contextlib.ExitStack() as stack:
        if sdk_report_port:
            stack.enter_context(_report_port_lock(XARM_SDK_REPORT_PORT, lock_timeout_s))
        arm = SimArm(SimArmConfig(time_scale=time_scale), BackendContext(seed=seed)).connect()
        stack.callback(arm.close)
        emulator = XArmEmulator(arm, axes=axes, start_ready=ready)
        stack.callback(emulator.close)
        server = XArmTcpServer(emulator, report_port=XARM_SDK_REPORT_PORT if sdk_report_port else 0,
                               report_hz=report_hz)
        try:
            tcp_port, report_port = server.start()
        except OSError as exc:
            raise DeviceConnectionError(f"xarm emulator: cannot listen on 127.0.0.1: {exc}") from None
        stack.callback(server.close)
        yield XArmAddress(server.host, tcp_port, report_port, arm, emulator, server)


# ---------------------------------------------------------------------- UR


@contextlib.contextmanager
def ur_emulator(*, time_scale: float = 0.1, powered: bool = True, unlock_delay_s: float = 0.0, seed: int = 0,
                startup_timeout_s: float = 60.0) -> Iterator[URAddress]:
    """A UR controller (``python -m cellcal.sims.ur``) on a free loopback address 127.0.0.N.

    Args:
        time_scale: Wall seconds per simulated second of motion (1 = real time).
        powered: Start powered with brakes released (a real arm starts powered off).
        unlock_delay_s: Minimum time from a protective stop to its unlock, s (5 on a real UR).
        seed: Seed of the arm's read-back noise.
        startup_timeout_s: Seconds the child may take to listen.

    Raises:
        DeviceTimeoutError: If it does not listen in time.
        DeviceConnectionError: If it exits instead.
    """
    if not 0.0 <= time_scale <= 10.0:
        raise CellcalError(f"ur_emulator: time_scale must be within [0, 10], got {time_scale!r}")
    process = UREmulatorProcess("auto", arm_config={"time_scale": float(time_scale)}, powered=powered,
                                unlock_delay_s=unlock_delay_s, seed=seed)
    host = process.start(startup_timeout_s)
    try:
        yield URAddress(host, RTDE_PORT, SCRIPT_PORT, DASHBOARD_PORT, process)
    finally:
        process.close()
