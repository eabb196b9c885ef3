"""The safety envelope between a move's endpoints, at its exact boundaries, and in its messages.

Each case is checked against an independent dense re-sampling of the true path (scipy's
Slerp on 4001 points, written here), so the tests hold for any sampling the envelope uses
as long as it is dense enough to see what a controller would do.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp
from test_safety import DOWN, RecordingArm

from cellcal.devices import Pose, SafetyError
from cellcal.devices.arrival import MAX_ANGLE_TOLERANCE_RAD, MAX_POSITION_TOLERANCE_M, ArrivalTolerance
from cellcal.devices.safety import SafeArm, SafetyLimits

MOUNT_X = Pose.from_xyz_rpy([0.3, 0.0, 0.0], [0.0, 0.0, 0.0])  # camera 0.3 m along the flange's x
BOX = SafetyLimits((-1.0, -1.0, 0.3), (1.0, 1.0, 1.0), 1.0, 1.0, mount=MOUNT_X)


def about_y(angle_rad: float) -> Rotation:
    return Rotation.from_rotvec([0.0, angle_rad, 0.0])


def true_camera_path(limits: SafetyLimits, start: Pose, target: Pose, n: int = 4001) -> NDArray[np.float64]:
    """Camera positions along the move, densely: linear translation, slerped orientation."""
    s = np.linspace(0.0, 1.0, n)
    rots = Slerp([0.0, 1.0], Rotation.concatenate([start.rotation, target.rotation]))(s)
    flange = start.translation[None, :] + s[:, None] * (target.translation - start.translation)[None, :]
    return flange + rots.apply(np.array(limits.mount.translation))


def reported_point(message: str, what: str) -> NDArray[np.float64]:
    """The (x, y, z) a violation message names for ``what`` ("flange" or "camera")."""
    m = re.search(rf"{what} leaves the workspace box on the (?:path|target) at \(([^)]*)\) m", message)
    assert m, message
    return np.array([float(v) for v in m.group(1).split(",")])


def test_a_rotation_in_place_that_swings_the_camera_out_of_the_box_is_refused() -> None:
    """The issue's case: both endpoints inside, the camera dips below z = 0.3 m on the way."""
    start = Pose(about_y(0.0), [0.0, 0.0, 0.58])
    target = Pose(about_y(0.95 * math.pi), [0.0, 0.0, 0.58])
    assert BOX.violations(None, start, 0.1, 0.1) == [] and BOX.violations(None, target, 0.1, 0.1) == []
    truth = true_camera_path(BOX, start, target)
    assert truth[:, 2].min() < 0.3 - 0.01  # the independent path does leave, by 1.5 cm
    problems = BOX.violations(start, target, 0.1, 0.1)
    assert len(problems) == 1 and problems[0].startswith("camera leaves the workspace box on the path at (")
    p = reported_point(problems[0], "camera")
    assert p[2] < 0.3  # the named point is outside the box ...
    assert np.min(np.linalg.norm(truth - p, axis=1)) < 5e-4  # ... and on the true path (message rounds to 0.1 mm)
    with pytest.raises(SafetyError, match=r"^move to xyz=\(0\.0000, 0\.0000, 0\.5800\) m .* rejected: camera leaves"):
        BOX.check(start, target, 0.1, 0.1)


def test_a_short_excursion_on_a_long_move_is_seen() -> None:
    """The camera dips 0.5 mm below the box for 4 % of a 0.6 m move: sampling must be dense enough."""
    z = 0.3 + 0.3 - 0.0005  # lowest camera point: flange z - 0.3 m (at 90 deg about y)
    start = Pose(about_y(0.05 * math.pi), [0.0, -0.3, z])
    target = Pose(about_y(0.95 * math.pi), [0.0, 0.3, z])
    truth = true_camera_path(BOX, start, target)
    below = truth[:, 2] < 0.3
    assert 0.02 < below.mean() < 0.06 and not below[0] and not below[-1]
    problems = BOX.violations(start, target, 0.1, 0.1)
    assert len(problems) == 1, problems
    p = reported_point(problems[0], "camera")
    assert p[2] < 0.3 and np.min(np.linalg.norm(truth - p, axis=1)) < 5e-4


def test_a_path_excursion_is_refused_by_the_wrapper_and_by_the_plan_check() -> None:
    """SafeArm checks from the arm's current pose; a plan from each previous pose."""
    inside_a = Pose(about_y(0.0), [0.0, 0.0, 0.58])
    inside_b = Pose(about_y(0.95 * math.pi), [0.0, 0.0, 0.58])
    inner = RecordingArm(inside_a)
    with SafeArm(inner, BOX) as arm, pytest.raises(SafetyError, match="camera leaves the workspace box on the path"):
        arm.move_linear(inside_b, speed=0.1, acceleration=0.1)
    assert inner.commands == []
    # each pose is safe from the one before except the last, which swings back the long way round
    plan = [Pose(about_y(0.0), [0.0, 0.0, 0.65]), inside_a, inside_b]
    with pytest.raises(SafetyError, match=r"^plan pose 3 \(.*camera leaves the workspace box on the path"):
        BOX.check_plan(inside_a, plan, 0.1, 0.1)
    BOX.check_plan(inside_a, plan[:2], 0.1, 0.1)  # the first two moves are fine
    # the first move of a plan is checked from where the arm is, not from its target alone
    with pytest.raises(SafetyError, match=r"^plan pose 1 \(.*camera leaves the workspace box on the path"):
        BOX.check_plan(inside_a, [inside_b], 0.1, 0.1)
    BOX.check_plan(None, [inside_b], 0.1, 0.1)  # without a start pose only the target can be checked


def test_a_target_outside_names_where_the_move_leaves_the_box() -> None:
    limits = SafetyLimits((-1.0, -1.0, 0.3), (1.0, 1.0, 1.0), 1.0, 1.0)  # camera at the flange
    above = Pose(DOWN, [0.2, 0.1, 0.5])
    # the target alone: "on the target", at the target
    assert limits.violations(None, Pose(DOWN, [0.2, 0.1, 0.1]), 0.1, 0.1) == [
        f"{what} leaves the workspace box on the target at (0.2000, 0.1000, 0.1000) m" for what in ("flange", "camera")]
    # a long way down: the first point below the floor, within one sampling step (5 mm) of it
    problems = limits.violations(above, Pose(DOWN, [0.2, 0.1, 0.1]), 0.1, 0.1)
    assert [p.split(" on the ")[1][:4] for p in problems] == ["path", "path"]  # flange, then camera
    p = reported_point(problems[0], "flange")
    assert p[0] == pytest.approx(0.2) and p[1] == pytest.approx(0.1) and 0.295 <= p[2] < 0.3
    # 1.5 mm past the floor, approached over 15 mm: the path is outside before the target is
    near = Pose(DOWN, [0.2, 0.1, 0.3135])
    assert limits.violations(near, Pose(DOWN, [0.2, 0.1, 0.2985]), 0.1, 0.1)[0].startswith(
        "flange leaves the workspace box on the path at (0.2000, 0.1000, 0.299")


def test_the_box_faces_speed_and_acceleration_maxima_are_allowed_exactly() -> None:
    limits = SafetyLimits((-0.5, -0.25, 0.125), (0.5, 0.25, 0.875), 0.5, 2.0)  # camera at the flange
    corners = [Pose(DOWN, [-0.5, -0.25, 0.125]), Pose(DOWN, [0.5, 0.25, 0.875])]
    assert limits.violations(corners[0], corners[1], 0.5, 2.0) == []  # a diagonal from corner to corner
    assert limits.violations(corners[1], corners[0], 0.5, 2.0) == []
    assert limits.violations(None, Pose(DOWN, [0.5 + 1e-9, 0.0, 0.5]), 0.5, 2.0) != []
    assert limits.violations(None, Pose(DOWN, [0.0, -0.25 - 1e-9, 0.5]), 0.5, 2.0) != []
    assert limits.violations(None, corners[1], math.nextafter(0.5, 1.0), 2.0) == [
        "speed 0.5 m/s exceeds max 0.5 m/s"]
    assert limits.violations(None, corners[1], 0.5, math.nextafter(2.0, 3.0)) == [
        "acceleration 2 m/s^2 exceeds max 2 m/s^2"]


def test_standoff_is_measured_from_the_plane_point_along_the_unit_normal() -> None:
    # plane z = 0.125 m given by a non-unit normal; the camera may come to exactly 0.25 m above it
    limits = SafetyLimits((-1.0, -1.0, 0.0), (1.0, 1.0, 1.0), 1.0, 1.0, min_standoff_m=0.25,
                          plane_point_m=(0.4, -0.3, 0.125), plane_normal=(0.0, 0.0, 2.5))
    assert limits.violations(None, Pose(DOWN, [0.0, 0.0, 0.375]), 0.1, 0.1) == []
    assert limits.violations(None, Pose(DOWN, [0.0, 0.0, 0.75]), 0.1, 0.1) == []
    (problem,) = limits.violations(None, Pose(DOWN, [0.0, 0.0, 0.3125]), 0.1, 0.1)
    assert problem == "camera comes within 0.1875 m of the measuring plane (min standoff 0.2500 m)"
    # along a move the closest approach counts, not the endpoints
    tilted = SafetyLimits((-1.0, -1.0, 0.0), (1.0, 1.0, 1.0), 1.0, 1.0, min_standoff_m=0.2,
                          plane_point_m=(0.0, 0.0, 0.0), plane_normal=(0.0, 0.0, 1.0), mount=MOUNT_X)
    start, target = Pose(about_y(0.0), [0.0, 0.0, 0.45]), Pose(about_y(0.95 * math.pi), [0.0, 0.0, 0.45])
    assert tilted.violations(None, start, 0.1, 0.1) == [] and tilted.violations(None, target, 0.1, 0.1) == []
    (problem,) = tilted.violations(start, target, 0.1, 0.1)
    assert problem.startswith("camera comes within 0.15") and problem.endswith("(min standoff 0.2000 m)")


def test_every_problem_is_named_in_one_line() -> None:
    with pytest.raises(SafetyError) as info:
        BOX.check(None, Pose(about_y(0.0), [0.0, 0.0, 1.5]), 2.0, 0.5)
    assert str(info.value) == ("move to xyz=(0.0000, 0.0000, 1.5000) m rpy=(0.00, 0.00, 0.00) deg rejected: "
                               "speed 2 m/s exceeds max 1 m/s; "
                               "flange leaves the workspace box on the target at (0.0000, 0.0000, 1.5000) m; "
                               "camera leaves the workspace box on the target at (0.3000, 0.0000, 1.5000) m")
    with pytest.raises(SafetyError) as plan:
        BOX.check_plan(None, [Pose(about_y(0.0), [0.0, 0.0, 0.5]), Pose(about_y(0.0), [0.0, 0.0, 1.5])], 0.1, 1.0)
    assert str(plan.value).startswith("plan pose 2 (xyz=(0.0000, 0.0000, 1.5000) m rpy=(0.00, 0.00, 0.00) deg) "
                                      "rejected: flange leaves the workspace box on the path at (0.0000, 0.0000, 1.00")
    assert "; camera leaves the workspace box on the path at (0.3000, 0.0000, 1.00" in str(plan.value)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"workspace_min_m": (0.0, 0.0)}, "workspace corners must be 3 finite numbers each (metres)"),
    ({"workspace_max_m": (1.0, 1.0)}, "workspace corners must be 3 finite numbers each (metres)"),
    ({"workspace_min_m": (math.nan, 0.0, 0.0)}, "workspace corners must be 3 finite numbers each (metres)"),
    ({"workspace_max_m": (1.0, math.inf, 1.0)}, "workspace corners must be 3 finite numbers each (metres)"),
    ({"min_standoff_m": -0.1}, "min_standoff_m must be >= 0, got -0.1"),
    ({"min_standoff_m": math.inf}, "min_standoff_m must be >= 0, got inf"),
    ({"plane_point_m": (0.0, 0.0, 0.0)}, "plane_point_m and plane_normal must be given together"),
    ({"plane_normal": (0.0, 0.0, 1.0)}, "plane_point_m and plane_normal must be given together"),
    ({"plane_point_m": (0.0, 0.0, 0.0), "plane_normal": (0.0, 0.0, 0.0)}, "plane_normal must be non-zero"),
    ({"max_acceleration_m_s2": math.inf}, "max_acceleration_m_s2 must be positive and finite, got inf"),
])
def test_limits_refuse_what_no_envelope_can_be(kwargs: dict[str, object], message: str) -> None:
    args: dict[str, object] = {"workspace_min_m": (0.0, 0.0, 0.0), "workspace_max_m": (1.0, 1.0, 1.0),
                               "max_speed_m_s": 1.0, "max_acceleration_m_s2": 1.0, **kwargs}
    with pytest.raises(SafetyError) as info:
        SafetyLimits(**args)  # type: ignore[arg-type]
    assert str(info.value) == message


class TimedArm(RecordingArm):
    """Records the timeout of every pose read and motion command it is given."""

    def __init__(self, start: Pose) -> None:
        super().__init__(start)
        self.read_timeouts: list[float] = []
        self.move_timeouts: list[float] = []

    def _get_pose(self, timeout: float) -> Pose:
        self.read_timeouts.append(timeout)
        return self.pose

    def _move_linear(self, pose: Pose, speed: float, acceleration: float, timeout: float) -> None:
        self.move_timeouts.append(timeout)
        super()._move_linear(pose, speed, acceleration, timeout)


def test_the_wrapper_bounds_its_start_read_and_hands_the_move_timeout_down() -> None:
    start = Pose(DOWN, [0.3, 0.0, 0.6])
    inner = TimedArm(start)
    limits = SafetyLimits((-1.0, -1.0, 0.1), (1.0, 1.0, 1.0), 1.0, 1.0)
    with SafeArm(inner, limits) as arm:
        arm.move_linear(Pose(DOWN, [0.3, 0.1, 0.6]), speed=0.1, acceleration=0.1, timeout=0.25)
        assert inner.read_timeouts[0] == 0.25 and inner.move_timeouts == [0.25]
        inner.read_timeouts.clear()
        arm.move_linear(start, speed=0.1, acceleration=0.1, timeout=1000.0)
        assert inner.read_timeouts[0] == arm.default_timeout_s < 1000.0


def test_the_largest_arrival_tolerances_are_allowed_exactly() -> None:
    limits = SafetyLimits((-1.0, -1.0, 0.1), (1.0, 1.0, 1.0), 1.0, 1.0, arrival_tolerance_m=MAX_POSITION_TOLERANCE_M,
                          arrival_tolerance_rad=MAX_ANGLE_TOLERANCE_RAD)
    assert (limits.arrival_tolerance_m, limits.arrival_tolerance_rad) == (MAX_POSITION_TOLERANCE_M,
                                                                          MAX_ANGLE_TOLERANCE_RAD)
    with pytest.raises(SafetyError, match="arrival_tolerance_m must be in"):
        SafetyLimits((-1.0, -1.0, 0.1), (1.0, 1.0, 1.0), 1.0, 1.0,
                     arrival_tolerance_m=math.nextafter(MAX_POSITION_TOLERANCE_M, 1.0))


@pytest.mark.parametrize(("metres", "radians", "expected"), [
    (0.0004, None, ArrivalTolerance(position_m=0.0004)),
    (None, 0.0005, ArrivalTolerance(angle_rad=0.0005)),
    (0.0002, 0.0003, ArrivalTolerance(position_m=0.0002, angle_rad=0.0003)),
])
def test_each_arrival_tolerance_given_reaches_the_arm(metres: float | None, radians: float | None,
                                                      expected: ArrivalTolerance) -> None:
    limits = SafetyLimits((-1.0, -1.0, 0.1), (1.0, 1.0, 1.0), 1.0, 1.0, arrival_tolerance_m=metres,
                          arrival_tolerance_rad=radians)
    inner = RecordingArm(Pose(DOWN, [0.3, 0.0, 0.6]))
    SafeArm(inner, limits)
    assert inner.arrival_tolerance == expected
