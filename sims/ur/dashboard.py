"""The emulated controller's dashboard server (port 29999): one reply line per command line.

Replies are worded as PolyScope 5.11 words them (``shared/spec/protocols.md`` C2);
ur_rtde's ``DashboardClient`` compares some of them literally.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from .controller import (
    ROBOT_MODE_NAMES,
    SAFETY_MODE_NAMES,
    ControllerState,
)
from .net import Connection, Listener
from .script_role import PROGRAM_NAME, ScriptRole

DASHBOARD_PORT = 29999
GREETING = "Connected: Universal Robots Dashboard Server"
#: Longest command line accepted, bytes (a longer one is answered as not understood).
MAX_LINE_BYTES = 4096
KEEP_COMMANDS = 200
UNLOCK_REFUSED = ("Cannot unlock protective stop until 5s after occurrence. "
                  "Always inspect cause of protective stop before unlocking")


@dataclass(frozen=True)
class Identity:
    """What the dashboard reports about the robot.

    Attributes:
        model: ``get robot model`` reply (e.g. ``UR5``).
        serial: ``get serial number`` reply.
        polyscope: ``PolyscopeVersion`` reply.
    """

    model: str = "UR5"
    serial: str = "20235500001"
    polyscope: str = "URSoftware 5.11.0.108249 (Nov 04 2021)"


class Dashboard:
    """Answers dashboard commands from the controller state (no sockets; see :class:`DashboardServer`).

    Args:
        state: Controller state read and changed.
        role: The control-script role (``play`` / ``stop`` act on its program).
        identity: Model, serial number and software version reported.
    """

    def __init__(self, state: ControllerState, role: ScriptRole, identity: Identity | None = None) -> None:
        self.state = state
        self.role = role
        self.identity = identity or Identity()
        #: The latest commands received (at most :data:`KEEP_COMMANDS`), oldest first.
        self.commands: deque[str] = deque(maxlen=KEEP_COMMANDS)
        self._table: dict[str, Callable[[], str]] = {
            "polyscopeversion": lambda: self.identity.polyscope,
            "get serial number": lambda: self.identity.serial,
            "get robot model": lambda: self.identity.model,
            "is in remote control": lambda: "true" if self.state.remote_control else "false",
            "robotmode": lambda: f"Robotmode: {ROBOT_MODE_NAMES.get(self.state.robot_mode, 'UNKNOWN')}",
            "safetymode": lambda: f"Safetymode: {SAFETY_MODE_NAMES.get(self.state.safety_mode, 'UNKNOWN')}",
            "safetystatus": lambda: f"Safetystatus: {SAFETY_MODE_NAMES.get(self.state.safety_mode, 'UNKNOWN')}",
            "programstate": self._program_state,
            "running": lambda: f"Program running: {'true' if self.state.program_running else 'false'}",
            "play": self._play,
            "stop": self._stop,
            "pause": self._pause,
            "power on": self._power_on,
            "power off": self._power_off,
            "brake release": self._brake_release,
            "unlock protective stop": lambda: "Protective stop releasing" if self.state.unlock_protective_stop()
            else UNLOCK_REFUSED,
            "close safety popup": lambda: "closing safety popup",
            "close popup": lambda: "closing popup",
            "restart safety": self._restart_safety,
            "get loaded program": lambda: "No program loaded",
            "isprogramsaved": lambda: "false <unnamed>",
            "get operational mode": lambda: "NONE",
            "shutdown": lambda: "Shutting down",
            "quit": lambda: "Disconnected",
        }

    def reply(self, line: str) -> str:
        """The reply to one command line (without its newline)."""
        command = line.strip()
        self.commands.append(command)
        key = command.lower()
        handler = self._table.get(key)
        if handler is not None:
            return handler()
        for prefix, answer in (("popup ", "showing popup"), ("addtolog ", "Added log message"),
                               ("load ", f"File not found: {command[5:]}"), ("setuserrole ", "Setting user role")):
            if key.startswith(prefix):
                return answer
        return f"could not understand: '{command}'"

    def _program_state(self) -> str:
        return f"{'PLAYING' if self.state.program_running else 'STOPPED'} {PROGRAM_NAME}"

    def _play(self) -> str:
        return "Starting program" if self.role.start_program() else "Failed to execute: play"

    def _stop(self) -> str:
        self.role.stop_program("dashboard stop")
        return "Stopped"

    def _pause(self) -> str:
        self.role.stop_program("dashboard pause")
        return "Pausing program"

    def _power_on(self) -> str:
        self.state.power(True)
        return "Powering on"

    def _power_off(self) -> str:
        self.role.stop_program("power off")
        self.state.power(False)
        return "Powering off"

    def _brake_release(self) -> str:
        self.state.brake_release()
        return "Brake releasing"

    def _restart_safety(self) -> str:
        self.role.stop_program("restart safety")
        with self.state.lock:
            if self.state.safety_mode != 7:  # an e-stop still needs the button pulled out
                self.state.safety_mode = 1
            self.state.power(False)
        return "Restarting safety"


class DashboardServer:
    """The dashboard port: greeting, then one reply line per newline-terminated command."""

    def __init__(self, dashboard: Dashboard, host: str, port: int = DASHBOARD_PORT) -> None:
        self.dashboard = dashboard
        self.listener = Listener(host, port, self._serve, f"ur-emulator dashboard {host}")

    def start(self) -> None:
        """Start listening (raises OSError if the address is taken)."""
        self.listener.start()

    def close(self) -> None:
        """Close every connection and stop listening."""
        self.listener.close()

    def _serve(self, conn: Connection) -> None:
        if not conn.send((GREETING + "\n").encode()):
            return
        buf = b""
        while not conn.closing.is_set():
            data = conn.recv(0.05)
            if data == b"":
                return
            buf += data or b""
            while b"\n" in buf:
                raw, buf = buf.split(b"\n", 1)
                line = raw.decode("utf-8", errors="replace").rstrip("\r")
                reply = self.dashboard.reply(line)
                if not conn.send((reply + "\n").encode()) or line.strip().lower() == "quit":
                    return
            if len(buf) > MAX_LINE_BYTES:
                conn.send(b"could not understand: '<line too long>'\n")
                buf = b""
