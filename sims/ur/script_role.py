"""The script interface (port 30003) and the role of ur_rtde's uploaded control script.

ur_rtde writes its URScript program (``def rtde_control(): ... end``) to port 30003; a
real controller runs it, and the script talks to the client through RTDE registers.
The emulator does not interpret URScript: :class:`ScriptRole` *plays* that program,
cycle by cycle, with the same register handshake (``shared/spec/protocols.md`` C2):

* ``output_int_register_0``: 1 = ready for a command, 2 = done with it;
* ``input_int_register_0``: the command id (0 = none), arguments in the input
  double / int registers; results in ``output_int_register_1`` / output doubles;
* ``output_int_register_2``: asynchronous progress (bit 15 running, bits 0-14
  progress, 16-23 write counter, 24-30 operation id).
"""

from __future__ import annotations

import logging
import re
import threading

from cellcal.devices.errors import CellcalError
from cellcal.devices.geometry.vendor_poses import pose_from_ur, pose_to_ur
from cellcal.devices.pose import Pose

from .controller import SAFETY_PROTECTIVE_STOP, ControllerState, pose_from_joints
from .net import Connection, Listener

log = logging.getLogger(__name__)

SCRIPT_PORT = 30003
#: Largest program kept (ur_rtde's is ~42 KB); a longer one is discarded.
MAX_PROGRAM_BYTES = 1 << 20
PROGRAM_NAME = "rtde_control"

# Command ids of ur_rtde 1.6 (RTDE::RobotCommand::Type).
MOVEJ, MOVEL, SET_TCP, PROTECTIVE_STOP, STOPL, STOPJ = 1, 3, 29, 31, 33, 34
GET_TCP_OFFSET, IS_STEADY, STOP_SCRIPT = 40, 47, 255
# output_int_register_0 values
READY, DONE = 1, 2
ASYNC_RUNNING = 1 << 15

_OFFSET = re.compile(r"reg_offset_(float|int)\s*=\s*(\d+)")
_DEF = re.compile(r"^[ \t]*def\s+(\w+)\s*\(\s*\)\s*:", re.MULTILINE)
_END = re.compile(r"^end[ \t]*$", re.MULTILINE)


class ProgramReader:
    """Cuts a byte stream into URScript programs: ``def name():`` up to a line ``end`` at column 0."""

    def __init__(self) -> None:
        self._buf = ""

    def feed(self, data: bytes) -> list[str]:
        """Add received bytes; return the complete programs now available."""
        self._buf += data.decode("utf-8", errors="replace")
        out: list[str] = []
        while True:
            start = _DEF.search(self._buf)
            if start is None:
                self._buf = self._buf[-256:]  # stray commands (e.g. "stopj(2)"): not programs
                return out
            end = _END.search(self._buf, start.end())
            if end is None:
                if len(self._buf) > MAX_PROGRAM_BYTES:
                    log.warning("script port: program longer than %d bytes discarded", MAX_PROGRAM_BYTES)
                    self._buf = ""
                return out
            out.append(self._buf[start.start():end.end()])
            self._buf = self._buf[end.end():]


class ScriptRole:
    """Plays ur_rtde's control script on the emulated controller.

    :meth:`load` is called with every program written to port 30003; :meth:`step` runs
    one controller cycle of the script (call it every 2 ms). Motion goes to the
    simulated arm; the arm moves along straight lines only, so ``moveJ`` moves linearly
    to the joint target's pose.

    Attributes:
        refuse_start: Fault injection: uploaded programs never start (as when the
            controller rejects the script).
        programs_received: Programs written to the script port, counted once each is started or refused.
        commands: Commands executed, by id.
    """

    def __init__(self, state: ControllerState) -> None:
        self.state = state
        self.refuse_start = False
        self.programs_received = 0
        self.commands: dict[int, int] = {}
        self.last_program = ""
        self._lock = threading.RLock()
        self._int_offset = 0
        self._float_offset = 0
        self._executing = False
        self._sync_move = False
        self._async_move = False
        self._op_id = 0
        self._writes = 0

    # ------------------------------------------------------------------ program life cycle
    def load(self, text: str) -> bool:
        """A program arrived on the script port: stop the running one, start this one; True if it runs."""
        with self._lock:
            try:
                names = _DEF.findall(text)
                self.stop_program("a new program arrived")
                if not names or names[0] != PROGRAM_NAME:
                    log.info("script port: program %s is not ur_rtde's control script; not run", names[:1])
                    return False
                self.last_program = text
                return self.start_program()
            finally:
                self.programs_received += 1  # counted once handled: a watcher then sees its effect

    def start_program(self) -> bool:
        """Start the last control script (``load`` or the dashboard's ``play``); False if refused."""
        with self._lock, self.state.lock:
            if self.refuse_start or not self.last_program or not self.state.can_move():
                return False
            offsets = dict(_OFFSET.findall(self.last_program))
            self._int_offset = int(offsets.get("int", 0))
            self._float_offset = int(offsets.get("float", 0))
            self._executing = self._sync_move = self._async_move = False
            self.state.program_running = True
            self._write_async(running=False)
            self.state.set_output_int(self._int_offset, READY)
            return True

    def stop_program(self, why: str) -> None:
        """End the running program; the arm halts (motion belongs to the program)."""
        with self._lock, self.state.lock:
            if self.state.program_running:
                log.info("control script stopped: %s", why)
                self.state.program_running = False
                self.state.halt()
            self._sync_move = self._async_move = False

    # ------------------------------------------------------------------ one cycle
    def step(self) -> None:
        """One controller cycle of the script's main loop."""
        with self._lock, self.state.lock:
            if not self.state.program_running:
                return
            moving = self.state.arm.is_moving()
            if self._async_move and not moving:
                self._async_move = False
                self._write_async(running=False)
            if self._sync_move:
                if moving:
                    return
                self._sync_move = False
                self._signal(DONE)
            cmd = self.state.input_int(self._int_offset)
            if cmd == 0:
                self._executing = False
                self._signal(READY)
            elif not self._executing:
                self._executing = True
                self.commands[cmd] = self.commands.get(cmd, 0) + 1
                self._process(cmd)

    def _signal(self, value: int) -> None:
        self.state.set_output_int(self._int_offset, value)

    def _write_async(self, *, running: bool) -> None:
        """``output_int_register_2``: operation id, write counter, running bit."""
        self._writes = (self._writes + 1) & 0xFF
        value = (self._op_id & 0x7F) << 24 | self._writes << 16 | (ASYNC_RUNNING if running else 0)
        self.state.set_output_int(self._int_offset + 2, value)

    # ------------------------------------------------------------------ commands
    def _doubles(self, first: int, count: int) -> list[float]:
        return [self.state.input_double(self._float_offset + first + i) for i in range(count)]

    def _process(self, cmd: int) -> None:
        if cmd == STOP_SCRIPT:
            self.stop_program("stopScript")
            return
        if cmd in (MOVEL, MOVEJ):
            if not self._move(cmd):
                return
        elif cmd in (STOPL, STOPJ):
            self._stop_motion()
        elif cmd == SET_TCP:
            self.state.tcp_offset = pose_from_ur(self._doubles(0, 6))
        elif cmd == GET_TCP_OFFSET:
            for i, v in enumerate(pose_to_ur(self.state.tcp_offset)):
                self.state.set_output_double(self._float_offset + i, float(v))
        elif cmd == IS_STEADY:
            self.state.set_output_int(self._int_offset + 1, 0 if self.state.arm.is_moving() else 1)
        elif cmd == PROTECTIVE_STOP:
            self.state.enter_safety(SAFETY_PROTECTIVE_STOP)
            return
        else:
            log.info("control script: command %d is not emulated; reported done", cmd)
        if not self._sync_move:
            self._signal(DONE)

    def _stop_motion(self) -> None:
        self.state.halt()
        if self._async_move:
            self._async_move = False
            self._write_async(running=False)

    def _move(self, cmd: int) -> bool:
        """moveL / moveJ (recipe 1: d0-5 target, d6 speed, d7 acceleration, int1 async); False if it failed."""
        target, speed, acc = self._doubles(0, 6), *self._doubles(6, 2)
        asynchronous = self.state.input_int(self._int_offset + 1) == 1
        flange = pose_from_joints(target) if cmd == MOVEJ else self.state.flange_for_tcp(target)
        self._stop_motion()
        if not self._start_motion(flange, speed, acc):
            return False
        self.state.target_tcp = pose_from_ur(target) if cmd == MOVEL else flange @ self.state.tcp_offset
        if asynchronous:
            self._op_id = (self._op_id + 1) & 0x7F
            self._async_move = True
            self._write_async(running=True)
        else:
            self._sync_move = True
        return True

    def _start_motion(self, flange: Pose, speed: float, acc: float) -> bool:
        arm = self.state.arm
        try:
            arm.begin_move_linear(flange, speed, acc)
        except CellcalError as exc:
            self.stop_program(f"motion refused: {exc}")
            return False
        if arm.current_error()[0]:
            # The sim arm refuses an unreachable target with an error code; on a UR the
            # script's inverse kinematics fail and the program stops.
            arm.set_error(0)
            self.stop_program("target out of reach (inverse kinematics failed)")
            return False
        return True


class ScriptPort:
    """The port ur_rtde uploads its script to; hands every complete program to :meth:`ScriptRole.load`."""

    def __init__(self, role: ScriptRole, host: str, port: int = SCRIPT_PORT) -> None:
        self.role = role
        self.listener = Listener(host, port, self._serve, f"ur-emulator script {host}")

    def start(self) -> None:
        """Start listening (raises OSError if the address is taken)."""
        self.listener.start()

    def close(self) -> None:
        """Close every connection and stop listening."""
        self.listener.close()

    def _serve(self, conn: Connection) -> None:
        reader = ProgramReader()
        while not conn.closing.is_set():
            data = conn.recv(0.05)
            if data == b"":
                return
            for program in reader.feed(data or b""):
                self.role.load(program)
