"""cellcal.testing.emulators: each emulator listens where its address says, answers a real client, and goes away."""

from __future__ import annotations

import os
import socket

import numpy as np
import pytest

from cellcal.devices.errors import CellcalError
from cellcal.devices.pose import Pose
from cellcal.devices.registry import default_registry
from cellcal.sims.world import MountConfig, SimConfig
from cellcal.testing import o3r_emulator, ur_emulator, xarm_emulator
from cellcal.testing.emulators import XARM_SDK_REPORT_PORT


def _refused(host: str, port: int) -> bool:
    try:
        socket.create_connection((host, port), timeout=2.0).close()
    except ConnectionRefusedError:
        return True
    return False


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_the_o3r_emulator_serves_cellcal_s_o3r_driver_and_ends_with_its_process() -> None:
    with o3r_emulator(noise=False, extra_args=("--no-systematic",)) as address:  # an ideal camera: the true range
        assert address.host == "127.0.0.1" and address.xmlrpc_port != address.pcic_port
        with default_registry().create_camera(address.cellcal_camera()) as camera:
            first, second = camera.capture(5.0), camera.capture(5.0)
            assert camera.info().model.startswith("O3R")
        assert first.distance.shape == (172, 224) and first.valid.mean() > 0.9
        both = first.valid & second.valid
        assert np.abs(first.distance[both] - second.distance[both]).max() < 1e-6  # noise off: the same table
        # the standalone emulator's world is the sim's default one: where its optical axis meets the table (z = 0)
        optical = SimConfig().initial_flange_pose() @ MountConfig().pose()
        truth = -optical.translation[2] / optical.rotation_matrix[2, 2]
        assert float(np.median(first.distance[84:89, 110:115])) == pytest.approx(truth, abs=0.0015)  # 1 mm steps
    assert not _alive(address.pid)  # ended and reaped
    assert _refused(address.host, address.xmlrpc_port)


def test_the_xarm_emulator_serves_cellcal_s_xarm_driver_and_its_sim_arm_moves() -> None:
    with xarm_emulator(time_scale=0.01) as address:
        assert address.report_port != XARM_SDK_REPORT_PORT
        target = address.sim_arm.true_flange_pose()
        target = target.with_translation(target.translation + np.array([0.0, 0.03, -0.02]))
        with default_registry().create_arm(address.cellcal_arm()) as arm:
            arm.move_linear(target, speed=0.2, acceleration=2.0, timeout=10.0)
            assert arm.get_pose().distance_to(target) < 0.0005
        assert address.sim_arm.true_flange_pose().distance_to(target) < 1e-6
        assert address.emulator.last_move is not None
    assert _refused(address.host, address.tcp_port) and _refused(address.host, address.report_port)


def test_the_xarm_emulator_can_serve_the_sdk_report_port() -> None:
    with xarm_emulator(sdk_report_port=True) as address:
        assert address.report_port == XARM_SDK_REPORT_PORT
        with socket.create_connection((address.host, address.report_port), timeout=2.0) as sock:
            sock.settimeout(2.0)
            assert len(sock.recv(4096)) > 0  # the rich report streams
    assert _refused(address.host, XARM_SDK_REPORT_PORT)


def test_the_ur_emulator_answers_its_dashboard_and_its_control_channel() -> None:
    with ur_emulator(time_scale=0.1) as address:
        assert address.host.startswith("127.0.0.") and address.dashboard_port == 29999
        with socket.create_connection((address.host, address.dashboard_port), timeout=5.0) as sock:
            reader = sock.makefile("r", encoding="utf-8", newline="\n")
            greeting = reader.readline()
            sock.sendall(b"robotmode\n")
            assert "Dashboard" in greeting and reader.readline().strip() == "Robotmode: RUNNING"
        assert address.process.snapshot()["robot_mode"] == 7
        assert address.process.running
    assert not address.process.running
    assert _refused(address.host, address.rtde_port)


def test_the_ur_emulator_moves_for_cellcal_s_ur_driver() -> None:
    pytest.importorskip("rtde_control")
    with ur_emulator(time_scale=0.1) as address:
        with default_registry().create_arm(address.cellcal_arm()) as arm:
            start = arm.get_pose()
            target = start.with_translation(start.translation + np.array([0.02, 0.0, 0.0]))
            arm.move_linear(target, speed=0.25, acceleration=1.2, timeout=10.0)
            assert arm.get_pose().distance_to(target) < 0.0005
        tcp = address.process.snapshot()["tcp"]
        assert Pose.from_xyz_rotvec(tcp[:3], tcp[3:]).translation == pytest.approx(target.translation, abs=5e-4)


def test_bad_emulator_arguments_are_one_line_errors() -> None:
    with pytest.raises(CellcalError, match="state must be RUN, IDLE or CONF, got 'GO'"), o3r_emulator(state="GO"):
        pass
    with pytest.raises(CellcalError, match=r"time_scale must be within \[0, 10\], got -1"), \
            xarm_emulator(time_scale=-1):
        pass
    with pytest.raises(CellcalError, match=r"time_scale must be within \[0, 10\], got 11"), ur_emulator(time_scale=11):
        pass
