"""Conformance checks for :class:`~cellcal.devices.arm.RobotArm` backends.

Every check takes a *factory* — a zero-argument callable that returns a new,
unconnected arm — and :class:`ArmOptions`. The arm must start at rest, free of
errors, with room for a small move: the round trip goes ``step_m`` (base frame)
away from the start pose, turned ``step_rotation_rad`` about the flange z axis, and
back. Run it against a simulator or emulator, or on a real arm with a clear cell.

The arrival rule (ADR 0016) also fakes a move that stops short: for one move it shifts
what the backend's ``_get_pose`` hook reads back by :data:`FAKE_SHORTFALL_M` and requires
``move_linear`` to raise :class:`~cellcal.devices.errors.MotionError` and to tell the arm
to stop (the arm really moves by the round-trip step only). For a wrapper
(``verifies_arrival`` false) the hooks of the arm it wraps are shifted; an arm that
checks nothing and wraps nothing (a replay) moves nothing, and skips this part.
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from cellcal.devices.arm import RobotArm
from cellcal.devices.errors import CellcalError, DeviceTimeoutError, MotionError
from cellcal.devices.pose import Pose
from cellcal.devices.types import ArmStatus

from ._runner import (
    Check,
    ConformanceReport,
    Violation,
    check_bad_connect_timeouts,
    check_bad_timeouts,
    check_stalled,
    connected,
    expect,
    raises,
    run_checks,
    timed,
)
from .lifecycle import CommonOptions, lifecycle_checks

Factory = Callable[[], RobotArm]

#: How far the arrival rule shifts the read-back of one move to fake an arm that stopped short, metres.
FAKE_SHORTFALL_M = 0.07
#: Pose reads the arrival rule takes at rest after a move.
ARRIVAL_READS = 3


@dataclass(frozen=True)
class ArmOptions(CommonOptions):
    """What the kit may assume about an arm backend under test.

    Attributes:
        io_timeout_s: Timeout of reads (pose, joints, status) and ``stop()``, seconds.
        motion_timeout_s: Timeout of each ``move_linear``, seconds.
        step_m: Translation of the round-trip target from the start pose, base frame, metres.
        step_rotation_rad: Rotation of the round-trip target about the flange z axis, radians.
        speed_m_s: Tool speed of the round trip, m/s.
        acceleration_m_s2: Tool acceleration of the round trip, m/s².
        pose_tolerance_m: Allowed position error after a move (and read-back noise), metres.
        pose_tolerance_rad: Allowed orientation error after a move, radians.
        max_reach_m: No flange position may be farther than this from the base origin, metres.
        joint_count: Number of joints the arm must report; None accepts any (>= 1).

    The shared attributes (``connect_timeout_s``, ``short_timeout_s``, ``timing_slack_s``,
    ``check_resources``) are described in :class:`CommonOptions`.
    """

    io_timeout_s: float = 5.0
    motion_timeout_s: float = 30.0
    step_m: tuple[float, float, float] = (0.0, 0.0, 0.02)
    step_rotation_rad: float = 0.05
    speed_m_s: float = 0.05
    acceleration_m_s2: float = 0.5
    pose_tolerance_m: float = 1e-3
    pose_tolerance_rad: float = 2e-3
    max_reach_m: float = 5.0
    joint_count: int | None = None

    def __post_init__(self) -> None:
        self._require_positive("io_timeout_s", "motion_timeout_s", "speed_m_s", "acceleration_m_s2",
                               "pose_tolerance_m", "pose_tolerance_rad", "max_reach_m")
        step = np.asarray(self.step_m, dtype=float)
        if step.shape != (3,) or not np.all(np.isfinite(step)):
            raise CellcalError(f"ArmOptions.step_m must be 3 finite numbers (metres), got {self.step_m!r}")
        tiny_turn = abs(self.step_rotation_rad) <= self.pose_tolerance_rad
        if np.linalg.norm(step) <= 10 * self.pose_tolerance_m and tiny_turn:
            raise CellcalError("ArmOptions: the round-trip step must be larger than the pose tolerance")

    def target(self, start: Pose) -> Pose:
        """The round-trip target for a start pose."""
        turn = Rotation.from_rotvec([0.0, 0.0, self.step_rotation_rad])
        return Pose(start.rotation * turn, start.translation + np.asarray(self.step_m, dtype=float))


def _pose_error(a: Pose, b: Pose) -> str:
    return f"{a.distance_to(b) * 1000:.3g} mm and {math.degrees(a.angle_to(b)):.3g} deg"


def _near(a: Pose, b: Pose, o: ArmOptions) -> bool:
    return bool(a.distance_to(b) <= o.pose_tolerance_m and a.angle_to(b) <= o.pose_tolerance_rad)


# ---------------------------------------------------------------- state
def _status(factory: Factory, o: ArmOptions) -> None:
    with connected(factory, RobotArm, o.connect_timeout_s) as arm:
        status = arm.status(o.io_timeout_s)
        expect(isinstance(status, ArmStatus), f"status() returned {type(status).__name__}, not ArmStatus")
        expect(isinstance(status.error_code, int) and isinstance(status.warning_code, int)
               and isinstance(status.message, str) and isinstance(status.can_move, bool),
               f"ArmStatus fields have the wrong types: {status!r}")
        expect(status.ok, f"a freshly connected test arm must be ready to move, status is {status!r}")
        arm.clear_errors(o.io_timeout_s)  # clearing when there is nothing to clear is harmless
        after = arm.status(o.io_timeout_s)
        expect(after.ok, f"clear_errors() on a ready arm left status {after!r}")


def _joint_positions(factory: Factory, o: ArmOptions) -> None:
    with connected(factory, RobotArm, o.connect_timeout_s) as arm:
        q = arm.joint_positions(o.io_timeout_s)
        q2 = arm.joint_positions(o.io_timeout_s)
    expect(isinstance(q, np.ndarray) and q.dtype == np.float64 and q.ndim == 1 and q.size >= 1,
           f"joint_positions() must be a 1-D float64 array, got {getattr(q, 'dtype', type(q))} "
           f"{getattr(q, 'shape', '')}")
    if o.joint_count is not None:
        expect(q.size == o.joint_count, f"joint_positions() has {q.size} values, the arm has {o.joint_count} joints")
    expect(q2.shape == q.shape, f"joint_positions() changed shape between reads: {q.shape} -> {q2.shape}")
    expect(np.all(np.isfinite(q)), f"joint positions must be finite, got {q.tolist()}")
    expect(np.all(np.abs(q) <= 2 * math.pi + 1e-6), f"joint positions {np.round(q, 4).tolist()} exceed 2 pi: "
                                                     "radians expected")


def _pose_units(factory: Factory, o: ArmOptions) -> None:
    with connected(factory, RobotArm, o.connect_timeout_s) as arm:
        p1 = arm.get_pose(o.io_timeout_s)
        p2 = arm.get_pose(o.io_timeout_s)
    expect(isinstance(p1, Pose), f"get_pose() returned {type(p1).__name__}, not Pose")
    reach = float(np.linalg.norm(p1.translation))
    expect(reach <= o.max_reach_m, f"flange at {reach:.6g} from the base origin, beyond {o.max_reach_m:g} m: "
                                   "metres expected")
    expect(_near(p1, p2, o), f"two pose reads of an arm at rest differ by {_pose_error(p1, p2)}")


# ---------------------------------------------------------------- motion
def _argument_validation(factory: Factory, o: ArmOptions) -> None:
    with connected(factory, RobotArm, o.connect_timeout_s) as arm:
        start = arm.get_pose(o.io_timeout_s)
        target = o.target(start)
        move = arm.move_linear
        raises(CellcalError, lambda: move(start.as_matrix(), speed=o.speed_m_s,  # type: ignore[arg-type]
                                          acceleration=o.acceleration_m_s2), "move_linear(<4x4 array>)")
        for bad in (0.0, -0.1, math.nan, math.inf):
            raises(CellcalError, functools.partial(move, target, speed=bad, acceleration=o.acceleration_m_s2),
                   f"move_linear(speed={bad!r})", contains="speed")
            raises(CellcalError, functools.partial(move, target, speed=o.speed_m_s, acceleration=bad),
                   f"move_linear(acceleration={bad!r})", contains="acceleration")
        now = arm.get_pose(o.io_timeout_s)
        expect(_near(now, start, o), f"rejected move commands moved the arm by {_pose_error(now, start)}")


def _pose_round_trip(factory: Factory, o: ArmOptions) -> None:
    with connected(factory, RobotArm, o.connect_timeout_s) as arm:
        start = arm.get_pose(o.io_timeout_s)
        target = o.target(start)
        arm.move_linear(target, speed=o.speed_m_s, acceleration=o.acceleration_m_s2, timeout=o.motion_timeout_s)
        reached = arm.get_pose(o.io_timeout_s)
        expect(_near(reached, target, o), f"after move_linear to a target {np.linalg.norm(o.step_m):.3g} m and "
                                          f"{o.step_rotation_rad:g} rad away, get_pose is "
                                          f"{_pose_error(reached, target)} from it (metres and radians expected)")
        arm.move_linear(start, speed=o.speed_m_s, acceleration=o.acceleration_m_s2, timeout=o.motion_timeout_s)
        back = arm.get_pose(o.io_timeout_s)
        expect(_near(back, start, o), f"after moving back, get_pose is {_pose_error(back, start)} from the start")


def _arrival(factory: Factory, o: ArmOptions) -> None:
    with connected(factory, RobotArm, o.connect_timeout_s) as arm:
        start = arm.get_pose(o.io_timeout_s)
        target = o.target(start)
        try:
            arm.move_linear(target, speed=o.speed_m_s, acceleration=o.acceleration_m_s2, timeout=o.motion_timeout_s)
        except MotionError as exc:
            raise Violation(f"move_linear to a reachable target raised MotionError: {exc}") from None
        reads = [arm.get_pose(o.io_timeout_s) for _ in range(ARRIVAL_READS)]
        for i, (a, b) in enumerate(itertools.pairwise(reads), 1):
            expect(_near(a, b, o), f"pose reads {i} and {i + 1} at rest after a move differ by {_pose_error(a, b)}")
        for i, reading in enumerate(reads, 1):
            expect(_near(reading, target, o), f"move_linear returned, but pose read {i} is "
                                              f"{_pose_error(reading, target)} from the target: it reported an "
                                              "arrival that did not happen")
        arm.move_linear(start, speed=o.speed_m_s, acceleration=o.acceleration_m_s2, timeout=o.motion_timeout_s)
        _misreported_arrival(arm, start, o)


def _arrival_checker(arm: RobotArm) -> RobotArm | None:
    """The arm that checks arrivals: ``arm``, or the one a wrapper delegates to (None for a replay)."""
    while not arm.verifies_arrival:
        inner = getattr(arm, "inner", None)
        if not isinstance(inner, RobotArm):
            return None
        arm = inner
    return arm


def _misreported_arrival(arm: RobotArm, start: Pose, o: ArmOptions) -> None:
    """One move whose read-back is shifted by FAKE_SHORTFALL_M must end in MotionError and a stop."""
    checker = _arrival_checker(arm)
    if checker is None:  # declares it moves nothing (verifies_arrival False, wraps no arm): nothing to fake
        return
    real_get_pose, real_stop = checker._get_pose, checker._stop
    stops: list[float] = []

    def short_pose(timeout: float) -> Pose:
        p = real_get_pose(timeout)
        return Pose(p.rotation, p.translation + np.array([FAKE_SHORTFALL_M, 0.0, 0.0]))

    def counted_stop(timeout: float) -> None:
        stops.append(timeout)
        real_stop(timeout)

    target = o.target(start)
    hooks = vars(checker)  # instance attributes shadow the backend's hooks for this one move
    hooks["_get_pose"], hooks["_stop"] = short_pose, counted_stop
    try:
        raises(MotionError, lambda: arm.move_linear(target, speed=o.speed_m_s, acceleration=o.acceleration_m_s2,
                                                    timeout=o.motion_timeout_s),
               f"move_linear whose pose reads back {FAKE_SHORTFALL_M * 1000:g} mm off the target")
    finally:
        hooks.pop("_get_pose", None)
        hooks.pop("_stop", None)
    expect(stops, "move_linear raised MotionError for a move that did not arrive but never told the arm to stop")
    arm.clear_errors(o.io_timeout_s)
    arm.move_linear(start, speed=o.speed_m_s, acceleration=o.acceleration_m_s2, timeout=o.motion_timeout_s)


def _stop_idempotent(factory: Factory, o: ArmOptions) -> None:
    with connected(factory, RobotArm, o.connect_timeout_s) as arm:
        start = arm.get_pose(o.io_timeout_s)
        arm.stop(o.io_timeout_s)
        arm.stop(o.io_timeout_s)
        expect(isinstance(arm.status(o.io_timeout_s), ArmStatus), "status() after stop() is not an ArmStatus")
        arm.clear_errors(o.io_timeout_s)
        status = arm.status(o.io_timeout_s)
        expect(status.ok, f"after stop(), stop(), clear_errors() the arm is not ready: {status!r}")
        now = arm.get_pose(o.io_timeout_s)
        expect(_near(now, start, o), f"stop() on an idle arm moved it by {_pose_error(now, start)}")


# ---------------------------------------------------------------- timeouts and resources
def _timeout_validation(factory: Factory, o: ArmOptions) -> None:
    with connected(factory, RobotArm, o.connect_timeout_s) as arm:
        start = arm.get_pose(o.io_timeout_s)
        target = o.target(start)
        check_bad_timeouts({
            "get_pose": arm.get_pose, "stop": arm.stop, "joint_positions": arm.joint_positions,
            "status": arm.status, "clear_errors": arm.clear_errors,
            "move_linear": lambda t: arm.move_linear(target, speed=o.speed_m_s, acceleration=o.acceleration_m_s2,
                                                     timeout=t),
        })
        now = arm.get_pose(o.io_timeout_s)
        expect(_near(now, start, o), f"move_linear with a rejected timeout moved the arm by {_pose_error(now, start)}")
    check_bad_connect_timeouts(factory, RobotArm, "arm")


def _timeout_bounded(factory: Factory, o: ArmOptions) -> None:
    with connected(factory, RobotArm, o.connect_timeout_s) as arm:
        calls: dict[str, Callable[[], object]] = {
            "get_pose": lambda: arm.get_pose(o.short_timeout_s),
            "status": lambda: arm.status(o.short_timeout_s),
            "joint_positions": lambda: arm.joint_positions(o.short_timeout_s),
        }
        for name, call in calls.items():
            elapsed, _, exc = timed(call)
            expect(exc is None or isinstance(exc, DeviceTimeoutError),
                   f"{name}(timeout={o.short_timeout_s:g}) raised {type(exc).__name__} ({exc}), expected a value "
                   "or DeviceTimeoutError")
            expect(elapsed <= o.short_timeout_s + o.timing_slack_s,
                   f"{name}(timeout={o.short_timeout_s:g}) took {elapsed:.3g} s (more than timeout + "
                   f"{o.timing_slack_s:g} s slack)")
    check_stalled(o, RobotArm, lambda arm: {f"{name}()": functools.partial(getattr(arm, name), o.short_timeout_s)
                                            for name in ("get_pose", "status", "joint_positions")})


def _refusals(arm: RobotArm) -> dict[str, Callable[[], object]]:
    return {
        "get_pose()": lambda: arm.get_pose(1.0),
        "move_linear()": lambda: arm.move_linear(Pose.identity(), speed=0.1, acceleration=1.0, timeout=1.0),
        "stop()": lambda: arm.stop(1.0),
        "joint_positions()": lambda: arm.joint_positions(1.0),
        "status()": lambda: arm.status(1.0),
        "clear_errors()": lambda: arm.clear_errors(1.0),
        "info()": arm.info,
    }


def _use(arm: RobotArm, o: ArmOptions) -> None:
    arm.get_pose(o.io_timeout_s)
    arm.status(o.io_timeout_s)


_FIRST, _LAST = lifecycle_checks("arm", RobotArm, _refusals, _use)

ARM_CHECKS: tuple[Check[RobotArm, ArmOptions], ...] = (
    *_FIRST,
    Check("arm.status", "status() is an ArmStatus; a ready arm stays ready through clear_errors()", _status),
    Check("arm.joint-positions", "joint_positions() is a stable 1-D float64 array in radians", _joint_positions),
    Check("arm.pose-units", "get_pose() is a Pose in metres, stable at rest", _pose_units),
    Check("arm.argument-validation", "bad pose, speed or acceleration is a CellcalError and nothing moves",
          _argument_validation),
    Check("arm.pose-round-trip", "move_linear then get_pose agree within tolerance (metres, radians)",
          _pose_round_trip),
    Check("arm.arrival", "move_linear returns only once the arm is at the target (steady read-back within "
                         "tolerance); a move that reads back elsewhere raises MotionError and stops the arm",
          _arrival),
    Check("arm.stop-idempotent", "stop() on an idle arm, twice, is harmless", _stop_idempotent),
    Check("arm.timeout-validation", "a non-positive, NaN, infinite or non-number timeout is a clear CellcalError "
                                    "and nothing moves", _timeout_validation),
    Check("arm.timeout-bounded", "reads with a timeout return or raise DeviceTimeoutError in bounded time",
          _timeout_bounded),
    _LAST,
)

#: The arm contract rules, in the order they run.
ARM_RULES: tuple[str, ...] = tuple(c.rule for c in ARM_CHECKS)


def check_arm(factory: Factory, options: ArmOptions | None = None, *, only: Iterable[str] | None = None,
              raise_on_failure: bool = True, quiet: bool = False) -> ConformanceReport:
    """Run the arm contract checks against one backend.

    Args:
        factory: Zero-argument callable returning a new, unconnected arm each call.
        options: Round-trip step, tolerances, timeouts; defaults apply if None.
        only: Run only these rules (see :data:`ARM_RULES`).
        raise_on_failure: Raise :class:`ConformanceError` listing every failed rule.
        quiet: Do not print each rule's name to stderr as it starts.

    Returns:
        The report (all checks passed when ``raise_on_failure`` is true).

    Raises:
        ConformanceError: If a check failed and ``raise_on_failure`` is true.
        CellcalError: If ``factory`` is not callable or ``only`` names an unknown rule.
    """
    return run_checks("arm", ARM_CHECKS, factory, options or ArmOptions(), RobotArm, only, raise_on_failure,
                      quiet)
