"""cellcal's own drivers, and a cell configuration, pointed at the address an emulator fixture yields.

docs/testing.md section 6 quotes these tests; ``tests/integration/testing/test_testing_doc.py`` checks that
every code block of that section is here word for word. Units are SI: metres, radians, seconds.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cellcal.core.calibration import build_devices, load_config
from cellcal.drivers.o3r import O3RCamera, O3RConfig
from cellcal.drivers.xarm import XArmArm
from cellcal.testing import O3RAddress, URAddress, XArmAddress


def test_the_o3r_driver_reads_the_emulator(cellcal_o3r_emulator: O3RAddress) -> None:
    config = O3RConfig(host=cellcal_o3r_emulator.host, xmlrpc_port=cellcal_o3r_emulator.xmlrpc_port)
    with O3RCamera(config) as camera:  # connects; reads the PCIC port of port2 over XML-RPC
        frame = camera.capture(5.0)
    assert frame.distance.shape == (172, 224) and frame.valid.mean() > 0.9
    assert 0.3 < float(np.median(frame.distance[frame.valid])) < 1.0  # metres to the emulator's table


def test_the_xarm_driver_moves_the_emulated_arm(cellcal_xarm_emulator: XArmAddress) -> None:
    config = XArmArm.Config(host=cellcal_xarm_emulator.host, tcp_port=cellcal_xarm_emulator.tcp_port,
                            report_port=cellcal_xarm_emulator.report_port, axes=5)
    with XArmArm(config) as arm:  # connects over TCP and enables the arm
        start = arm.get_pose()
        target = start.with_translation(start.translation - [0.0, 0.0, 0.02])  # 20 mm down
        arm.move_linear(target, speed=0.1, acceleration=1.0, timeout=10.0)
        assert arm.get_pose().distance_to(target) < 0.001
    assert cellcal_xarm_emulator.sim_arm.get_pose().distance_to(target) < 0.001  # the emulator's arm moved


def test_the_ur_driver_moves_the_emulated_arm(cellcal_ur_emulator: URAddress) -> None:
    pytest.importorskip("rtde_control")  # cellcal's UR driver talks through ur_rtde: pip install 'cellcal[ur]'
    from cellcal.drivers.ur import URArm, URConfig

    with URArm(URConfig(host=cellcal_ur_emulator.host)) as arm:  # the fixed UR ports on 127.0.0.N
        start = arm.get_pose()
        target = start.with_translation(start.translation + np.array([0.02, 0.0, 0.0]))
        arm.move_linear(target, speed=0.25, acceleration=1.2, timeout=10.0)
    reached = cellcal_ur_emulator.process.snapshot()["tcp"]
    assert np.linalg.norm(np.subtract(reached[:3], target.translation)) < 0.001


def test_a_cell_config_on_the_emulators(cellcal_sim_config: Path, cellcal_o3r_emulator: O3RAddress,
                                        cellcal_xarm_emulator: XArmAddress) -> None:
    config = load_config(cellcal_sim_config)  # cell.toml: mount, reference plane, safety envelope, plan
    camera, arm = build_devices(config, camera=cellcal_o3r_emulator.cellcal_camera(),
                                arm=cellcal_xarm_emulator.cellcal_arm())
    assert camera.backend_name == "o3r" and arm.inner.backend_name == "xarm"
    with camera, arm:  # arm is the config's SafeArm: every move is checked against [safety]
        assert camera.capture(5.0).valid.mean() > 0.9
        start = arm.get_pose()
        arm.move_linear(start.with_translation(start.translation - [0.0, 0.0, 0.02]), speed=0.1, acceleration=1.0)
        assert start.translation[2] - arm.get_pose().translation[2] == pytest.approx(0.02, abs=0.001)
