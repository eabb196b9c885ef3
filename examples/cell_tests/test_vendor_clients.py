"""The wire emulators driven by each vendor's own client, and by cellcal's drivers on the same address.

Each test is skipped when its vendor's client is not installed (``pip install ifm3dpy``,
``xarm-python-sdk``, ``ur-rtde``).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.devices import Pose
from cellcal.devices.registry import default_registry
from cellcal.testing import O3RAddress, URAddress, XArmAddress


def test_ifm3dpy_reads_a_frame_of_the_table(cellcal_o3r_emulator: O3RAddress) -> None:
    device = pytest.importorskip("ifm3dpy.device")
    framegrabber = pytest.importorskip("ifm3dpy.framegrabber")
    o3r = device.O3R(cellcal_o3r_emulator.host, cellcal_o3r_emulator.xmlrpc_port)
    assert o3r.get(["/ports/port2/info/features/type"])["ports"]["port2"]["info"]["features"]["type"] == "3D"

    buffers = framegrabber.buffer_id
    grabber = framegrabber.FrameGrabber(o3r, pcic_port=cellcal_o3r_emulator.pcic_port)
    ok, _ = grabber.start([buffers.RADIAL_DISTANCE_IMAGE, buffers.CONFIDENCE_IMAGE]).wait_for(5000)
    assert ok
    try:
        ok, frame = grabber.wait_for_frame().wait_for(5000)
        assert ok
        theirs = np.array(frame.get_buffer(buffers.RADIAL_DISTANCE_IMAGE), dtype=np.float64)
        valid = (np.array(frame.get_buffer(buffers.CONFIDENCE_IMAGE)) & 1) == 0
    finally:
        grabber.stop().wait_for(5000)

    # cellcal's own O3R driver on the same emulator sees the same table
    camera = default_registry().create_camera(cellcal_o3r_emulator.cellcal_camera())
    with camera:
        ours = camera.capture(5.0)
    assert theirs.shape == ours.distance.shape == (172, 224)
    assert valid.mean() > 0.9 and ours.valid.mean() > 0.9
    assert abs(np.median(theirs[valid]) - np.median(ours.distance[ours.valid])) < 0.005  # metres


def test_xarm_python_sdk_moves_the_arm(cellcal_xarm_emulator: XArmAddress, monkeypatch: pytest.MonkeyPatch) -> None:
    wrapper = pytest.importorskip("xarm.wrapper")
    x_config = pytest.importorskip("xarm.core.config.x_config")
    # the SDK has no port argument: point its control port (502 on a real arm) at the emulator
    monkeypatch.setattr(x_config.XCONF.SocketConf, "TCP_CONTROL_PORT", cellcal_xarm_emulator.tcp_port)
    arm = wrapper.XArmAPI(cellcal_xarm_emulator.host, is_radian=True)
    try:
        assert arm.connected and arm.axis == 5
        assert arm.motion_enable(enable=True) == 0 and arm.set_mode(0) == 0 and arm.set_state(0) == 0
        target_mm_rad = [320.0, -60.0, 380.0, math.pi - 0.2, 0.1, 0.4]
        code = arm.set_position(*target_mm_rad, speed=200, mvacc=2000, is_radian=True, wait=True, timeout=20)
        assert code == 0
        code, position = arm.get_position(is_radian=True)
        assert code == 0 and np.abs(np.subtract(position[:3], target_mm_rad[:3])).max() < 0.5  # mm
    finally:
        arm.disconnect()

    # cellcal's xArm driver on the same emulator reads the pose the SDK left (SI units: metres, radians)
    target = Pose.from_xyz_rpy(np.array(target_mm_rad[:3]) / 1000.0, target_mm_rad[3:])
    with default_registry().create_arm(cellcal_xarm_emulator.cellcal_arm()) as ours:
        assert ours.get_pose().distance_to(target) < 0.0005


def test_ur_rtde_reads_and_moves_the_arm(cellcal_ur_emulator: URAddress) -> None:
    rtde_receive = pytest.importorskip("rtde_receive")
    rtde_control = pytest.importorskip("rtde_control")
    receive = rtde_receive.RTDEReceiveInterface(cellcal_ur_emulator.host)
    control = rtde_control.RTDEControlInterface(cellcal_ur_emulator.host)
    try:
        start = list(receive.getActualTCPPose())
        truth = cellcal_ur_emulator.process.snapshot()["tcp"]
        assert np.abs(np.subtract(start[:3], truth[:3])).max() < 1e-4  # metres
        target = [start[0] + 0.02, *start[1:]]
        assert control.moveL(target, 0.25, 1.2) is True  # returns once arrived
        reached = cellcal_ur_emulator.process.snapshot()["tcp"]
        assert np.linalg.norm(np.subtract(reached[:3], target[:3])) < 0.0005
    finally:
        control.disconnect()
        receive.disconnect()
