"""UFACTORY's own xarm-python-sdk against the xArm emulator: the proof that it speaks the real protocol.

Known SDK limitation worked around here: xarm-python-sdk (checked with 1.18.4) marks
itself synchronised (``_is_sync``) only when a TCP report packet arrives; over a serial
port there are none, so ``set_position`` would wait forever in its private
``__wait_sync`` loop. The test sets that flag once after connecting, as the SDK's TCP
report handler does on its first report. Everything else is the SDK's unmodified
serial path.
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Iterator

import numpy as np
import pytest
from xarm_wire_helpers import bounded_call, sdk_refuses_an_out_of_workspace_move

from cellcal.devices.base import BackendContext
from cellcal.devices.pose import Pose
from cellcal.drivers.xarm.arm import XArmArm
from cellcal.drivers.xarm.registers import Reg
from cellcal.sims.arm import SimArm, SimArmConfig
from cellcal.sims.xarm.emulator import XArmEmulator

xarm_wrapper = pytest.importorskip("xarm.wrapper")


@pytest.fixture(params=[(2, 5, 0), (1, 10, 0)], ids=["fw2.5.0-common-move-line", "fw1.10.0-legacy-move-line"])
def emulator(request: pytest.FixtureRequest) -> Iterator[tuple[SimArm, XArmEmulator]]:
    threads = set(threading.enumerate())
    fds = len(os.listdir("/proc/self/fd"))
    sim = SimArm(SimArmConfig(time_scale=0.05, repeatability_m=0.0), BackendContext()).connect()
    emu = XArmEmulator(sim, axes=5, firmware=request.param)
    emu.start()
    yield sim, emu
    emu.close()
    sim.close()
    for t in [t for t in threading.enumerate() if t not in threads]:
        t.join(timeout=5.0)
    leaked = [t for t in threading.enumerate() if t not in threads]
    assert not leaked, f"leaked threads: {leaked}"
    assert len(os.listdir("/proc/self/fd")) == fds


def test_official_sdk_reads_moves_and_agrees_with_the_cellcal_driver(
        emulator: tuple[SimArm, XArmEmulator]) -> None:
    sim, emu = emulator
    sdk = bounded_call(lambda: xarm_wrapper.XArmAPI(emu.path, is_radian=True), 10.0)
    try:
        assert sdk.connected
        code, version = sdk.get_version()
        assert code == 0 and version == emu.version_text
        assert sdk.axis == 5 and sdk.version_number == emu.firmware
        code, start = sdk.get_position(is_radian=True)
        assert code == 0
        true = sim.true_flange_pose()
        np.testing.assert_allclose(start[:3], true.translation * 1000.0, atol=1e-4)

        assert sdk.motion_enable(enable=True) == 0
        assert sdk.set_mode(0) == 0
        assert sdk.set_state(0) == 0
        assert bounded_call(lambda: sdk.get_state(), 5.0) == (0, 2)
        sdk._arm._is_sync = True  # see the module docstring

        target_mm_rad = [320.0, -60.0, 380.0, math.pi - 0.2, 0.1, 0.4]
        code = bounded_call(lambda: sdk.set_position(*target_mm_rad, speed=200, mvacc=2000, is_radian=True,
                                                     wait=True, timeout=20), 30.0)
        assert code == 0
        assert emu.requests[Reg.MOVE_LINE] == 1
        assert emu.last_move is not None and emu.last_move.common == (emu.firmware >= (1, 11, 100))
        assert emu.last_move.speed_mm_s == 200.0 and emu.last_move.acc_mm_s2 == 2000.0
        assert not sim.is_moving()
        code, after = sdk.get_position(is_radian=True)
        assert code == 0
        assert sdk.get_err_warn_code()[1] == [0, 0]
    finally:
        bounded_call(sdk.disconnect, 10.0)
    assert not sdk.connected

    target = Pose.from_xyz_rpy(np.asarray(target_mm_rad[:3]) / 1000.0, target_mm_rad[3:])
    true = sim.true_flange_pose()
    assert true.distance_to(target) < 1e-6 and true.angle_to(target) < 1e-6
    sdk_pose = Pose.from_xyz_rpy(np.asarray(after[:3]) / 1000.0, after[3:])
    with XArmArm(XArmArm.Config(port=emu.path, axes=5)) as drv:
        ours = drv.get_pose()
    assert np.abs(ours.translation - sdk_pose.translation).max() * 1000.0 < 1e-4  # mm
    assert ours.angle_to(sdk_pose) < 1e-6
    assert ours.distance_to(true) * 1000.0 < 1e-4 and ours.angle_to(true) < 1e-6


def test_official_sdk_sees_an_out_of_workspace_error(emulator: tuple[SimArm, XArmEmulator]) -> None:
    sim, emu = emulator
    sdk = bounded_call(lambda: xarm_wrapper.XArmAPI(emu.path, is_radian=True), 10.0)
    try:
        sdk.motion_enable(enable=True)
        sdk.set_mode(0)
        sdk.set_state(0)
        sdk._arm._is_sync = True  # see the module docstring
        sdk_refuses_an_out_of_workspace_move(sdk, sim)
    finally:
        bounded_call(sdk.disconnect, 10.0)
