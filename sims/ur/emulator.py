"""A UR controller (e-Series, PolyScope 5.11) on one loopback address, backed by a simulated arm.

Anything that speaks to a UR over RTDE, the script port and the dashboard (cellcal's
``ur`` driver, or ur_rtde itself from another process) talks to it as to a real one::

    emulator = UREmulator(SimArm(SimArmConfig(**UR_LIKE)).connect(), host="127.0.0.2")
    emulator.start()
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from dataclasses import dataclass
from typing import Any

from cellcal.devices.geometry.vendor_poses import pose_to_ur
from cellcal.devices.pose import Pose

from .controller import (
    CYCLE_S,
    ROBOT_MODE_RUNNING,
    SAFETY_NORMAL,
    SAFETY_PROTECTIVE_STOP,
    SAFETY_ROBOT_EMERGENCY_STOP,
    ArmModel,
    ControllerState,
)
from .dashboard import DASHBOARD_PORT, Dashboard, DashboardServer, Identity
from .rtde_server import RTDE_PORT, RTDEServer
from .script_role import SCRIPT_PORT, ScriptPort, ScriptRole

log = logging.getLogger(__name__)

#: UR5e-like settings of the simulated arm: 850 mm reach, ±0.03 mm repeatability.
UR_LIKE: dict[str, float] = {"reach_m": 0.85, "repeatability_m": 3e-5}
SAFETY_FAULTS = {"protective_stop": SAFETY_PROTECTIVE_STOP, "emergency_stop": SAFETY_ROBOT_EMERGENCY_STOP}


@dataclass
class _MotionFault:
    mode: int
    at_progress: float


class UREmulator:
    """Serve RTDE (30004), the script port (30003) and the dashboard (29999) for one simulated arm.

    A controller cycle runs every 2 ms in its own thread: it samples the arm for the
    RTDE streams, fires armed faults and steps the control-script role.

    Fault injection: :meth:`safety_stop` (protective or emergency stop, now or part-way
    through the next motion), :meth:`refuse_script` (uploaded scripts never start),
    :meth:`freeze_stream` (RTDE data stops, sockets stay open), :meth:`send_raw_rtde` (malformed
    bytes), :meth:`drop_connections` (every link cut, new ones optionally reset for a while).

    Args:
        arm: The simulated arm (connected).
        host: Loopback address to listen on (ur_rtde's ports are fixed, so one address per emulator).
        powered: Start powered with brakes released; else POWER_OFF.
        unlock_delay_s: Minimum time between a protective stop and its unlock (UR: 5 s).
        identity: What the dashboard reports.
        ports: ``(rtde, script, dashboard)`` ports (0 = any free port, see :attr:`ports`).
    """

    def __init__(self, arm: ArmModel, host: str = "127.0.0.1", *, powered: bool = True,
                 unlock_delay_s: float = 5.0, identity: Identity | None = None,
                 ports: tuple[int, int, int] = (RTDE_PORT, SCRIPT_PORT, DASHBOARD_PORT)) -> None:
        self.host = host
        self.state = ControllerState(arm, powered=powered, unlock_delay_s=unlock_delay_s)
        self.role = ScriptRole(self.state)
        self.dashboard = Dashboard(self.state, self.role, identity)
        self._wake = threading.Event()
        self.rtde = RTDEServer(self.state, host, ports[0], on_input=self._wake.set)
        self.script_port = ScriptPort(self.role, host, ports[1])
        self.dashboard_server = DashboardServer(self.dashboard, host, ports[2])
        self._servers = (self.rtde, self.script_port, self.dashboard_server)
        self._lock = threading.Lock()
        self._fault: _MotionFault | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._restore_timer: threading.Timer | None = None

    @property
    def ports(self) -> tuple[int, int, int]:
        """``(rtde, script, dashboard)`` ports listened on (known once started)."""
        return self.rtde.listener.port, self.script_port.listener.port, self.dashboard_server.listener.port

    # ------------------------------------------------------------------ life cycle
    def start(self) -> None:
        """Listen on all three ports and start the controller cycle.

        Raises:
            OSError: If a port cannot be bound on :attr:`host` (nothing is left listening).
        """
        started = []
        try:
            for server in self._servers:
                server.start()
                started.append(server)
        except OSError:
            for server in started:
                server.close()
            raise
        self._stop.clear()
        self._thread = threading.Thread(target=self._cycle_loop, name=f"ur-emulator cycle {self.host}", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop everything and join every thread (bounded); safe to call twice."""
        self._stop.set()
        self._wake.set()
        timer, self._restore_timer = self._restore_timer, None
        if timer is not None:
            timer.cancel()
        for server in self._servers:
            server.close()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(2.0)
        self.state.halt()

    def __enter__(self) -> UREmulator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _cycle_loop(self) -> None:
        next_cycle = time.monotonic()
        while not self._stop.is_set():
            try:
                self.state.refresh()
                self._fire_fault()
                self.role.step()
            except Exception:
                log.exception("ur emulator %s: controller cycle failed", self.host)
            next_cycle += CYCLE_S
            delay = next_cycle - time.monotonic()
            if delay < -0.05:
                next_cycle = time.monotonic()  # fell behind (a loaded machine): skip, do not burst
            self._wake.wait(max(0.0, delay))
            self._wake.clear()

    # ------------------------------------------------------------------ faults
    def safety_stop(self, kind: str = "protective_stop", *, at_progress: float | None = None) -> None:
        """A protective or emergency stop: now, or once the next motion is ``at_progress`` (0..1) done.

        The arm halts, the control script stops; a protective stop is unlocked from the
        dashboard (after ``unlock_delay_s``), an e-stop by :meth:`release_emergency_stop`.
        """
        if kind not in SAFETY_FAULTS:
            raise ValueError(f"safety stop kind must be one of {sorted(SAFETY_FAULTS)}, got {kind!r}")
        mode = SAFETY_FAULTS[kind]
        if at_progress is None:
            self.state.enter_safety(mode)
            return
        if not 0.0 <= at_progress < 1.0:
            raise ValueError(f"at_progress must be in [0, 1), got {at_progress!r}")
        with self._lock:
            self._fault = _MotionFault(mode, float(at_progress))

    def _fire_fault(self) -> None:
        with self._lock:
            fault = self._fault
            if fault is None or not self.state.arm.is_moving():
                return
            if self.state.arm.motion_progress() < fault.at_progress:
                return
            self._fault = None
        log.info("ur emulator %s: safety stop (mode %d) at %.0f%% of a motion", self.host, fault.mode,
                 100 * fault.at_progress)
        self.state.enter_safety(fault.mode)

    def release_emergency_stop(self) -> None:
        """Pull the e-stop button out (power on and brake release follow from the dashboard)."""
        self.state.release_emergency_stop()

    def refuse_script(self, refuse: bool = True) -> None:
        """Uploaded control scripts never start (``True``) or start normally again."""
        self.role.refuse_start = bool(refuse)

    def freeze_stream(self, target: str = "all", *, new_sessions: bool = False) -> int:
        """Stop RTDE data packages to ``"receive"``, ``"control"`` or ``"all"`` sessions; sockets stay open."""
        return self.rtde.freeze(target, new_sessions=new_sessions)

    def send_raw_rtde(self, data_hex: str, target: str = "receive") -> int:
        """Send the bytes ``data_hex`` (hex text) to the ``target`` RTDE sessions between two messages."""
        return self.rtde.send_raw(bytes.fromhex(data_hex), target)

    def unfreeze_stream(self) -> None:
        """Resume every RTDE stream."""
        self.rtde.unfreeze()

    def drop_connections(self, refuse_s: float = 0.0) -> int:
        """Cut every connection on all three ports; turn new ones away (reset on accept) for ``refuse_s``
        seconds (< 0: until :meth:`accept_connections`). The control script stops with its link.
        Returns the links cut."""
        listeners = [s.listener for s in self._servers]
        if refuse_s != 0.0:
            for listener in listeners:
                listener.refuse()
        cut = sum(listener.drop_all() for listener in listeners)
        self.role.stop_program("connection dropped")
        if refuse_s > 0.0:
            timer = threading.Timer(refuse_s, self.accept_connections)
            timer.daemon = True
            self._restore_timer = timer
            timer.start()
        return cut

    def accept_connections(self) -> None:
        """Serve new connections again after :meth:`drop_connections` turned them away."""
        for server in self._servers:
            server.listener.accept_again()

    def reset(self) -> None:
        """Back to a healthy controller: faults off, streams and ports open, safety normal, powered,
        no program running (the next client uploads its script), TCP offset zero."""
        with self._lock:
            self._fault = None
        self.refuse_script(False)
        self.unfreeze_stream()
        self.accept_connections()
        self.role.stop_program("reset")
        with self.state.lock:
            self.state.safety_mode = SAFETY_NORMAL
            self.state.robot_mode = ROBOT_MODE_RUNNING
            self.state.remote_control = True
            self.state.tcp_offset = Pose.identity()

    def set_time_scale(self, time_scale: float) -> None:
        """Wall seconds per simulated second of the arm's next motions (0 = instant)."""
        arm: Any = self.state.arm
        arm.config = dataclasses.replace(arm.config, time_scale=float(time_scale))

    def set_unlock_delay(self, delay_s: float) -> None:
        """Minimum time between a protective stop and its unlock from the dashboard, s (UR: 5)."""
        self.state.unlock_delay_s = float(delay_s)

    def set_remote_control(self, remote: bool) -> None:
        """Pendant in Remote Control (True) or Local Control (the control interface refuses to start)."""
        self.state.remote_control = bool(remote)

    # ------------------------------------------------------------------ inspection
    def snapshot(self) -> dict[str, Any]:
        """JSON-able state for tests and logs (true poses, modes, counters)."""
        arm: Any = self.state.arm
        with self.state.lock:
            return {
                "flange": [float(v) for v in pose_to_ur(arm.true_flange_pose())],
                "tcp": [float(v) for v in pose_to_ur(self.state.tcp_pose())],
                "moving": bool(arm.is_moving()),
                "robot_mode": self.state.robot_mode,
                "safety_mode": self.state.safety_mode,
                "program_running": self.state.program_running,
                "programs_received": self.role.programs_received,
                "commands": {str(k): v for k, v in self.role.commands.items()},
                "stops": int(getattr(arm, "stops", 0)),
                "moves_started": int(getattr(arm, "moves_started", 0)),
                "sim_elapsed_s": float(arm.world.clock.elapsed_s) if hasattr(arm, "world") else 0.0,
                "rtde_sessions": [s.kind for s in self.rtde.sessions],
                "connections": {s.listener.name: len(s.listener.connections) for s in self._servers},
                "dashboard_commands": list(self.dashboard.commands)[-20:],
            }
