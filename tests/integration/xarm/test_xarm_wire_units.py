"""The xArm driver puts millimetres and radians on the wire: what the controller reads, not what the driver meant.

The MOVE_LINE request is decoded by the emulator's own wire code (``cellcal.sims.xarm.wire``,
independent of the driver's), so a driver that sent m/s for mm/s, or metres for
millimetres, fails here whatever its motion timeout.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.devices.base import BackendContext
from cellcal.devices.pose import Pose
from cellcal.drivers.xarm.arm import XArmArm
from cellcal.sims.arm import SimArm, SimArmConfig
from cellcal.sims.xarm.emulator import XArmEmulator


@pytest.mark.parametrize(("firmware", "common"), [((2, 5, 0), True), ((1, 5, 0), False)])
@pytest.mark.parametrize(("speed_m_s", "acc_m_s2"), [(0.05, 0.8), (0.25, 2.5)])
def test_move_line_carries_mm_mm_s_mm_s2_and_rad(firmware: tuple[int, int, int], common: bool,
                                                 speed_m_s: float, acc_m_s2: float) -> None:
    sim = SimArm(SimArmConfig(time_scale=0.002, repeatability_m=0.0, seed=3), BackendContext()).connect()
    emu = XArmEmulator(sim, axes=5, firmware=firmware)
    target = Pose.from_xyz_rpy([0.3125, -0.0625, 0.4375], [math.pi - 0.25, 0.125, -0.5])
    try:
        with XArmArm(XArmArm.Config(port=emu.start(), axes=5, poll_interval_s=0.005)) as arm:
            arm.move_linear(target, speed=speed_m_s, acceleration=acc_m_s2, timeout=5.0)
        move = emu.last_move
        assert move is not None and move.common is common
        # float32 on the wire: mm/s and mm/s² to float32 precision
        assert move.speed_mm_s == pytest.approx(speed_m_s * 1000.0, rel=1e-6)
        assert move.acc_mm_s2 == pytest.approx(acc_m_s2 * 1000.0, rel=1e-6)
        assert list(move.pose[:3]) == pytest.approx([312.5, -62.5, 437.5], abs=1e-4)  # millimetres, base frame
        # roll/pitch/yaw in radians, the xArm's convention: the same rotation as the target's
        rpy = np.asarray(move.pose[3:], float)
        back = Pose.from_xyz_rpy([0.0, 0.0, 0.0], rpy)
        assert back.angle_to(target) < 1e-6
        assert (move.coord, move.axis_angle, move.only_check) == (0, False, 0)
        assert sim.true_flange_pose().distance_to(target) < 1e-6  # and the arm went there
    finally:
        emu.close()
        sim.close()
