"""What a UR controller's state says, read from ur_rtde's receive interface: can the arm move, and why not.

Pure functions of one ``rtde_receive.RTDEReceiveInterface`` (or anything with its getters):
the modes are checked against the documented sets (:mod:`.limits`), named with their codes
(:mod:`.codes`) and turned into an :class:`~cellcal.devices.types.ArmStatus` or the typed
error the driver raises (ADR 0015).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from cellcal.devices.errors import VendorError
from cellcal.devices.types import ArmStatus

from .codes import (
    ROBOT_MODE_RUNNING,
    ROBOT_MODES,
    RUNTIME_STATES,
    SAFETY_MODES,
    SAFETY_OK,
    SAFETY_REDUCED,
    STATUS_PROGRAM_RUNNING,
    name,
)
from .limits import checked_mode

__all__ = ["arm_status", "not_ready_reason", "program_running", "raise_known_cause", "ready_for_program",
           "robot_mode", "runtime_state", "safety_mode"]


def safety_mode(receive: Any) -> int:
    """The receive interface's safety mode, checked against the documented set."""
    return checked_mode(receive.getSafetyMode(), SAFETY_MODES, "getSafetyMode")


def robot_mode(receive: Any) -> int:
    """The receive interface's robot mode, checked against the documented set."""
    return checked_mode(receive.getRobotMode(), ROBOT_MODES, "getRobotMode")


def runtime_state(receive: Any) -> int:
    """The receive interface's program state, checked against the documented set."""
    return checked_mode(receive.getRuntimeState(), RUNTIME_STATES, "getRuntimeState")


def program_running(receive: Any) -> bool:
    """Whether a program (ur_rtde's control script) runs: bit 1 of ``getRobotStatus``."""
    return bool(int(receive.getRobotStatus()) & STATUS_PROGRAM_RUNNING)


def ready_for_program(receive: Any) -> bool:
    """Whether the arm can run a program: safety normal or reduced, robot mode RUNNING."""
    return safety_mode(receive) in SAFETY_OK and robot_mode(receive) == ROBOT_MODE_RUNNING


def not_ready_reason(receive: Any) -> str:
    """Why the arm cannot move now ("" when it can): safety, power, or the control script."""
    safety = safety_mode(receive)
    if safety not in SAFETY_OK:
        return f"safety mode {name(SAFETY_MODES, safety)}"
    robot = robot_mode(receive)
    if robot != ROBOT_MODE_RUNNING:
        return f"robot mode {name(ROBOT_MODES, robot)} (needs power on, brakes released)"
    if not program_running(receive):
        return "the RTDE control script is not running on the controller"
    return ""


def arm_status(receive: Any) -> ArmStatus:
    """The arm's status: the safety mode as the error code, reduced mode as a warning, why it cannot move."""
    safety = safety_mode(receive)
    if safety not in SAFETY_OK:
        return ArmStatus(error_code=safety, message=f"safety mode {name(SAFETY_MODES, safety)}", can_move=False)
    warning = safety if safety == SAFETY_REDUCED else 0
    reason = not_ready_reason(receive)
    if reason:
        return ArmStatus(warning_code=warning, can_move=False, message=reason)
    return ArmStatus(warning_code=warning, message="reduced mode" if warning else "", can_move=True)


def raise_known_cause(receive: Any, operation: str, remote_control_hint: Callable[[], str]) -> None:
    """Raise the typed error for the state the receive interface reports, if any.

    :class:`VendorError` with the safety-mode code (e-stop, protective stop, another safety
    mode), the robot-mode code (not powered, brakes on) or the program-state code (control
    script not running). Returns when the state explains nothing.

    Args:
        receive: The receive interface.
        operation: What failed, for the message (``"moveL"``).
        remote_control_hint: Says ``"; the pendant is in Local Control ..."`` when it is
            (asked only when the control script is not running).
    """
    safety = safety_mode(receive)
    if receive.isEmergencyStopped():
        raise VendorError("ur", safety, (
            f"{operation} failed: emergency stop engaged (safety mode {name(SAFETY_MODES, safety)}); "
            "release the e-stop by hand, then call clear_errors()"))
    if receive.isProtectiveStopped():
        raise VendorError("ur", safety, (
            f"{operation} failed: protective stop (safety mode {name(SAFETY_MODES, safety)}); "
            "remove the cause, then call clear_errors()"))
    if safety not in SAFETY_OK:
        raise VendorError("ur", safety, f"{operation} failed: safety mode {name(SAFETY_MODES, safety)}")
    robot = robot_mode(receive)
    if robot != ROBOT_MODE_RUNNING:
        raise VendorError("ur", robot, (
            f"{operation} failed: robot mode {name(ROBOT_MODES, robot)} (power on and release the brakes)"))
    if not program_running(receive):
        state = runtime_state(receive)
        raise VendorError("ur", state, (
            f"{operation} failed: the RTDE control script is not running (program state "
            f"{name(RUNTIME_STATES, state)}){remote_control_hint()}; clear_errors() restarts it"))
