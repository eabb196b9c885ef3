"""UR controller codes read over RTDE: robot, safety and program states, and the status bits.

Sources: UR's RTDE guide and ur_rtde's ``getRobotMode`` / ``getSafetyMode`` docs
(``shared/spec/protocols.md`` C, C2).
"""

from __future__ import annotations

#: RTDE ``safety_mode`` codes.
SAFETY_MODES: dict[int, str] = {
    1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP",
    6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT",
    10: "VALIDATE_JOINT_ID", 11: "UNDEFINED_SAFETY_MODE", 12: "AUTOMATIC_MODE_SAFEGUARD_STOP",
    13: "SYSTEM_THREE_POSITION_ENABLING_STOP",
}
#: RTDE ``robot_mode`` codes.
ROBOT_MODES: dict[int, str] = {
    -1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF",
    4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE",
}
#: RTDE ``runtime_state`` codes (program state).
RUNTIME_STATES: dict[int, str] = {
    0: "STOPPING", 1: "STOPPED", 2: "PLAYING", 3: "PAUSING", 4: "PAUSED", 5: "RESUMING",
}
SAFETY_OK = (1, 2)          # NORMAL, REDUCED
SAFETY_REDUCED = 2
ROBOT_MODE_RUNNING = 7
#: ``robot_status_bits``: bit 1 is set while a program (ur_rtde's control script) runs.
STATUS_PROGRAM_RUNNING = 0x2
#: ``RTDEControlInterface`` flag (ur_rtde 1.6 ``Flags.FLAG_NO_WAIT``): without ``FLAG_UPLOAD_SCRIPT``
#: the constructor neither uploads the control script nor waits for it to run.
FLAG_NO_WAIT = 16


def name(table: dict[int, str], code: int) -> str:
    """``"3 PROTECTIVE_STOP"``: a code with its name, for messages."""
    return f"{code} {table.get(code, 'UNKNOWN')}"
