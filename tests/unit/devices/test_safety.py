"""The safety envelope: nothing outside it ever reaches a backend."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cellcal.devices import ArmStatus, DeviceInfo, Pose, RobotArm, SafetyError
from cellcal.devices.safety import SafeArm, SafetyLimits

LIMITS = SafetyLimits(
    workspace_min_m=(-0.1, -0.5, 0.05),
    workspace_max_m=(0.7, 0.5, 0.9),
    max_speed_m_s=0.5,
    max_acceleration_m_s2=2.0,
    min_standoff_m=0.2,
    plane_point_m=(0.0, 0.0, 0.0),
    plane_normal=(0.0, 0.0, 1.0),
    mount=Pose.from_xyz_rpy([0.0, 0.04, 0.06], [0.0, 0.0, math.pi / 2]),
)
DOWN = Rotation.from_euler("xyz", [math.pi, 0.0, 0.0])


class RecordingArm(RobotArm):
    """A backend that records every motion command and moves instantly.

    With a non-zero ``error_code`` it reports that controller error (a protective
    stop) and does not move, until its errors are cleared.
    """

    backend_name = "recording"

    def __init__(self, start: Pose, error_code: int = 0):
        super().__init__()
        self.pose = start
        self.start = start
        self.error_code = error_code
        self.commands: list[tuple[Pose, float, float]] = []

    def _connect(self, timeout: float) -> None: ...
    def _close(self) -> None: ...

    def _info(self) -> DeviceInfo:
        return DeviceInfo("recording", "test", "recording arm")

    def _get_pose(self, timeout: float) -> Pose:
        return self.pose

    def _move_linear(self, pose: Pose, speed: float, acceleration: float, timeout: float) -> None:
        self.commands.append((pose, speed, acceleration))
        if not self.error_code:
            self.pose = pose

    def _stop(self, timeout: float) -> None: ...

    def _joint_positions(self, timeout: float) -> NDArray[np.float64]:
        return np.zeros(6)

    def _status(self, timeout: float) -> ArmStatus:
        return ArmStatus(self.error_code, 0, "protective stop" if self.error_code else "", self.error_code == 0)

    def _clear_errors(self, timeout: float) -> None:
        self.error_code = 0


def inside(limits: SafetyLimits, start: Pose, target: Pose, speed: float, acc: float) -> bool:
    """Independent re-check of a command: dense path sampling, flange and camera."""
    if speed > limits.max_speed_m_s or acc > limits.max_acceleration_m_s2:
        return False
    lo, hi = np.array(limits.workspace_min_m), np.array(limits.workspace_max_m)
    for s in np.linspace(0, 1, 101):
        rot = Rotation.from_rotvec(s * (target.rotation * start.rotation.inv()).as_rotvec()) * start.rotation
        flange = Pose(rot, start.translation + s * (target.translation - start.translation))
        cam = flange @ limits.mount
        for p in (flange.translation, cam.translation):
            if np.any(p < lo - 1e-9) or np.any(p > hi + 1e-9):
                return False
        if cam.translation[2] < limits.min_standoff_m - 1e-9:
            return False
    return True


START = Pose(DOWN, [0.3, 0.0, 0.6])


def test_safe_move_is_forwarded() -> None:
    inner = RecordingArm(START)
    target = Pose(DOWN, [0.35, 0.1, 0.5])
    with SafeArm(inner, LIMITS) as arm:
        arm.move_linear(target, speed=0.3, acceleration=1.0)
    assert len(inner.commands) == 1 and inner.commands[0][0].is_close(target)


@pytest.mark.parametrize(
    ("target", "speed", "acc", "expected"),
    [
        (Pose(DOWN, [0.8, 0.0, 0.5]), 0.1, 1.0, "flange leaves the workspace box"),
        (Pose(DOWN, [0.3, 0.0, 0.22]), 0.1, 1.0, "of the measuring plane"),
        (Pose(DOWN, [0.3, 0.0, 0.5]), 0.9, 1.0, "speed 0.9 m/s exceeds max 0.5 m/s"),
        (Pose(DOWN, [0.3, 0.0, 0.5]), 0.1, 3.0, r"acceleration 3 m/s\^2 exceeds max 2 m/s\^2"),
    ],
)
def test_violations_are_rejected_before_anything_moves(target: Pose, speed: float, acc: float, expected: str) -> None:
    inner = RecordingArm(START)
    with SafeArm(inner, LIMITS) as arm, pytest.raises(SafetyError, match=expected) as info:
        arm.move_linear(target, speed=speed, acceleration=acc)
    assert inner.commands == []
    assert "rejected" in str(info.value) and "\n" not in str(info.value)


def test_camera_outside_box_while_flange_inside() -> None:
    # the camera hangs 0.06 m below the flange: a flange at z=0.1 puts it at 0.04 < 0.05
    limits = SafetyLimits((-1, -1, 0.05), (1, 1, 1), 1.0, 1.0, mount=LIMITS.mount)
    assert any("camera leaves" in v for v in limits.violations(None, Pose(DOWN, [0, 0, 0.1]), 0.1, 0.1))


def test_plan_check_names_the_offending_pose() -> None:
    poses = [Pose(DOWN, [0.3, 0.0, 0.6]), Pose(DOWN, [0.3, 0.0, 0.5]), Pose(DOWN, [0.3, 0.6, 0.5])]
    with pytest.raises(SafetyError, match=r"plan pose 3 \(xyz=\(0.3000, 0.6000, 0.5000\)"):
        LIMITS.check_plan(START, poses, 0.1, 1.0)


poses_st = st.builds(
    lambda xyz, rv: Pose(Rotation.from_rotvec(rv) * DOWN, xyz),
    st.lists(st.floats(-0.4, 1.0), min_size=3, max_size=3),
    st.lists(st.floats(-0.6, 0.6), min_size=3, max_size=3),
)


@settings(max_examples=150, deadline=None)
@given(plan=st.lists(poses_st, min_size=1, max_size=6), speed=st.floats(0.01, 1.0), acc=st.floats(0.01, 4.0))
def test_random_plans_never_send_a_command_outside_the_envelope(plan: list[Pose], speed: float, acc: float) -> None:
    inner = RecordingArm(START)
    with SafeArm(inner, LIMITS) as arm:
        for target in plan:
            start = inner.pose
            try:
                arm.move_linear(target, speed=speed, acceleration=acc)
            except SafetyError:
                assert inner.pose is start  # nothing moved
    prev = START
    for pose, sp, ac in inner.commands:
        assert inside(LIMITS, prev, pose, sp, ac), f"unsafe command reached the backend: {pose}"
        prev = pose


def test_limits_validate_themselves() -> None:
    with pytest.raises(SafetyError, match="workspace_min_m"):
        SafetyLimits((0, 0, 0), (1, 1, 0), 1.0, 1.0)
    with pytest.raises(SafetyError, match="max_speed_m_s"):
        SafetyLimits((0, 0, 0), (1, 1, 1), 0.0, 1.0)


def test_plan_check_numbers_poses_from_first_index() -> None:
    """A resumed run checks only the poses still to do; messages keep their plan numbers."""
    poses = [Pose(DOWN, [0.3, 0.0, 0.6]), Pose(DOWN, [0.3, 0.6, 0.5]), Pose(DOWN, [0.3, 0.0, 0.5])]
    with pytest.raises(SafetyError) as default:
        LIMITS.check_plan(START, poses, 0.1, 1.0)
    with pytest.raises(SafetyError, match=r"^plan pose 5 \(xyz=\(0.3000, 0.6000, 0.5000\)") as shifted:
        LIMITS.check_plan(START, poses, 0.1, 1.0, first_index=4)
    assert str(default.value).startswith("plan pose 2 (")
    assert str(shifted.value) == str(default.value).replace("plan pose 2", "plan pose 5", 1)
    LIMITS.check_plan(START, poses[:1], 0.1, 1.0, first_index=7)  # a safe sequence passes whatever its numbering
