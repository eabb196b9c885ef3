"""The emulated UR controller's state: modes, status bits, RTDE registers and the arm behind them.

Everything the RTDE server streams, the control-script role changes and the dashboard
reports lives here, behind one lock. Joint values come from the simulated arm's 5-DoF
chain, reported as UR's six joints with wrist 2 held at 0 (see docs/adr/0017-ur-emulator.md).
"""

from __future__ import annotations

import functools
import threading
import time
from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cellcal.devices.geometry.vendor_poses import pose_from_ur, pose_to_ur
from cellcal.devices.pose import Pose
from cellcal.sims.arm import forward_position, inverse_kinematics

from .rtde_wire import IN_USE, NOT_FOUND, REGISTER_BANKS, TYPE_CODES, input_type, output_type, register_of

# robot_mode (RTDE guide)
ROBOT_MODE_POWER_OFF = 3
ROBOT_MODE_IDLE = 5
ROBOT_MODE_RUNNING = 7
ROBOT_MODE_NAMES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF",
                    4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE"}
# safety_mode, and the safety_status_bits each one sets
SAFETY_NORMAL = 1
SAFETY_PROTECTIVE_STOP = 3
SAFETY_ROBOT_EMERGENCY_STOP = 7
SAFETY_MODE_NAMES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP",
                     6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT"}
_SAFETY_BITS = {SAFETY_NORMAL: 0x1, SAFETY_PROTECTIVE_STOP: 0x4 | 0x400,      # protective stopped, stopped by safety
                SAFETY_ROBOT_EMERGENCY_STOP: 0x40 | 0x80 | 0x400}               # robot e-stop, emergency stopped
# robot_status_bits and runtime_state
STATUS_POWER_ON = 0x1
STATUS_PROGRAM_RUNNING = 0x2
RUNTIME_STOPPED = 1
RUNTIME_PLAYING = 2
#: Controller cycle (e-Series, 500 Hz), seconds: timestamps advance in these steps.
CYCLE_S = 0.002
#: joint_mode values: running / power off (RTDE guide).
JOINT_RUNNING, JOINT_POWER_OFF = 253, 239


@functools.lru_cache(maxsize=512)
def _zero(name: str) -> object:
    """The value of a field the emulator does not model: zero of its type."""
    kind = output_type(name)
    n = TYPE_CODES[kind][1] if kind is not None else 1
    return (0,) * n if n > 1 else 0


class ArmModel(Protocol):
    """What the controller needs from the simulated arm (``cellcal.sims.arm.SimArm`` provides it)."""

    def begin_move_linear(self, pose: Pose, speed_m_s: float, acceleration_m_s2: float) -> None: ...

    def is_moving(self) -> bool: ...

    def current_error(self) -> tuple[int, int]: ...

    def set_error(self, code: int, warning: int = 0) -> None: ...

    def true_flange_pose(self) -> Pose: ...

    def get_pose(self, timeout: float | None = None) -> Pose: ...

    def stop(self, timeout: float | None = None) -> None: ...

    def motion_progress(self) -> float: ...


def ur_joints(flange: Pose, previous: NDArray[np.float64] | None) -> NDArray[np.float64]:
    """Six UR joint angles (rad) for a flange pose: the 5-DoF chain's J1-J4, wrist 2 = 0, then J5."""
    q5 = inverse_kinematics(flange, None if previous is None else previous[[0, 1, 2, 3, 5]])
    return np.array([q5[0], q5[1], q5[2], q5[3], 0.0, q5[4]], dtype=np.float64)


def pose_from_joints(q: Sequence[float]) -> Pose:
    """Flange pose of six joint angles (rad) on the same chain (wrist 2 must be 0).

    Position from the chain's forward kinematics; orientation in the convention the
    sim arm's :func:`~cellcal.sims.arm.inverse_kinematics` decomposes (base yaw and tool
    pitch as extrinsic z-y angles, then J6 about the tool axis). Read back through
    :func:`ur_joints`, the position and J1 are exact; J2-J4 and J6 are the simplified
    chain's own solution for that pose (equal to the command when J1 = 0).
    """
    qa = np.asarray(q, dtype=np.float64)
    rotation = Rotation.from_euler("zy", [qa[0], qa[1] + qa[2] + qa[3]]) * Rotation.from_rotvec([0.0, 0.0, qa[5]])
    return Pose(rotation, forward_position(qa[:4]))


class ControllerState:
    """Modes, status bits, RTDE registers and published kinematics of one emulated controller.

    Thread-safe: the RTDE sessions, the control-script role, the dashboard and fault
    injection all go through :attr:`lock`. :meth:`refresh` (called every controller
    cycle) samples the arm once for every stream.

    Args:
        arm: The simulated arm (connected).
        powered: Start powered on with brakes released (robot mode RUNNING); else POWER_OFF.
        unlock_delay_s: A protective stop cannot be unlocked sooner than this after it
            happened (UR: 5 s).
    """

    def __init__(self, arm: ArmModel, *, powered: bool = True, unlock_delay_s: float = 5.0) -> None:
        self.arm = arm
        self.lock = threading.RLock()
        self.start = time.monotonic()
        self.unlock_delay_s = float(unlock_delay_s)
        self.robot_mode = ROBOT_MODE_RUNNING if powered else ROBOT_MODE_POWER_OFF
        self.safety_mode = SAFETY_NORMAL
        self.program_running = False
        self.remote_control = True
        self.tcp_offset = Pose.identity()
        self.target_tcp: Pose | None = None
        self.stopped_at = 0.0
        zero = {"INT32": 0, "DOUBLE": 0.0, "BOOL": False}
        self.registers: dict[str, list[Any]] = {
            f"{d}_{k}": [zero[REGISTER_BANKS[k][0]]] * 128 for d in ("input", "output") for k in REGISTER_BANKS}
        self._owners: dict[str, int] = {}
        self._q: NDArray[np.float64] | None = None
        self._sample: dict[str, object] = {}
        self.refresh()

    # ------------------------------------------------------------------ derived values
    def timestamp(self) -> float:
        """Controller time since start, s, in whole cycles."""
        return round((time.monotonic() - self.start) / CYCLE_S) * CYCLE_S

    def safety_status_bits(self) -> int:
        """``safety_status_bits`` for the current safety mode."""
        return _SAFETY_BITS.get(self.safety_mode, 0)

    def robot_status_bits(self) -> int:
        """``robot_status_bits``: bit 0 power on, bit 1 program running."""
        powered = self.robot_mode in (ROBOT_MODE_IDLE, ROBOT_MODE_RUNNING)
        return (STATUS_POWER_ON if powered else 0) | (STATUS_PROGRAM_RUNNING if self.program_running else 0)

    def can_move(self) -> bool:
        """Whether motion is allowed: powered, brakes released, safety normal."""
        return self.robot_mode == ROBOT_MODE_RUNNING and self.safety_mode == SAFETY_NORMAL

    def refresh(self) -> None:
        """Sample the arm once (pose with read-back noise, joints, targets) for this cycle's packages."""
        flange = self.arm.get_pose()
        with self.lock:
            tcp = flange @ self.tcp_offset
            self._q = ur_joints(flange, self._q)
            target = self.target_tcp if self.target_tcp is not None and self.arm.is_moving() else tcp
            self._sample = {"actual_TCP_pose": tuple(pose_to_ur(tcp)), "target_TCP_pose": tuple(pose_to_ur(target)),
                            "actual_q": tuple(self._q), "target_q": tuple(self._q)}

    def values(self, names: Sequence[str], timestamp: float | None = None) -> list[object]:
        """Current values of output fields, in order (one consistent snapshot).

        Args:
            names: Field names.
            timestamp: The ``timestamp`` field's value (the cycle a package is sent in); None: now.
        """
        with self.lock:
            special = self._specials()
            if timestamp is not None:
                special["timestamp"] = timestamp
            return [self._value(n, special) for n in names]

    def _value(self, name: str, special: dict[str, object]) -> object:
        found = self._sample.get(name)
        if found is None:
            found = special.get(name)
        if found is None:
            reg = register_of(name)
            found = self.registers[f"{reg[0]}_{reg[1]}"][reg[2]] if reg is not None else _zero(name)
        return found

    def _specials(self) -> dict[str, object]:
        running = self.robot_mode == ROBOT_MODE_RUNNING
        return {
            "timestamp": self.timestamp(), "robot_mode": self.robot_mode, "safety_mode": self.safety_mode,
            "safety_status": self.safety_mode, "safety_status_bits": self.safety_status_bits(),
            "robot_status_bits": self.robot_status_bits(),
            "runtime_state": RUNTIME_PLAYING if self.program_running else RUNTIME_STOPPED,
            "joint_mode": (JOINT_RUNNING if running else JOINT_POWER_OFF,) * 6,
            "speed_scaling": 1.0, "target_speed_fraction": 1.0,
            "actual_main_voltage": 48.0, "actual_robot_voltage": 48.0 if running else 0.0,
        }

    # ------------------------------------------------------------------ RTDE inputs
    def claim_inputs(self, owner: int, names: Sequence[str]) -> list[str]:
        """Types for an input recipe, claiming its fields for ``owner``; NOT_FOUND / IN_USE refuse it."""
        with self.lock:
            types = []
            for name in names:
                kind = input_type(name)
                holder = self._owners.get(name)
                types.append(NOT_FOUND if kind is None else IN_USE if holder not in (None, owner) else kind)
            if all(t not in (NOT_FOUND, IN_USE) for t in types):
                self._owners.update(dict.fromkeys(names, owner))
            return types

    def release_inputs(self, owner: int) -> None:
        """Free every input field ``owner`` claimed (its connection closed)."""
        with self.lock:
            self._owners = {n: o for n, o in self._owners.items() if o != owner}

    def write_inputs(self, values: dict[str, object]) -> None:
        """Store the fields of one input data package (registers only; the rest is ignored)."""
        with self.lock:
            for name, value in values.items():
                reg = register_of(name)
                if reg is not None:
                    self.registers[f"input_{reg[1]}"][reg[2]] = value  # type: ignore[assignment]

    def input_int(self, index: int) -> int:
        """``input_int_register_<index>``."""
        with self.lock:
            return int(self.registers["input_int"][index])

    def input_double(self, index: int) -> float:
        """``input_double_register_<index>``."""
        with self.lock:
            return float(self.registers["input_double"][index])

    def set_output_int(self, index: int, value: int) -> None:
        """Write ``output_int_register_<index>`` (INT32)."""
        with self.lock:
            value &= 0xFFFFFFFF  # INT32 on the wire: wrap like the controller's 32-bit register
            self.registers["output_int"][index] = value - (1 << 32) if value >= 1 << 31 else value

    def set_output_double(self, index: int, value: float) -> None:
        """Write ``output_double_register_<index>``."""
        with self.lock:
            self.registers["output_double"][index] = float(value)

    # ------------------------------------------------------------------ motion helpers
    def tcp_pose(self) -> Pose:
        """True TCP pose (flange with the TCP offset), no read-back noise."""
        with self.lock:
            return self.arm.true_flange_pose() @ self.tcp_offset

    def flange_for_tcp(self, tcp_ur: Sequence[float]) -> Pose:
        """The flange pose that puts the TCP at ``tcp_ur`` (UR pose vector)."""
        with self.lock:
            return pose_from_ur(np.asarray(tcp_ur, dtype=np.float64)) @ self.tcp_offset.inv()

    def halt(self) -> None:
        """Stop the arm where it is now."""
        with self.lock:
            self.stopped_at = time.monotonic()
            if self.arm.is_moving():
                self.arm.stop()
            self.target_tcp = None

    # ------------------------------------------------------------------ safety and power
    def enter_safety(self, mode: int) -> None:
        """Protective or emergency stop: the arm halts, the running program stops."""
        with self.lock:
            self.halt()
            self.safety_mode = mode
            self.program_running = False
            if mode == SAFETY_ROBOT_EMERGENCY_STOP:
                self.robot_mode = ROBOT_MODE_POWER_OFF

    def release_emergency_stop(self) -> None:
        """The e-stop button pulled out by hand: safety normal, the arm stays powered off."""
        with self.lock:
            if self.safety_mode == SAFETY_ROBOT_EMERGENCY_STOP:
                self.safety_mode = SAFETY_NORMAL

    def unlock_protective_stop(self) -> bool:
        """Release a protective stop; False while within :attr:`unlock_delay_s` of it."""
        with self.lock:
            if self.safety_mode != SAFETY_PROTECTIVE_STOP:
                return True
            if time.monotonic() - self.stopped_at < self.unlock_delay_s:
                return False
            self.safety_mode = SAFETY_NORMAL
            return True

    def power(self, on: bool) -> None:
        """Power on (to IDLE, brakes still engaged) or off (program stops)."""
        with self.lock:
            if not on:
                self.halt()
                self.program_running = False
                self.robot_mode = ROBOT_MODE_POWER_OFF
            elif self.robot_mode == ROBOT_MODE_POWER_OFF and self.safety_mode != SAFETY_ROBOT_EMERGENCY_STOP:
                self.robot_mode = ROBOT_MODE_IDLE

    def brake_release(self) -> None:
        """Release the brakes of a powered arm (IDLE -> RUNNING)."""
        with self.lock:
            if self.robot_mode == ROBOT_MODE_IDLE:
                self.robot_mode = ROBOT_MODE_RUNNING

