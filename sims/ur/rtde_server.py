"""The emulated controller's RTDE interface (port 30004): negotiation, recipes and the output stream.

One session per connection, in one thread: it answers the client's requests and, once
started, sends every output recipe at its requested frequency. Input data packages are
written to the controller's registers. A session can be frozen (fault injection): the
socket stays open and requests are still read, but no data package is sent.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from cellcal.devices.errors import ProtocolError

from . import rtde_wire as w
from .controller import CYCLE_S, ControllerState
from .net import POLL_S, Connection, Listener

log = logging.getLogger(__name__)

RTDE_PORT = 30004
#: Highest output rate the controller offers (e-Series), Hz.
MAX_FREQUENCY_HZ = 500.0
FREEZE_TARGETS = ("receive", "control", "all")


@dataclass
class _Output:
    recipe: w.Recipe
    period_s: float
    next_due: float = 0.0
    last_cycle: float = -1.0


class RTDESession:
    """One client connection to the RTDE interface.

    Attributes:
        frozen: No data packages are sent while set (the socket stays open).
        outputs: Output recipes, by id.
        inputs: Input recipes, by id (numbered 1, 2, 3... in setup order).
        packages_sent: Data packages sent.
    """

    def __init__(self, conn: Connection, server: RTDEServer) -> None:
        self.conn = conn
        self.server = server
        self.frozen = False
        self.started = False
        self.outputs: dict[int, _Output] = {}
        self.inputs: dict[int, w.Recipe] = {}
        self.packages_sent = 0
        #: Raw bytes to send between two messages (fault injection), by this session's own thread.
        self.pending_raw: list[bytes] = []
        self._handlers: dict[int, Callable[[bytes], None]] = {
            w.REQUEST_PROTOCOL_VERSION: self._on_protocol, w.GET_URCONTROL_VERSION: self._on_version,
            w.CONTROL_PACKAGE_SETUP_OUTPUTS: self._on_outputs, w.CONTROL_PACKAGE_SETUP_INPUTS: self._on_inputs,
            w.CONTROL_PACKAGE_START: self._on_start, w.CONTROL_PACKAGE_PAUSE: self._on_pause,
            w.DATA_PACKAGE: self._on_data, w.TEXT_MESSAGE: lambda _p: None,
        }

    @property
    def kind(self) -> str:
        """``"control"`` if the client set up inputs (ur_rtde's control interface), else ``"receive"``."""
        return "control" if self.inputs else "receive"

    # ------------------------------------------------------------------ serving
    def run(self) -> None:
        """Serve until the client goes away or the connection is cut."""
        reader = w.FrameReader()
        while not self.conn.closing.is_set():
            data = self.conn.recv(self._wait_s())
            if data == b"":
                return
            if data:
                try:
                    for msg_type, payload in reader.feed(data):
                        self._dispatch(msg_type, payload)
                except ProtocolError as exc:
                    log.warning("rtde #%d: %s; closing the connection", self.conn.number, exc)
                    return
            self._send_due()

    def _wait_s(self) -> float:
        if not self.started or self.frozen or not self.outputs:
            return POLL_S
        due = min(o.next_due for o in self.outputs.values())
        return min(POLL_S, max(0.0, due - time.monotonic()))

    def _dispatch(self, msg_type: int, payload: bytes) -> None:
        if msg_type != w.DATA_PACKAGE:
            log.debug("rtde #%d: request %r (%d bytes)", self.conn.number, chr(msg_type), len(payload))
        handler = self._handlers.get(msg_type)
        if handler is None:
            log.warning("rtde #%d: ignoring message type %d", self.conn.number, msg_type)
            return
        handler(payload)

    def _send_due(self) -> None:
        """Send each output recipe that is due: at most one package per controller cycle, no catch-up bursts."""
        while self.pending_raw:  # injected bytes go out whole, between two messages
            self.conn.send(self.pending_raw.pop(0))
        if not self.started or self.frozen:
            return
        now = time.monotonic()
        cycle = self.server.state.timestamp()
        for out in self.outputs.values():
            if now < out.next_due:
                continue
            if cycle <= out.last_cycle:  # this cycle was sent already (late wake-up): next cycle
                out.next_due = now + CYCLE_S / 4
                continue
            values = self.server.state.values(out.recipe.names, timestamp=cycle)
            if not self.conn.send(w.data_package(out.recipe.recipe_id, out.recipe.pack(values))):
                return
            self.packages_sent += 1
            out.last_cycle = cycle
            out.next_due += out.period_s
            if out.next_due <= now:  # behind schedule (a loaded machine): skip, as a controller would
                out.next_due = now + out.period_s

    # ------------------------------------------------------------------ requests
    def _on_protocol(self, payload: bytes) -> None:
        version = w.parse_protocol_request(payload)
        self.conn.send(w.protocol_reply(version == w.PROTOCOL_VERSION))

    def _on_version(self, _payload: bytes) -> None:
        self.conn.send(w.version_reply(*self.server.version))

    def _on_outputs(self, payload: bytes) -> None:
        freq, names = w.parse_output_setup(payload)
        types = [w.output_type(n) or w.NOT_FOUND for n in names]
        ok = w.NOT_FOUND not in types and 0.0 < freq <= MAX_FREQUENCY_HZ
        recipe_id = len(self.outputs) + 1 if ok else 0
        if ok:
            recipe = w.Recipe(recipe_id, names, tuple(types), freq)
            self.outputs[recipe_id] = _Output(recipe, 1.0 / freq, time.monotonic())
        else:
            log.warning("rtde #%d: output setup refused (%g Hz, %s)", self.conn.number, freq,
                        [n for n, t in zip(names, types, strict=True) if t == w.NOT_FOUND])
        self.conn.send(w.setup_reply(w.CONTROL_PACKAGE_SETUP_OUTPUTS, recipe_id, types))

    def _on_inputs(self, payload: bytes) -> None:
        names = w.parse_input_setup(payload)
        types = self.server.state.claim_inputs(self.conn.number, names)
        ok = w.NOT_FOUND not in types and w.IN_USE not in types
        recipe_id = len(self.inputs) + 1 if ok else 0
        if ok:
            self.inputs[recipe_id] = w.Recipe(recipe_id, names, tuple(types))
        self.conn.send(w.setup_reply(w.CONTROL_PACKAGE_SETUP_INPUTS, recipe_id, types))

    def _on_start(self, _payload: bytes) -> None:
        now = time.monotonic()
        for out in self.outputs.values():
            out.next_due = now
        self.started = True
        self.frozen = self.frozen or self.server.freezes_new(self.kind)
        self.conn.send(w.start_reply(True))

    def _on_pause(self, _payload: bytes) -> None:
        self.started = False
        self.conn.send(w.pause_reply(True))

    def _on_data(self, payload: bytes) -> None:
        if not payload:
            raise ProtocolError("rtde: empty data package")
        recipe = self.inputs.get(payload[0])
        if recipe is None:
            log.warning("rtde #%d: data package for unknown input recipe %d", self.conn.number, payload[0])
            return
        self.server.state.write_inputs(recipe.unpack(payload[1:]))
        self.server.on_input()


class RTDEServer:
    """The RTDE interface of one emulated controller.

    Args:
        state: The controller state streamed and written.
        host: Address to listen on.
        port: TCP port (30004 on a real controller).
        version: ``(major, minor, bugfix, build)`` reported to ``v`` requests.
        on_input: Called after every input data package (wakes the control-script role).
    """

    def __init__(self, state: ControllerState, host: str, port: int = RTDE_PORT,
                 version: tuple[int, int, int, int] = (5, 11, 0, 0),
                 on_input: Callable[[], None] | None = None) -> None:
        self.state = state
        self.version = version
        self.on_input = on_input or (lambda: None)
        self.listener = Listener(host, port, self._serve, f"ur-emulator rtde {host}")
        self._lock = threading.Lock()
        self._sessions: dict[int, RTDESession] = {}
        self._freeze_new: str | None = None

    @property
    def sessions(self) -> list[RTDESession]:
        """Sessions currently connected."""
        with self._lock:
            return list(self._sessions.values())

    def start(self) -> None:
        """Start listening (raises OSError if the address is taken)."""
        self.listener.start()

    def close(self) -> None:
        """Close every session and stop listening."""
        self.listener.close()

    def _serve(self, conn: Connection) -> None:
        session = RTDESession(conn, self)
        with self._lock:
            self._sessions[conn.number] = session
        log.info("rtde #%d: connected from %s:%d", conn.number, *conn.peer)
        try:
            session.run()
        finally:
            log.info("rtde #%d: closed (%s, %d inputs, %d packages sent)", conn.number, session.kind,
                     len(session.inputs), session.packages_sent)
            with self._lock:
                self._sessions.pop(conn.number, None)
            self.state.release_inputs(conn.number)

    # ------------------------------------------------------------------ faults
    def freeze(self, target: str = "all", *, new_sessions: bool = False) -> int:
        """Stop the data stream of the matching sessions (sockets stay open); returns how many.

        Args:
            target: ``"receive"`` (sessions without inputs), ``"control"`` or ``"all"``.
            new_sessions: Sessions started later are frozen too, until :meth:`unfreeze`.
        """
        if target not in FREEZE_TARGETS:
            raise ValueError(f"freeze target must be one of {FREEZE_TARGETS}, got {target!r}")
        hit = [s for s in self.sessions if target in ("all", s.kind)]
        for session in hit:
            session.frozen = True
        self._freeze_new = target if new_sessions else None
        return len(hit)

    def send_raw(self, data: bytes, target: str = "receive") -> int:
        """Send ``data`` as is to the matching sessions, between two of their messages; returns how many.

        Fault injection: a malformed message (a size field smaller than its header, say) as a
        broken or hostile controller would send it.
        """
        if target not in FREEZE_TARGETS:
            raise ValueError(f"target must be one of {FREEZE_TARGETS}, got {target!r}")
        hit = [s for s in self.sessions if target in ("all", s.kind)]
        for session in hit:
            session.pending_raw.append(bytes(data))
        return len(hit)

    def unfreeze(self) -> None:
        """Resume every stream; new sessions stream normally."""
        self._freeze_new = None
        for session in self.sessions:
            session.frozen = False

    def freezes_new(self, kind: str) -> bool:
        """Whether a session of ``kind`` starting now is frozen from the start."""
        target = self._freeze_new
        return target is not None and target in ("all", kind)
