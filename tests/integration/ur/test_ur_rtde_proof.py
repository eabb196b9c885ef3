"""ur_rtde's own, unmodified interfaces against the UR emulator: it speaks the real protocol.

``RTDEReceiveInterface``, ``RTDEControlInterface`` (default flags: it uploads its control
script and waits for it) and ``DashboardClient`` talk to ``python -m cellcal.sims.ur``.
How the ``ur`` backend turns ur_rtde's False into a typed error: test_ur_driver.py.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from ur_rig import HOME, wait_until

pytest.importorskip("rtde_control")  # the ur extra
import dashboard_client
import rtde_control
import rtde_receive

from cellcal.devices.geometry.vendor_poses import pose_to_ur
from cellcal.sims.ur.process import UREmulatorProcess


@pytest.fixture(scope="module")
def interfaces(emulator_process: UREmulatorProcess) -> Iterator[tuple[Any, Any]]:
    """One receive and one control interface for the module (each disconnect costs ur_rtde 0.5 s)."""
    emulator_process.call("reset")
    receive = rtde_receive.RTDEReceiveInterface(emulator_process.host)
    control = rtde_control.RTDEControlInterface(emulator_process.host)   # uploads its script, waits for it
    yield receive, control
    control.disconnect()
    receive.disconnect()


@pytest.fixture
def rtde(interfaces: tuple[Any, Any], emu: UREmulatorProcess) -> tuple[Any, Any]:
    """The module's interfaces, the control script running again (the reset stops it)."""
    receive, control = interfaces
    assert control.reuploadScript()
    wait_until(control.isProgramRunning, what="control script running")
    wait_until(lambda: np.linalg.norm(np.subtract(receive.getActualTCPPose()[:3], pose_to_ur(HOME)[:3])) < 1e-3,
               what="home pose in the stream")
    return receive, control


def test_receive_interface_reads_the_tcp_pose_and_a_running_clock(rtde: tuple[Any, Any],
                                                                  emu: UREmulatorProcess) -> None:
    receive, _control = rtde
    pose = np.array(receive.getActualTCPPose())
    truth = np.array(emu.snapshot()["tcp"])
    assert np.abs(pose[:3] - truth[:3]).max() < 1e-4              # UR-like read-back noise: 0.03 mm
    np.testing.assert_allclose(pose[:3], pose_to_ur(HOME)[:3], atol=1e-4)
    assert (receive.getRobotMode(), receive.getSafetyMode()) == (7, 1)
    assert len(receive.getActualQ()) == 6
    # controller time advances with the stream, and no faster than the wall clock (the emulator's motion runs
    # 10 times faster: a clock on it would advance 0.5 s in 0.05 s); 0.25 s for the age of the first package read
    t0, wall0 = receive.getTimestamp(), time.monotonic()
    deadline = wall0 + 60.0
    while receive.getTimestamp() - t0 < 0.5 and time.monotonic() < deadline:
        time.sleep(0.01)
    advanced, wall = receive.getTimestamp() - t0, time.monotonic() - wall0
    assert 0.5 <= advanced <= wall + 0.25, (advanced, wall)


def test_move_l_two_centimetres_arrives_within_half_a_millimetre(rtde: tuple[Any, Any],
                                                                 emu: UREmulatorProcess) -> None:
    receive, control = rtde
    assert control.isProgramRunning()
    target = list(receive.getActualTCPPose())
    target[0] += 0.02
    before = emu.snapshot()["commands"].get("3", 0)
    assert control.moveL(target, 0.25, 1.2) is True               # synchronous: returns once arrived
    wait_until(lambda: np.linalg.norm(np.subtract(receive.getActualTCPPose()[:3], target[:3])) < 0.5e-3,
               what="the target in the receive stream")          # its next packages show it
    reached = np.array(receive.getActualTCPPose())
    assert np.linalg.norm(reached[:3] - target[:3]) < 0.5e-3
    assert np.abs(reached[3:] - target[3:]).max() < 1e-6
    assert emu.snapshot()["commands"]["3"] == before + 1           # one moveL reached the script


def test_stop_l_stops_a_long_move_early(rtde: tuple[Any, Any], emu: UREmulatorProcess) -> None:
    receive, control = rtde
    emu.call("set_time_scale", time_scale=1.0)                    # real time: 0.4 m at 0.1 m/s is 4 s
    start = np.array(receive.getActualTCPPose())
    far = start.copy()
    far[1] += 0.4
    assert control.moveL(list(far), 0.1, 1.0, True) is True      # asynchronous
    wait_until(lambda: control.getAsyncOperationProgressEx().isAsyncOperationRunning(), what="async move")
    wait_until(lambda: np.linalg.norm(np.subtract(emu.snapshot()["tcp"][:3], start[:3])) > 0.02,
               what="20 mm of the move")                         # 0.2 s at speed; stopped long before 0.3 m
    control.stopL(5.0)
    wait_until(lambda: not control.getAsyncOperationProgressEx().isAsyncOperationRunning(), what="stop")
    wait_until(lambda: not emu.snapshot()["moving"], what="the controller at rest")
    rest = np.array(emu.snapshot()["tcp"])
    wait_until(lambda: np.abs(np.subtract(receive.getActualTCPPose()[:3], rest[:3])).max() < 1e-4,
               what="the rest pose in the receive stream")
    stopped = np.array(receive.getActualTCPPose())
    time.sleep(0.1)                                               # and it stays there
    assert np.linalg.norm(np.array(receive.getActualTCPPose()) - stopped) < 1e-4   # at rest
    travelled = np.linalg.norm(stopped[:3] - start[:3])
    assert 0.005 < travelled < 0.3, f"travelled {travelled * 1000:.1f} mm of 400 mm"
    assert not emu.snapshot()["moving"]


def test_protective_stop_is_reported_and_move_l_returns_false(rtde: tuple[Any, Any],
                                                              emu: UREmulatorProcess) -> None:
    receive, control = rtde
    assert not receive.isProtectiveStopped()
    emu.call("safety_stop", kind="protective_stop")
    wait_until(receive.isProtectiveStopped, what="isProtectiveStopped()")
    assert receive.getSafetyMode() == 3 and not receive.isEmergencyStopped()
    target = list(receive.getActualTCPPose())
    target[2] -= 0.02
    before = emu.snapshot()["commands"].get("3", 0)
    assert control.moveL(target, 0.25, 1.2) is False
    assert emu.snapshot()["commands"].get("3", 0) == before       # nothing reached the script


def test_dashboard_client_reports_the_robot_mode(emu: UREmulatorProcess) -> None:
    dash = dashboard_client.DashboardClient(emu.host)
    dash.connect(1000)
    try:
        assert dash.isConnected()
        assert dash.robotmode() == "Robotmode: RUNNING"
        assert dash.isInRemoteControl()
        assert dash.getRobotModel() == "UR5"
        assert dash.safetystatus() == "Safetystatus: NORMAL"
        dash.powerOff()
        assert dash.robotmode() == "Robotmode: POWER_OFF"
        dash.powerOn()
        assert dash.robotmode() == "Robotmode: IDLE"
        dash.brakeRelease()
        assert dash.robotmode() == "Robotmode: RUNNING"
    finally:
        dash.disconnect()
