"""xArm controller error and warning codes with their meanings.

Code numbers and titles as documented by UFACTORY (controller error/warning tables of
the xArm manual and SDK); meanings restated in short.
"""

from __future__ import annotations

ERRORS: dict[int, str] = {
    1: "emergency stop button on the controller pressed",
    2: "emergency IO of the control box triggered",
    3: "emergency stop button of the three-state switch pressed",
    10: "servo motor error",
    11: "servo motor 1 error",
    12: "servo motor 2 error",
    13: "servo motor 3 error",
    14: "servo motor 4 error",
    15: "servo motor 5 error",
    16: "servo motor 6 error",
    17: "servo motor 7 error",
    18: "force/torque sensor communication error",
    19: "end effector communication error",
    21: "kinematic error (target not reachable)",
    22: "self-collision error",
    23: "joint angle exceeds limit",
    24: "speed exceeds limit",
    25: "planning error",
    26: "Linux RT error",
    27: "command reply error",
    28: "end module communication error",
    30: "feedback speed exceeds limit",
    31: "collision caused abnormal current",
    32: "three-point circle calculation error",
    33: "controller GPIO error",
    34: "recording timeout",
    35: "safety boundary limit (target outside the allowed workspace)",
    36: "too many delay commands",
    37: "abnormal movement in manual mode",
    38: "abnormal joint angle",
    39: "abnormal communication between master and slave IC of the power board",
    40: "no error-free joint trajectory solution",
    41: "invalid friction file",
    42: "invalid calibration file",
    50: "six-axis force/torque sensor read error",
    51: "six-axis force/torque sensor set-mode error",
    52: "six-axis force/torque sensor set-zero error",
    53: "six-axis force/torque sensor overloaded",
    60: "linear speed exceeded limit in servo_j mode",
    110: "robot arm base board communication error",
    111: "control box external RS-485 device communication error",
}

WARNINGS: dict[int, str] = {
    11: "controller command cache is full",
    12: "user command parameter error",
    13: "user command control code does not exist",
    14: "user command has no solution (target not reachable)",
    15: "modbus command queue full",
}

NOT_READY = 9
"""The SDK's API code for "not ready to move" (the arm needs motion enable,
mode 0 and state 0). Used with the xArm's own codes in :class:`VendorError`."""

KINEMATIC_ERROR = 21
SAFETY_BOUNDARY = 35


def error_meaning(code: int) -> str:
    """Meaning of a controller error code ("no error" for 0)."""
    if code == 0:
        return "no error"
    return ERRORS.get(code, f"unknown controller error {code}")


def warning_meaning(code: int) -> str:
    """Meaning of a controller warning code ("no warning" for 0)."""
    if code == 0:
        return "no warning"
    return WARNINGS.get(code, f"unknown controller warning {code}")
