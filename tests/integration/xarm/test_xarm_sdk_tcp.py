"""UFACTORY's own xarm-python-sdk against the xArm emulator over TCP, unmodified: the proof it speaks the real protocol.

Over TCP the SDK needs no workaround (over serial it does, see test_xarm_sdk.py): its report
thread reads the emulator's rich report and marks itself synchronised, so
``set_position(wait=True)`` returns. Only its port constants are pointed at the emulator:
the control port (``XCONF.SocketConf.TCP_CONTROL_PORT``, 502 on a real controller and
privileged here) at a free port. The report port stays 30002, because xarm-python-sdk
(checked with 1.18.4) picks its report decoder by that literal port number
(``ReportDataStructure.create`` in ``xarm/x3/report.py``) and drops every report that
arrives on any other; the emulator therefore serves its report on 127.0.0.1:30002, and a
lock file keeps two test processes from wanting it at once.
"""

from __future__ import annotations

import fcntl
import math
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from xarm_wire_helpers import bounded_call, sdk_refuses_an_out_of_workspace_move

from cellcal.devices.base import BackendContext
from cellcal.devices.pose import Pose
from cellcal.drivers.xarm.arm import XArmArm
from cellcal.drivers.xarm.registers import Reg
from cellcal.sims.arm import SimArm, SimArmConfig
from cellcal.sims.xarm.emulator import XArmEmulator
from cellcal.sims.xarm.tcp_server import XArmTcpServer

xarm_wrapper = pytest.importorskip("xarm.wrapper")
x_config = pytest.importorskip("xarm.core.config.x_config")

SDK_REPORT_PORT = 30002


@pytest.fixture
def served(monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[SimArm, XArmEmulator, XArmTcpServer]]:
    lock_path = Path(tempfile.gettempdir()) / "cellcal-xarm-sdk-report-30002.lock"
    with open(lock_path, "a+") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        sim = SimArm(SimArmConfig(time_scale=0.05, repeatability_m=0.0002), BackendContext()).connect()
        emu = XArmEmulator(sim, axes=5)
        server = XArmTcpServer(emu, report_port=SDK_REPORT_PORT, report_hz=20.0)
        try:
            tcp_port, _ = server.start()
        except OSError as exc:
            sim.close()
            pytest.skip(f"127.0.0.1:{SDK_REPORT_PORT} is taken by another program ({exc})")
        monkeypatch.setattr(x_config.XCONF.SocketConf, "TCP_CONTROL_PORT", tcp_port)
        try:
            yield sim, emu, server
        finally:
            server.close()
            emu.close()
            sim.close()


def test_official_sdk_over_tcp_connects_reads_and_moves_with_wait(
        served: tuple[SimArm, XArmEmulator, XArmTcpServer]) -> None:
    sim, emu, server = served
    sdk = bounded_call(lambda: xarm_wrapper.XArmAPI("127.0.0.1", is_radian=True), 15.0)
    try:
        assert sdk.connected
        code, version = sdk.get_version()
        assert code == 0 and version == emu.version_text
        assert sdk.axis == 5 and sdk.version_number == emu.firmware
        code, start = sdk.get_position(is_radian=True)
        assert code == 0
        np.testing.assert_allclose(np.asarray(start[:3]) / 1000.0, sim.true_flange_pose().translation, atol=1e-3)

        assert sdk.motion_enable(enable=True) == 0
        assert sdk.set_mode(0) == 0
        assert sdk.set_state(0) == 0
        target_mm_rad = [320.0, -60.0, 380.0, math.pi - 0.2, 0.1, 0.4]
        # no workaround: the SDK synchronises from the emulator's reports by itself
        code = bounded_call(lambda: sdk.set_position(*target_mm_rad, speed=200, mvacc=2000, is_radian=True,
                                                     wait=True, timeout=20), 30.0)
        assert code == 0
        assert emu.requests[Reg.MOVE_LINE] == 1 and emu.last_move is not None and emu.last_move.common
        assert not sim.is_moving()
        target = Pose.from_xyz_rpy(np.asarray(target_mm_rad[:3]) / 1000.0, target_mm_rad[3:])
        assert sim.true_flange_pose().distance_to(target) * 1000.0 < 0.5  # arrived, mm
        code, after = sdk.get_position(is_radian=True)
        assert code == 0 and np.abs(np.asarray(after[:3]) - target_mm_rad[:3]).max() < 0.5
        assert sdk.error_code == 0 and sdk.state in (1, 2) and server.reports_sent > 0
    finally:
        bounded_call(sdk.disconnect, 10.0)
    assert not sdk.connected

    # cellcal's driver on the same emulator reads what the SDK left
    cfg = XArmArm.Config(host="127.0.0.1", tcp_port=server.tcp_port, report_port=server.report_port, axes=5)
    with XArmArm(cfg) as drv:
        assert drv.get_pose().distance_to(target) * 1000.0 < 0.5


def test_official_sdk_over_tcp_sees_an_out_of_workspace_error(
        served: tuple[SimArm, XArmEmulator, XArmTcpServer]) -> None:
    sim, _emu, _server = served
    sdk = bounded_call(lambda: xarm_wrapper.XArmAPI("127.0.0.1", is_radian=True), 15.0)
    try:
        sdk.motion_enable(enable=True)
        sdk.set_mode(0)
        sdk.set_state(0)
        sdk_refuses_an_out_of_workspace_move(sdk, sim)
    finally:
        bounded_call(sdk.disconnect, 10.0)
