"""cellcal.testing.faults: each fault makes the cell's calls fail the way CellFaults documents."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from cellcal.core.calibration.calibrator import GUARD_GRACE_S
from cellcal.devices.errors import (
    BackendOverrunError,
    CellcalError,
    DeviceConnectionError,
    DeviceTimeoutError,
    VendorError,
)
from cellcal.devices.pose import Pose
from cellcal.devices.safety import SafeArm
from cellcal.testing import SimCell, sim_cell

CAPTURE_TIMEOUT_S = 0.5
FAST = {"plan": {"perimeters_px": [20], "methods": ["plane_fit"], "capture_timeout_s": CAPTURE_TIMEOUT_S,
                 "move_timeout_s": 1.5}}


@pytest.fixture
def cell() -> Iterator[SimCell]:
    with sim_cell(tables=FAST) as c:
        yield c


def _down(arm: SafeArm, drop_m: float = 0.02) -> Pose:
    start = arm.get_pose()
    return start.with_translation(start.translation + np.array([0.0, 0.0, -drop_m]))


def test_camera_timeout_hits_exactly_the_captures_counted_from_arming(cell: SimCell) -> None:
    with cell.camera:
        cell.camera.capture(1.0)  # before arming: not counted
        cell.faults.camera_timeout(capture=2, count=2)
        outcomes = []
        for _ in range(4):
            try:
                cell.camera.capture(1.0)
                outcomes.append("frame")
            except DeviceTimeoutError as exc:
                assert "injected fault" in str(exc)
                outcomes.append("timeout")
    assert outcomes == ["frame", "timeout", "timeout", "frame"]
    assert cell.faults.fired == {"camera_timeout": 2}


def test_camera_disconnect_and_failed_connects(cell: SimCell) -> None:
    cell.faults.camera_connect_fails(connect=1)
    with pytest.raises(DeviceConnectionError, match="connection refused"):
        cell.camera.connect(1.0)
    assert not cell.camera.connected
    cell.camera.connect(1.0)  # the second connect is not faulted
    cell.faults.camera_disconnect(capture=1)
    with pytest.raises(DeviceConnectionError, match="connection lost"):
        cell.camera.capture(1.0)
    assert cell.camera.capture(1.0).valid.mean() > 0.9


def test_blank_frames_have_no_valid_pixel_and_the_view_comes_back(cell: SimCell) -> None:
    mount = cell.world.mount
    with cell.camera:
        cell.faults.blank_frame(capture=1, count=2)
        valid = [float(cell.camera.capture(1.0).valid.mean()) for _ in range(3)]
    assert valid[:2] == [0.0, 0.0] and valid[2] > 0.9
    assert cell.world.mount.is_close(mount)


def test_clear_gives_the_mount_back_and_disarms(cell: SimCell) -> None:
    mount = cell.world.mount
    with cell.camera:
        cell.faults.blank_frame(capture=1)
        cell.faults.camera_timeout(capture=2)
        assert cell.camera.capture(1.0).valid.sum() == 0
        cell.faults.clear()
        assert cell.world.mount.is_close(mount)
        assert cell.camera.capture(1.0).valid.mean() > 0.9  # the timeout was disarmed
    assert cell.camera.fault_hook is None  # type: ignore[attr-defined]


def test_camera_stall_holds_the_capture_and_the_calibrator_abandons_it(cell: SimCell) -> None:
    with cell.camera:
        cell.faults.camera_stall(0.3, capture=1)
        start = time.monotonic()
        cell.camera.capture(1.0)
        assert time.monotonic() - start >= 0.3
    stall_s = CAPTURE_TIMEOUT_S + GUARD_GRACE_S + 1.0
    cell.faults.camera_stall(stall_s, capture=1)
    threads = set(threading.enumerate())
    start = time.monotonic()
    with pytest.raises(BackendOverrunError, match="camera backend 'sim'"):
        cell.calibrator().run()
    assert time.monotonic() - start < stall_s + 0.5  # ended by the guard, not by the stall
    assert cell.sim_arm is not None and cell.sim_arm.stops >= 1  # the arm was told to stop
    # the abandoned capture ends when its stall does: leave no thread behind for later tests
    for thread in set(threading.enumerate()) - threads:
        thread.join(stall_s + 2.0)
        assert not thread.is_alive()


def test_arm_stall_times_out_at_the_motion_timeout_and_the_arm_stands(cell: SimCell) -> None:
    with cell.arm:
        cell.faults.arm_stall(move=1)
        start = time.monotonic()
        with pytest.raises(DeviceTimeoutError, match=r"did not finish within 0\.4 s"):
            cell.arm.move_linear(_down(cell.arm), speed=0.1, acceleration=1.0, timeout=0.4)
        assert 0.4 <= time.monotonic() - start < 3.0
        assert cell.sim_arm is not None and not cell.sim_arm.is_moving()
        target = _down(cell.arm)
        cell.arm.move_linear(target, speed=0.1, acceleration=1.0, timeout=2.0)  # the next move is not faulted
        assert cell.arm.get_pose().distance_to(target) < 0.001


def test_arm_error_latches_until_cleared(cell: SimCell) -> None:
    with cell.arm:
        cell.faults.arm_error(code=31, move=1)
        with pytest.raises(VendorError, match="31"):
            cell.arm.move_linear(_down(cell.arm), speed=0.1, acceleration=1.0, timeout=2.0)
        assert cell.arm.status().error_code == 31
        cell.arm.clear_errors()
        target = _down(cell.arm)
        cell.arm.move_linear(target, speed=0.1, acceleration=1.0, timeout=2.0)
        assert cell.arm.get_pose().distance_to(target) < 0.001


def test_arm_disconnect_and_failed_connect(cell: SimCell) -> None:
    cell.faults.arm_connect_fails()
    with pytest.raises(DeviceConnectionError, match="sim arm: connection refused"):
        cell.arm.connect(1.0)
    with cell.arm:
        cell.faults.arm_disconnect(move=2)
        cell.arm.move_linear(_down(cell.arm), speed=0.1, acceleration=1.0, timeout=2.0)
        with pytest.raises(DeviceConnectionError, match="move 2"):
            cell.arm.move_linear(_down(cell.arm), speed=0.1, acceleration=1.0, timeout=2.0)
    assert cell.faults.fired == {"arm_connect_fails": 1, "arm_disconnect": 1}


def test_a_calibration_meets_a_lost_camera_at_the_second_pose(cell: SimCell) -> None:
    cell.faults.camera_disconnect(capture=2)
    with pytest.raises(DeviceConnectionError, match="capture 2"):
        cell.calibrator().run()
    assert cell.sim_arm is not None and cell.sim_arm.moves_started == 2 and cell.sim_arm.stops >= 1
    assert not cell.camera.connected and not cell.arm.connected  # the calibrator closed both


@pytest.mark.parametrize(("arm_fault", "message"), [
    (lambda f: f.camera_timeout(capture=0), "capture number must be an integer >= 1, got 0"),
    (lambda f: f.blank_frame(count=0), "count must be an integer >= 1, got 0"),
    (lambda f: f.camera_stall(0.0), r"seconds must be within \(0, 600\] s, got 0.0"),
    (lambda f: f.arm_error(code=0), r"code must be within \[1, 65535\], got 0"),
])
def test_bad_fault_arguments_are_one_line_errors(cell: SimCell, arm_fault: object, message: str) -> None:
    with pytest.raises(CellcalError, match=message) as err:
        arm_fault(cell.faults)  # type: ignore[operator]
    assert "\n" not in str(err.value)
