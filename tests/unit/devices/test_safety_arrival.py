"""Arrival as part of the RobotArm contract: a finished move must read back steady and at its target.

The rule lives in the base class, so every backend gets it; wrappers leave it to the arm
they wrap and hand the configured ``[safety]`` tolerance down to it.
"""

from __future__ import annotations

import copy
import math
import tomllib
from importlib import resources

import numpy as np
import pytest
from test_safety import DOWN, LIMITS, START, RecordingArm

from cellcal.core.calibration.calibrator import Calibrator, build_devices
from cellcal.core.calibration.config import parse_config
from cellcal.devices.arrival import ArrivalTolerance, arrival_problem
from cellcal.devices.errors import CellcalError, ConfigError, DeviceTimeoutError, MotionError, SafetyError
from cellcal.devices.forwarding import ForwardingArm
from cellcal.devices.pose import Pose
from cellcal.devices.safety import SafeArm, SafetyLimits
from cellcal.sims.arm import SimArm

TARGET = Pose(DOWN, [0.35, 0.1, 0.5])
SIM_DOC = tomllib.loads(resources.files("cellcal.configs").joinpath("sim.toml").read_text())


class LyingArm(RecordingArm):
    """Moves as told, but its read-back is off by ``offsets[i]`` (metres, along x) on the i-th read, or fails."""

    def __init__(self, start: Pose, offsets: list[float], fail_reads: bool = False):
        super().__init__(start)
        self.offsets = offsets
        self.fail_reads = fail_reads
        self.reads = 0
        self.stops = 0

    def _get_pose(self, timeout: float) -> Pose:
        if self.fail_reads:
            raise DeviceTimeoutError("lying arm: no pose within 0.1 s")
        offset = self.offsets[min(self.reads, len(self.offsets) - 1)]
        self.reads += 1
        return Pose(self.pose.rotation, self.pose.translation + np.array([offset, 0.0, 0.0]))

    def _stop(self, timeout: float) -> None:
        self.stops += 1


def test_arrival_problem_names_the_first_offending_read() -> None:
    tol = ArrivalTolerance()
    assert arrival_problem(TARGET, [TARGET, TARGET], tol) is None
    near = Pose(TARGET.rotation, TARGET.translation + np.array([0.0009, 0.0, 0.0]))
    assert arrival_problem(TARGET, [near, near], tol) is None
    far = Pose(TARGET.rotation, TARGET.translation + np.array([0.07, 0.0, 0.0]))
    assert arrival_problem(TARGET, [far, far], tol) == (
        "pose read 1 of 2 is 70.000 mm and 0.0000 deg from the target (tolerance 1 mm / 0.1 deg), "
        "at xyz=(0.4200, 0.1000, 0.5000) m rpy=(180.00, 0.00, 0.00) deg")
    # 0.9 mm either side of the target: each read is within 1 mm, but they are 1.8 mm apart
    other = Pose(TARGET.rotation, TARGET.translation - np.array([0.0009, 0.0, 0.0]))
    assert arrival_problem(TARGET, [near, other], tol) == (
        "pose reads 1 and 2 of 2 at rest differ by 1.800 mm and 0.0000 deg (tolerance 1 mm / 0.1 deg): "
        "the reported pose is not steady")
    turned = Pose(TARGET.rotation * Pose.from_xyz_rpy([0, 0, 0], [0, 0, math.radians(0.2)]).rotation,
                  TARGET.translation)
    assert "0.2000 deg from the target" in str(arrival_problem(TARGET, [turned, turned], tol))


@pytest.mark.parametrize(("offsets", "expected"), [
    ([0.07], r"pose read 1 of 2 is 70\.000 mm"),
    ([0.0, 0.03], r"pose reads 1 and 2 of 2 at rest differ by 30\.000 mm"),
])
def test_a_move_that_does_not_read_back_at_its_target_is_a_motion_error(offsets: list[float], expected: str) -> None:
    with LyingArm(START, offsets) as arm:
        with pytest.raises(MotionError, match=f"^recording: move to xyz=.* reported done, but {expected}") as err:
            arm.move_linear(TARGET, speed=0.1, acceleration=1.0, timeout=1.0)
        assert str(err.value).endswith("; the arm was told to stop")
        assert arm.stops == 1 and len(arm.commands) == 1 and arm.reads == 2


def test_an_arrival_that_cannot_be_read_back_is_a_motion_error() -> None:
    with LyingArm(START, [0.0], fail_reads=True) as arm:
        with pytest.raises(MotionError, match=r"the pose could not be read back \(lying arm: no pose within 0\.1 s\)"):
            arm.move_linear(TARGET, speed=0.1, acceleration=1.0, timeout=1.0)
        assert arm.stops == 1


def test_wrappers_leave_the_check_to_the_arm_they_wrap_and_hand_the_tolerance_down() -> None:
    inner = LyingArm(START, [0.0004])  # 0.4 mm off: within the default 1 mm
    limits = SafetyLimits(LIMITS.workspace_min_m, LIMITS.workspace_max_m, 0.5, 2.0, mount=LIMITS.mount,
                          arrival_tolerance_m=0.0003)
    with SafeArm(ForwardingArm(inner), limits) as arm:
        assert inner.arrival_tolerance == ArrivalTolerance(position_m=0.0003)  # the angle stays the inner's
        assert arm.arrival_tolerance is inner.arrival_tolerance
        with pytest.raises(MotionError, match=r"0\.400 mm .*\(tolerance 0\.3 mm / 0\.1 deg\)"):
            arm.move_linear(TARGET, speed=0.1, acceleration=1.0, timeout=1.0)
        # one check only, by the inner arm: SafeArm's start pose + its two arrival reads
        assert inner.reads == 3 and inner.stops == 1
        arm.arrival_tolerance = ArrivalTolerance(position_m=0.001, angle_rad=0.01, reads=3)
        inner.reads = 0
        arm.move_linear(START, speed=0.1, acceleration=1.0, timeout=1.0)
        assert inner.reads == 1 + 3


def test_safety_limits_refuse_arrival_tolerances_no_cell_has() -> None:
    for bad in (0.0, -1e-3, 0.2, math.nan, math.inf):
        with pytest.raises(SafetyError, match="arrival_tolerance_m must be in"):
            SafetyLimits((0, 0, 0), (1, 1, 1), 1.0, 1.0, arrival_tolerance_m=bad)
    with pytest.raises(SafetyError, match="arrival_tolerance_rad must be in"):
        SafetyLimits((0, 0, 0), (1, 1, 1), 1.0, 1.0, arrival_tolerance_rad=1.0)
    with pytest.raises(CellcalError, match="reads must be an integer in"):
        ArrivalTolerance(reads=1)


# ---------------------------------------------------------------- [safety] in the cell config
def _doc(**safety: object) -> dict[str, object]:
    doc = copy.deepcopy(SIM_DOC)
    doc["safety"].update(safety)
    return doc


def test_safety_section_sets_the_arrival_tolerance_of_the_backend() -> None:
    config = parse_config(_doc(arrival_tolerance_m=0.002, arrival_tolerance_deg=0.5), "<test>")
    limits = config.safety_limits()
    assert limits.arrival_tolerance_m == 0.002 and limits.arrival_tolerance_rad == pytest.approx(math.radians(0.5))
    _camera, arm = build_devices(config)
    assert isinstance(arm.inner, SimArm)
    assert arm.inner.arrival_tolerance == ArrivalTolerance(position_m=0.002, angle_rad=math.radians(0.5))
    unset = parse_config(_doc(), "<test>")
    assert unset.safety_limits().arrival_tolerance_m is None
    assert build_devices(unset)[1].inner.arrival_tolerance == ArrivalTolerance()


@pytest.mark.parametrize(("key", "value"), [
    ("arrival_tolerance_m", 0.5), ("arrival_tolerance_m", 0.0), ("arrival_tolerance_deg", 45.0),
    ("max_speed_m_s", 5e-324), ("max_acceleration_m_s2", 1e-9), ("min_standoff_m", 1e308),
    ("workspace_max_m", [0.7, 0.5, 1e308]), ("workspace_min_m", [-1e308, -0.5, 0.05]),
])
def test_safety_quantities_outside_a_real_cell_are_refused(key: str, value: object) -> None:
    with pytest.raises(ConfigError, match=f"key 'safety.{key}"):
        parse_config(_doc(**{key: value}), "<test>")


def test_the_calibrator_stops_the_arm_on_a_motion_error(tmp_path: object) -> None:
    config = parse_config(_doc(), "<test>")
    camera, arm = build_devices(config)
    sim = arm.inner
    assert isinstance(sim, SimArm)
    sim.faults.stop_short_m = 0.07
    with pytest.raises(MotionError, match=r"^sim: move to .* reported done, but pose read 1 of 2 is \d+\.\d+ mm"):
        Calibrator(config, camera, arm).run()
    assert sim.stops >= 2  # by the arrival check, then by the calibrator
    assert sim.moves_started == 1 and not sim.is_moving()
