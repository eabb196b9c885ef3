"""The ``sim`` arm: a simulated 5-DoF robot arm modelled on the UFACTORY xArm 5 (:class:`SimArm`).

It moves the flange of the shared simulated world (poses in the base frame, metres,
radians) along trapezoidal straight-line motions, refuses targets outside its
workspace with the xArm controller's error 21, and reads back with the xArm 5's
repeatability. Design: docs/adr/0014-simulated-cell.md.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.arm import RobotArm
from cellcal.devices.arm_model import ArmModel
from cellcal.devices.arrival import ArrivalTolerance
from cellcal.devices.base import BackendContext
from cellcal.devices.errors import ConfigError, DeviceTimeoutError, VendorError
from cellcal.devices.geometry.reach import ReachClass, orientation_violation
from cellcal.devices.pose import Pose
from cellcal.devices.types import ArmStatus, DeviceInfo

# the chain lives in .kinematics (the world needs it for the arm's errors); still importable from here
from .kinematics import FOREARM_M as FOREARM_M
from .kinematics import SHOULDER_HEIGHT_M as SHOULDER_HEIGHT_M
from .kinematics import UPPER_ARM_M as UPPER_ARM_M
from .kinematics import WRIST_TO_FLANGE_M as WRIST_TO_FLANGE_M
from .kinematics import forward_position as forward_position
from .kinematics import inverse_kinematics, rms_error
from .motion import LinearMotion
from .world import SimWorld, world_from_context

#: xArm 5 TCP limits.
MAX_SPEED_M_S = 1.0
MAX_ACCELERATION_M_S2 = 50.0

#: xArm controller error codes the sim raises or latches, with their meanings. The sim
#: arm speaks the xArm controller's codes by design; the full table is the xArm driver's
#: (``cellcal.drivers.xarm.codes.ERRORS``), which this generic sim may not import (sims
#: depend on devices only), so the codes it needs are repeated here, worded as there
#: (capitalised); tests/unit/sims/test_sim_arm.py checks that every one agrees with the driver's.
ERROR_MEANINGS: dict[int, str] = {
    1: "Emergency stop button on the controller pressed",
    2: "Emergency IO of the control box triggered",
    3: "Emergency stop button of the three-state switch pressed",
    21: "Kinematic error (target not reachable)",
    22: "Self-collision error",
    23: "Joint angle exceeds limit",
    24: "Speed exceeds limit",
    25: "Planning error",
    31: "Collision caused abnormal current",
    35: "Safety boundary limit (target outside the allowed workspace)",
}
ERROR_OUT_OF_REACH = 21


def error_meaning(code: int) -> str:
    """Human-readable meaning of an xArm-like controller error code."""
    return ERROR_MEANINGS.get(int(code), f"Controller Error {int(code)}")


@dataclass
class SimArmFaults:
    """Switchable misbehaviour of the sim arm, for tests (ADR 0016); everything is off by default.

    Seen the same way through the xArm emulator, which serves this arm on the wire.

    Attributes:
        stop_short_m: Every motion ends this far before its target along the path
            (a motion shorter than that does not move), and is reported done, metres.
        pose_jump_m: Every pose read is off the truth by a random vector of this length, metres.
        stale_reads: Every pose read returns the one before it (the first read the truth):
            a read-back lagging one request behind.
    """

    stop_short_m: float = 0.0
    pose_jump_m: float = 0.0
    stale_reads: bool = False


@dataclass(frozen=True)
class SimArmConfig:
    """Config of the ``sim`` arm backend (the ``[arm]`` table)."""

    reach_m: float = field(default=0.70, metadata={"ge": 0.05, "le": 5.0, "doc": "max flange radius from base axis, m"})
    min_radius_m: float = field(default=0.10, metadata={"ge": 0.0, "le": 5.0,
                                                        "doc": "min flange radius from the base axis, m"})
    z_min_m: float = field(default=-0.10, metadata={"ge": -5.0, "le": 5.0, "doc": "lowest flange z, m"})
    z_max_m: float = field(default=0.90, metadata={"ge": -5.0, "le": 5.0, "doc": "highest flange z, m"})
    time_scale: float = field(default=0.01, metadata={"ge": 0.0, "le": 10.0,
                                                      "doc": "wall seconds per simulated second (0 = instant)"})
    repeatability_m: float = field(default=0.0001, metadata={"ge": 0.0, "le": 0.01,
                                                             "doc": "pose read-back repeatability (4 sigma), m"})
    seed: int | None = field(default=None, metadata={"ge": 0, "doc": "read-back noise seed; default: world's"})
    reach: ReachClass = field(default="any", metadata={
        "doc": "orientations it takes: 'xarm5' refuses a tool axis tilted sideways, as a real xArm 5 must"})

    def __post_init__(self) -> None:
        if self.reach_m <= self.min_radius_m:
            raise ConfigError(f"reach_m ({self.reach_m}) must exceed min_radius_m ({self.min_radius_m})")
        if self.z_max_m <= self.z_min_m:
            raise ConfigError(f"z_max_m ({self.z_max_m}) must exceed z_min_m ({self.z_min_m})")


class SimArm(RobotArm):
    """Simulated xArm-5-like arm moving the flange of the shared :class:`SimWorld`.

    **Workspace** (flange position in the base frame, configurable): horizontal
    distance from the base axis ``min_radius_m <= r <= reach_m`` (defaults 0.10 m and
    0.70 m, the xArm 5's quoted reach) and ``z_min_m <= z <= z_max_m`` (defaults
    -0.10 m and 0.90 m). A target outside it is refused: the arm does not move and
    enters error state **21** ("Kinematic error", as the xArm controller reports an
    unsolvable target); :meth:`move_linear` raises ``VendorError("sim", 21, ...)``.
    With ``reach = "xarm5"`` an orientation a real xArm 5 cannot take (tool axis tilted
    sideways out of the base's vertical plane, :mod:`cellcal.devices.geometry.reach`) is
    refused the same way; the default ``"any"`` does not restrict the orientation.

    **Motion** (:class:`LinearMotion`): speed and acceleration are clamped to the
    xArm 5's limits (1.0 m/s, 50 m/s²). Simulated time advances by the motion's
    duration ``T``; the wall clock waits ``T · time_scale`` (0 = instantaneous, 1 = real
    time; the default 0.01 keeps the default run fast). A new target replaces a motion
    under way, starting from where the flange is; :meth:`stop` halts where it is.

    **Read-back**: :meth:`get_pose` returns the pose the controller believes plus Gaussian
    noise on each translation axis with ``sigma = repeatability_m / 4`` (xArm 5: ±0.1 mm), so
    readings stay within ± ``repeatability_m`` of it; the orientation is exact. The arm
    arrives exactly at the commanded target as the controller sees it. The flange truly
    stands there too unless the world's kinematic errors are on (``[sim.arm_errors]``, on by
    default): then it stands off it by the errors of the chain at those joint angles, the
    same every time (:meth:`physical_flange_pose`; :meth:`arm_model` states their RMS).
    **Joints** (radians, 5 values) come from :func:`inverse_kinematics`; J1 and J5 are
    unwrapped towards the previous reading, so they are continuous along a motion.

    **Fault injection** (tests): :attr:`fault_hook`, if set, is called as
    ``hook("connect", n)`` on the n-th connect and ``hook("move", n)`` right after the
    n-th motion has started (``n`` = :attr:`moves_started`); from there a test can
    latch a controller error (:meth:`set_error`, e.g. 31, the protective stop after a
    collision), freeze the motion (:meth:`freeze_motion`, a blocked arm that never
    arrives) or raise. :attr:`stops` counts the stop commands received.
    :attr:`faults` (:class:`SimArmFaults`) switches on an arm that stops short, a pose
    read-back that jumps or one that lags a read behind.

    **Arrival** (checked by :class:`RobotArm` after every move): the default tolerance is
    1 mm / 0.1 deg, widened to twice ``repeatability_m`` when that is larger, so two noisy
    reads at rest still agree.

    Thread-safe: the non-blocking API (:meth:`begin_move_linear`, :meth:`is_moving`,
    :meth:`motion_progress`, :meth:`current_error`, :meth:`set_error`) may be driven
    from an emulator's server thread while others read the pose.

    Args:
        config: Backend config; None uses the defaults.
        context: Backend context (gives the shared world); None makes a private one.
        world: Use this world instead of the context's.
    """

    backend_name = "sim"
    Config = SimArmConfig

    def __init__(self, config: SimArmConfig | None = None, context: BackendContext | None = None, *,
                 world: SimWorld | None = None) -> None:
        super().__init__()
        self.config = config or SimArmConfig()
        self.world = world if world is not None else world_from_context(context)
        self._rng = self.world.rng("arm", self.config.seed)
        self._lock = threading.RLock()
        self._error = 0
        self._warning = 0
        self._joints: NDArray[np.float64] | None = None
        self._motion: LinearMotion | None = None
        self.last_motion_duration_s = 0.0
        #: Fault-injection hook ``hook(event, n)``, see the class docstring. It runs on the
        #: thread that drives the arm (an emulator's server thread for ``xarm-emulated``).
        self.fault_hook: Callable[[str, int], None] | None = None
        #: Motions started, connects made and stop commands received (observable by tests).
        self.moves_started = 0
        self.connects = 0
        self.stops = 0
        #: Switchable misbehaviour (tests), see :class:`SimArmFaults`.
        self.faults = SimArmFaults()
        self._fault_rng = self.world.rng("arm.faults", self.config.seed)
        self._last_read: Pose | None = None
        self._model: ArmModel | None = None

    def default_arrival_tolerance(self) -> ArrivalTolerance:
        """1 mm / 0.1 deg, or twice the read-back repeatability when that is larger."""
        return ArrivalTolerance(position_m=max(1e-3, 2.0 * self.config.repeatability_m))

    # ------------------------------------------------------------------ workspace
    def workspace_violation(self, pose: Pose) -> str | None:
        """Why ``pose`` is outside the workspace, or None when it is reachable."""
        c = self.config
        x, y, z = (float(v) for v in pose.translation)
        r = math.hypot(x, y)
        if r > c.reach_m:
            return f"radius {r:.4f} m beyond the reach {c.reach_m} m"
        if r < c.min_radius_m:
            return f"radius {r:.4f} m inside the minimum radius {c.min_radius_m} m"
        if not c.z_min_m <= z <= c.z_max_m:
            return f"z {z:.4f} m outside [{c.z_min_m}, {c.z_max_m}] m"
        return orientation_violation(pose, c.reach)

    # ------------------------------------------------------------------ non-blocking API
    def begin_move_linear(self, pose: Pose, speed_m_s: float, acceleration_m_s2: float) -> None:
        """Start a straight-line motion and return at once.

        If an error is pending the command is ignored (check :meth:`current_error`); if
        the target is outside the workspace the arm does not move and enters error 21.
        Speed and acceleration are clamped to the xArm 5's limits.
        """
        with self._lock:
            if self._error:
                return
            if self.workspace_violation(pose) is not None:
                self.set_error(ERROR_OUT_OF_REACH)
                return
            v = min(float(speed_m_s), MAX_SPEED_M_S)
            acc = min(float(acceleration_m_s2), MAX_ACCELERATION_M_S2)
            model = self.world.arm
            motion = self._faulty(LinearMotion(model.flange_pose(), pose, v, acc))
            self.last_motion_duration_s = motion.duration_s
            model.start_motion(motion, self.config.time_scale)
            self._motion = motion
            self.moves_started += 1
            if self.fault_hook is not None:
                self.fault_hook("move", self.moves_started)

    def _faulty(self, motion: LinearMotion) -> LinearMotion:
        """``motion``, ending :attr:`SimArmFaults.stop_short_m` early when that fault is on."""
        short = self.faults.stop_short_m
        if short <= 0.0:
            return motion
        s = max(0.0, 1.0 - short / motion.length_m) if motion.length_m > 0 else 0.0  # fraction of the path made
        return LinearMotion(motion.start, motion.pose_at_fraction(s), motion.speed, motion.acceleration)

    def freeze_motion(self) -> None:
        """Fault injection: the motion under way stops progressing (a blocked arm).

        The arm stays where it is and keeps reporting that it is moving until it is
        stopped (:meth:`stop`, or a controller error); a waiting caller times out.
        Meant for the ``"move"`` fault hook, right as the motion starts: the arm is held
        at the motion's start (a short motion at a small ``time_scale`` may otherwise
        have finished already; holding it where it is would race with that).
        """
        with self._lock:
            motion = self._motion
            if motion is None:
                return
            model = self.world.arm
            here = motion.start
            model.set_flange_pose(here)
            model.start_motion(LinearMotion(here, motion.target, motion.speed, motion.acceleration), 1e12)

    def resume_state(self) -> dict[str, Any]:
        """JSON-able state of the read-back noise stream (restored when a run resumes)."""
        with self._lock:
            return {"rng": self._rng.bit_generator.state}

    def restore_resume_state(self, state: dict[str, Any]) -> None:
        """Continue the read-back noise stream from :meth:`resume_state`'s output."""
        with self._lock:
            self._rng.bit_generator.state = state["rng"]

    def is_moving(self) -> bool:
        """Whether a motion is under way."""
        return self.world.arm.is_moving()

    def motion_progress(self) -> float:
        """Fraction 0..1 of the current motion done (1.0 when idle)."""
        return self.world.arm.progress()

    def current_error(self) -> tuple[int, int]:
        """``(error_code, warning_code)``; 0 when clear."""
        with self._lock:
            return self._error, self._warning

    def set_error(self, code: int, warning: int = 0) -> None:
        """Enter an error state (fault injection); a non-zero error halts any motion."""
        with self._lock:
            self._error = int(code)
            self._warning = int(warning)
            if self._error:
                self.world.arm.halt()

    def true_flange_pose(self) -> Pose:
        """The flange pose the controller believes, without read-back noise (what the emulators plan with).

        With the arm's kinematic errors on (``[sim.arm_errors]``) the flange truly stands at
        :meth:`physical_flange_pose`; without them the two are the same.
        """
        return self.world.arm.flange_pose()

    def physical_flange_pose(self) -> Pose:
        """Where the flange truly stands (ground truth: the camera hangs there), kinematic errors included."""
        return self.world.true_flange_pose()

    def _arm_model(self) -> ArmModel:
        """The read-back repeatability and the RMS error its configured kinematic errors give over the
        workspace (:func:`~cellcal.sims.kinematics.rms_error`; zeros for the ideal arm)."""
        model = self._model
        if model is None:
            distance, angle = rms_error(self.world.arm_errors)
            model = self._model = ArmModel(self.config.repeatability_m, distance, angle, "sim")
        return model

    # ------------------------------------------------------------------ backend hooks
    def _connect(self, timeout: float) -> None:
        self.connects += 1
        if self.fault_hook is not None:
            self.fault_hook("connect", self.connects)

    def _close(self) -> None:
        self.world.arm.halt()

    def _info(self) -> DeviceInfo:
        return DeviceInfo(backend="sim", vendor="cellcal (simulated UFACTORY)", model="xArm 5 (simulated)",
                          serial=f"SIM-XA5-{self.world.seed:08d}", firmware="sim",
                          extra={"axes": 5, "time_scale": self.config.time_scale})

    def _get_pose(self, timeout: float) -> Pose:
        true = self.world.arm.flange_pose()
        with self._lock:
            noise = self._rng.standard_normal(3) * (self.config.repeatability_m / 4.0)
            reading = true.with_translation(true.translation + noise)
            previous, self._last_read = self._last_read, reading
            faults = self.faults
            if faults.stale_reads and previous is not None:
                reading = previous
            if faults.pose_jump_m > 0.0:
                direction = self._fault_rng.standard_normal(3)
                reading = reading.with_translation(reading.translation
                                                   + faults.pose_jump_m * direction / np.linalg.norm(direction))
            return reading

    def _move_linear(self, pose: Pose, speed: float, acceleration: float, timeout: float) -> None:
        self.begin_move_linear(pose, speed, acceleration)
        self._raise_if_error()
        deadline = time.monotonic() + timeout
        model = self.world.arm
        while model.is_moving():
            now = time.monotonic()
            if now >= deadline:
                model.halt()
                raise DeviceTimeoutError(f"sim arm: motion did not finish within {timeout:g} s; stopped")
            wait = model.remaining_s() * self.config.time_scale
            time.sleep(max(1e-4, min(wait, deadline - now, 0.05)))
        self._raise_if_error()

    def _raise_if_error(self) -> None:
        code, _ = self.current_error()
        if code:
            raise VendorError("sim", code, error_meaning(code))

    def _stop(self, timeout: float) -> None:
        self.stops += 1
        self.world.arm.halt()

    def _joint_positions(self, timeout: float) -> NDArray[np.float64]:
        with self._lock:
            self._joints = inverse_kinematics(self.world.arm.flange_pose(), self._joints)
            return self._joints.copy()

    def _status(self, timeout: float) -> ArmStatus:
        code, warn = self.current_error()
        message = error_meaning(code) if code else (f"warning {warn}" if warn else "")
        return ArmStatus(error_code=code, warning_code=warn, message=message, can_move=code == 0)

    def _clear_errors(self, timeout: float) -> None:
        with self._lock:
            self._error = 0
            self._warning = 0
