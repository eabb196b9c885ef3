"""A wire-level emulator of an ifm O3R VPU: XML-RPC + PCIC over TCP, on 127.0.0.1.

Made like the device by default (ADR 0024): PCIC ports numbered as a VPU numbers them
(``portN`` on base + N, the IMU on port6, an application instance on base + 1000) when
given a base port, chunk header versions as in a real capture, TOF_INFO version 4, a
realistic distance resolution, a non-zero factory optic-to-head extrinsic, state
changes that take time, a CONF-only mode, a schema-like read-only table, a clock that
counts from boot unless asked for Unix time, and XML-RPC faults labelled as its own.
Frames come from any :class:`~.frames.FrameSource` (e.g. ``SimCamera``)::

    emu = O3REmulator(SimCamera().connect(), state="IDLE").start()  # then emu.xmlrpc_port, emu.pcic_port
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from socketserver import ThreadingMixIn
from typing import Any, Literal
from xmlrpc.server import SimpleXMLRPCRequestHandler, SimpleXMLRPCServer

import numpy as np
from scipy.spatial.transform import Rotation

from cellcal.devices.geometry.camera_model import pixel_grid_rays

from .config_tree import FIRMWARE, RULES, ConfigTree, ConfigTreeError, Rule, default_tree
from .encoder import FrameEncoder
from .frames import FrameSource, PerFrame, PerPose
from .pcic_server import Conn, PcicPort
from .wire import DEFAULT_CHUNKS, DISTANCE_RESOLUTION_M, message, models_from_intrinsics

RPC_PATH = "/api/rpc/v1/com.ifm.efector/"
FAULT_KINDS = ("drop", "stall", "truncate", "corrupt", "async_error")
#: Optical frame in the head frame of a real O3R222 (transX/Y/Z m, rotX/Y/Z rad; the TOF_INFO v4 capture).
FACTORY_OPTIC_TO_HEAD = (0.0, 0.0, 0.00841006, -0.0204563, 0.0181109, -0.00622652)
#: Uptime the boot clock starts from, s (the real capture's clock read 3.76 days).
BOOT_UPTIME_S = 324896.0


@dataclass
class _Fault:
    kind: str
    params: dict[str, Any] = field(default_factory=dict)


class _RpcHandler(SimpleXMLRPCRequestHandler):
    rpc_paths = (RPC_PATH, RPC_PATH.rstrip("/"))

    def log_message(self, format: str, *args: Any) -> None:
        return None


class _RpcServer(ThreadingMixIn, SimpleXMLRPCServer):
    daemon_threads = True
    block_on_close = True
    allow_reuse_address = True


@dataclass(frozen=True)
class EmulatorOptions:
    """How the emulated VPU behaves (defaults: like the device).

    Attributes:
        port_name: VPU port of the 3D head, ``portN``.
        state: Initial port state (RUN, IDLE, CONF).
        frame_rate_hz: Frame rate in RUN.
        max_frame_rate_hz: Largest frame rate the tree accepts (30 as on a VPU; raise for load tests).
        distance_resolution_m: Metres per distance count (10 / 65535 as on a VPU).
        optic_to_head: Factory optical-to-head extrinsic (transX/Y/Z m, rotX/Y/Z rad).
        header_version: Chunk header version for every chunk, or None for the real mix.
        tof_info_version: TOF_INFO version 1..4.
        confidence_bits: 16 (current firmware) or 8 (older firmware).
        mode: Initial mode of the 3D head (``cyclic_4m_2m_4m_2m`` cycles measurement blocks).
        state_change_s: How long a state change takes (the ``set`` answers after it), s.
        clock: ``"boot"`` (time since boot, as a VPU without SNTP) or ``"unix"`` (the source's time).
        frames: ``"per_frame"`` (one source capture per frame, deterministic) or ``"per_pose"``
            (one capture per camera pose plus fresh noise per frame, for load rates).
        noise_scale: Noise multiplier of ``per_pose`` frames.
        capture_timeout_s: Timeout passed to ``source.capture``.
    """

    port_name: str = "port2"
    state: str = "RUN"
    frame_rate_hz: float = 20.0
    max_frame_rate_hz: float = 30.0
    distance_resolution_m: float = DISTANCE_RESOLUTION_M
    optic_to_head: tuple[float, float, float, float, float, float] = FACTORY_OPTIC_TO_HEAD
    header_version: int | None = None
    tof_info_version: int = 4
    confidence_bits: int = 16
    mode: str = "standard_range4m"
    state_change_s: float = 0.3
    clock: Literal["boot", "unix"] = "boot"
    frames: Literal["per_frame", "per_pose"] = "per_frame"
    noise_scale: float = 1.0
    capture_timeout_s: float = 5.0


class O3REmulator:
    """Emulated O3R VPU.

    Serves, on ``host`` only:

    * XML-RPC at ``/api/rpc/v1/com.ifm.efector/``: ``get``, ``set``, ``getInit``,
      ``saveInit``, ``getInitStatus``, ``getSchema``, ``reset``, ``getSWVersion`` (what
      ifm3dpy 1.6 calls); faults carry the emulator's own codes, labelled as such;
    * a PCIC server per VPU port (the 3D head, its 2D head, port6 IMU, application
      ``app0``); only the 3D port sends frames. It honours ``p``, ``c`` (chunks
      100/101/300/420; other O3R blob ids accepted and not sent, unknown ones refused)
      and ``t`` (only in IDLE). In RUN frames are sent at ``/ports/<port>/acquisition/framerate``
      to every connection whose mask has bit 0; in IDLE one frame per ``t`` to the
      connection that triggered; CONF sends nothing. A state change takes
      ``state_change_s``; no frame is sent meanwhile.

    Args:
        source: Frame source.
        xmlrpc_port: TCP port of the XML-RPC server (0: ephemeral).
        pcic_port: TCP port of the 3D head's PCIC server (0: ephemeral) when ``pcic_base_port`` is None.
        pcic_base_port: If given, every port is numbered as on a VPU from this base
            (50010 on a device): ``portN`` = base + N, port6 = base + 6, app0 = base + 1000.
        options: Behaviour (:class:`EmulatorOptions`); keyword arguments override its fields.
        host: Interface to bind (127.0.0.1).
    """

    def __init__(self, source: FrameSource, *, xmlrpc_port: int = 0, pcic_port: int = 0,
                 pcic_base_port: int | None = None, options: EmulatorOptions | None = None,
                 host: str = "127.0.0.1", **overrides: Any) -> None:
        self.options = opts = replace(options or EmulatorOptions(), **overrides)
        self.source = source
        self.port_name = opts.port_name
        self.host = host
        intr = source.intrinsics
        rays = pixel_grid_rays(intr) if intr.has_distortion else None
        self.models = models_from_intrinsics(intr, rays)
        self.encoder = FrameEncoder(self.models, distance_resolution_m=opts.distance_resolution_m,
                                    header_version=opts.header_version, tof_info_version=opts.tof_info_version,
                                    confidence_bits=opts.confidence_bits, mode=opts.mode)
        self._frames = (PerPose(source, self.encoder, opts.capture_timeout_s, noise_scale=opts.noise_scale)
                        if opts.frames == "per_pose" else PerFrame(source, self.encoder, opts.capture_timeout_s))
        self._req_xmlrpc_port = xmlrpc_port
        self._port_numbers = self._numbering(pcic_port, pcic_base_port)
        self._intr = intr
        self.tree: ConfigTree | None = None
        self.ports: dict[str, PcicPort] = {}
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._send_lock = threading.Lock()
        self._faults: list[_Fault] = []
        self._faults_lock = threading.Lock()
        self._frame_count = 0
        self._rpc: _RpcServer | None = None
        self._wake = threading.Event()
        self._acquisition_read: tuple[int, float, str] | None = None  # (tree generation, frame rate Hz, state)
        self._busy_until = 0.0
        self._boot_mono = time.monotonic()
        self.frames_sent = 0
        self.offline = False
        self.rpc_calls: list[str] = []

    def _numbering(self, pcic_port: int, base: int | None) -> dict[str, int]:
        """Requested TCP port per served VPU port (0: ephemeral)."""
        two_d = "port1" if self.port_name == "port0" else "port0"
        if base is None:
            return {self.port_name: pcic_port, two_d: 0, "port6": 0, "app0": 0}
        n = int(self.port_name.removeprefix("port"))
        return {self.port_name: base + n, two_d: base + int(two_d[-1]), "port6": base + 6, "app0": base + 1000}

    # ------------------------------------------------------------------ life cycle
    @property
    def xmlrpc_port(self) -> int:
        """Bound XML-RPC port."""
        assert self._rpc is not None, "emulator not started"
        return int(self._rpc.server_address[1])

    @property
    def pcic_port(self) -> int:
        """Bound PCIC port of the 3D head."""
        return self.ports[self.port_name].port

    @property
    def commands(self) -> list[str]:
        """PCIC commands (first letter) the 3D port received, in order."""
        return self.ports[self.port_name].commands

    def start(self) -> O3REmulator:
        """Bind every port and start serving; returns self.

        Raises:
            OSError: If a port cannot be bound (nothing stays bound).
        """
        try:
            self._bind()
        except OSError:
            self.close()
            raise
        for target, name in ((self._serve_rpc, "o3r-emu-rpc"), (self._run_loop, "o3r-emu-run")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        for p in self.ports.values():
            p.start()
        return self

    def _bind(self) -> None:
        opts = self.options
        for name, number in self._port_numbers.items():
            is_3d = name == self.port_name
            self.ports[name] = PcicPort(name, self.host, number,
                                        trigger_allowed=self._trigger_allowed if is_3d else None,
                                        on_trigger=self._on_trigger if is_3d else None,
                                        on_mask=self._wake.set if is_3d else None)
        rules = tuple(Rule(r.pattern, minimum=0.1, maximum=max(opts.max_frame_rate_hz, opts.frame_rate_hz))
                      if r.pattern.endswith("/framerate") else r for r in RULES)
        self.tree = ConfigTree(default_tree(port=self.port_name, pcic_ports={k: p.port for k, p in self.ports.items()},
                                            width=self._intr.width, height=self._intr.height, state=opts.state,
                                            frame_rate_hz=opts.frame_rate_hz, mode=opts.mode),
                               self._on_change, rules)
        self._update_extrinsic()
        rpc = _RpcServer((self.host, self._req_xmlrpc_port), requestHandler=_RpcHandler, allow_none=True,
                         logRequests=False)
        rpc.register_instance(self)
        self._rpc = rpc

    def close(self) -> None:
        """Stop serving, close every socket and join every thread."""
        self._stop.set()
        self._wake.set()
        if self._rpc is not None:
            if self._threads:
                self._rpc.shutdown()
            self._rpc.server_close()
        for p in self.ports.values():
            p.close()
        for t in self._threads:
            t.join(timeout=5.0)
        self._threads.clear()

    def __enter__(self) -> O3REmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ state helpers
    def _port(self, leaf: str) -> Any:
        assert self.tree is not None
        return self.tree.resolve(f"/ports/{self.port_name}/{leaf}")

    @property
    def state(self) -> str:
        """Current port state (RUN / IDLE / CONF)."""
        return str(self._port("state"))

    def set_state(self, state: str) -> None:
        """Set the port state at once (no state-change time: a test's back door)."""
        assert self.tree is not None
        self.tree.set(f'{{"ports": {{"{self.port_name}": {{"state": "{state}"}}}}}}')

    def _on_change(self, changed: set[str]) -> None:
        if any("extrinsicHeadToUser" in c for c in changed):
            self._update_extrinsic()
        if f"/ports/{self.port_name}/mode" in changed:
            self.encoder.mode = str(self._port("mode"))
            self.encoder._layouts.clear()
        self._wake.set()

    def _update_extrinsic(self) -> None:
        """extrinsicOpticToUser = extrinsicHeadToUser after the factory optic-to-head transform."""
        e = self._port("processing/extrinsicHeadToUser")
        r_hu = Rotation.from_euler("XYZ", [e["rotX"], e["rotY"], e["rotZ"]])
        t_hu = np.array([e["transX"], e["transY"], e["transZ"]])
        o = self.options.optic_to_head
        r = r_hu * Rotation.from_euler("XYZ", o[3:6])
        t = r_hu.apply(np.array(o[:3])) + t_hu
        rx, ry, rz = r.as_euler("XYZ")
        self.encoder.extrinsic_optic_to_user = (float(t[0]), float(t[1]), float(t[2]), float(rx), float(ry),
                                                float(rz))

    def inject_fault(self, kind: str, **params: Any) -> None:
        """Arm a one-shot fault applied to the next frame sent.

        Kinds: ``drop`` (close the connection instead of sending), ``stall`` (send half
        the frame, then nothing for ``seconds``, then close), ``truncate`` (announce the
        full length, send half, continue with the next message), ``corrupt`` (a header
        field: ``field`` = ``chunk_size`` | ``header_version`` | ``star`` |
        ``pcic_length``) and ``async_error`` (an ifm async error message, ticket 0001,
        with ``code`` and ``message``). A fault injected while a frame is being rendered
        (e.g. from the frame source's own fault hook) applies to that frame.
        """
        if kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault {kind!r}; one of {FAULT_KINDS}")
        with self._faults_lock:
            self._faults.append(_Fault(kind, params))
        self._wake.set()

    def go_offline(self) -> None:
        """Fault injection: the head drops off the network for good (PCIC closed and refused; XML-RPC answers)."""
        self.offline = True
        self.ports[self.port_name].go_offline()

    def connection_count(self) -> int:
        """Number of live PCIC connections to the 3D port."""
        return len(self.ports[self.port_name].connections())

    # ------------------------------------------------------------------ XML-RPC
    def _serve_rpc(self) -> None:
        assert self._rpc is not None
        self._rpc.serve_forever(poll_interval=0.05)

    def _dispatch(self, method: str, params: tuple[Any, ...]) -> Any:
        from xmlrpc.client import Fault

        self.rpc_calls.append(method)
        assert self.tree is not None
        try:
            return self._answer(method, params)
        except ConfigTreeError as exc:
            raise Fault(exc.code, str(exc)) from None

    def _answer(self, method: str, params: tuple[Any, ...]) -> Any:
        assert self.tree is not None
        if method == "get":
            pointers = params[0] if params else []
            if not isinstance(pointers, list):
                raise ConfigTreeError(901002, "get expects an array of JSON pointers")
            return self.tree.get(pointers)
        if method == "set":
            if len(params) != 1 or not isinstance(params[0], str):
                raise ConfigTreeError(901002, "set expects one JSON string")
            self._set(params[0])
            return ""
        if method == "getInit":
            return self.tree.get([])
        if method in ("saveInit", "reset", "remove", "lock", "unlock", "reboot"):
            return ""
        if method == "getInitStatus":
            return '{"status":"ok"}'
        if method == "getSchema":
            return self.tree.schema()
        if method == "getSWVersion":
            return {"IFM_Software": FIRMWARE}
        raise ConfigTreeError(901005, f"method {method!r} is not supported")

    def _set(self, text: str) -> None:
        """Apply a ``set``; a state change holds frames and the answer for ``state_change_s``."""
        assert self.tree is not None
        changed = self.tree.set(text)
        if any(p.startswith("/ports/") and p.endswith("/state") for p in changed):
            wait = self.options.state_change_s
            self._busy_until = time.monotonic() + wait  # no frame while the head switches
            self._stop.wait(wait)
            self._busy_until = 0.0
        self._wake.set()

    # ------------------------------------------------------------------ frames
    def _trigger_allowed(self) -> bool:
        return self.state == "IDLE" and time.monotonic() >= self._busy_until

    def _on_trigger(self, conn: Conn) -> None:
        self._send_frame([conn])

    def _acquisition(self) -> tuple[float, str]:
        """The 3D port's frame rate (Hz) and state, read from the tree again only after it changed."""
        assert self.tree is not None
        generation = self.tree.generation  # first: a set landing during the reads is read again next time
        read = self._acquisition_read
        if read is None or read[0] != generation:
            try:
                read = (generation, float(self._port("acquisition/framerate")), self.state)
            except ConfigTreeError:
                read = (generation, 1.0, "CONF")
            self._acquisition_read = read
        return read[1], read[2]

    def _run_loop(self) -> None:
        next_t = time.monotonic()
        port = self.ports[self.port_name]
        targets: list[Conn] = []
        seen = -1
        while not self._stop.is_set():
            rate, state = self._acquisition()
            if seen != port.generation or not all(c.alive for c in targets):
                seen = port.generation  # first: a client arriving during the look is seen next time
                targets = port.connections(mask_bit=1)
            now = time.monotonic()
            if state != "RUN" or not targets or now < self._busy_until:
                self._wake.wait(0.05)
                self._wake.clear()
                next_t = time.monotonic()
                continue
            if now < next_t:
                self._stop.wait(min(next_t - now, 0.05))
                continue
            next_t = max(next_t + 1.0 / max(rate, 0.1), now)
            self._send_frame(targets)

    def _timestamp_ns(self, source_s: float) -> int:
        """The frame's device time: since boot (``clock = "boot"``) or the source's Unix time."""
        if self.options.clock == "boot":
            return round((BOOT_UPTIME_S + time.monotonic() - self._boot_mono) * 1e9)
        if self.options.frames == "per_pose":
            return round(time.time() * 1e9)
        return max(0, round(source_s * 1e9))

    def _send_frame(self, targets: list[Conn]) -> None:
        with self._send_lock:  # one reused encode buffer per chunk selection
            # first: a fault injected while rendering applies here
            counts, source_s = self._frames.next(targets[0].chunks if targets else DEFAULT_CHUNKS)
            self._frame_count += 1
            fault = None
            if self._faults:  # read without the lock: an empty list stays empty until inject_fault
                with self._faults_lock:
                    fault = self._faults.pop(0) if self._faults else None
            if fault is not None and fault.kind == "async_error":
                code = int(fault.params.get("code", 104000005))
                text = str(fault.params.get("message", "emulated async error"))
                for c in targets:
                    c.send(message("0001", b"%09d:%s" % (code, text.encode())))
                fault = None
            ts_ns = self._timestamp_ns(source_s)
            for c in targets:
                data = self.encoder.encode(counts, self._frame_count, ts_ns, c.chunks)
                if fault is not None:
                    _faulty_send(c, bytes(data), fault, self._stop)
                elif c.send(data):
                    self.frames_sent += 1


def _faulty_send(conn: Conn, data: bytes, fault: _Fault, stop: threading.Event) -> None:
    """Send a frame message spoiled as ``fault`` says."""
    kind = fault.kind
    if kind == "drop":
        conn.kill()
    elif kind == "stall":
        conn.send(data[: len(data) // 2])
        stop.wait(float(fault.params.get("seconds", 1.0)))
        conn.kill()
    elif kind == "truncate":
        conn.send(data[: len(data) // 2])
    elif kind == "corrupt":
        buf = bytearray(data)
        which = fault.params.get("field", "chunk_size")
        first = 16 + 8  # first chunk header in the stream: PCIC header, ticket, "star"
        if which == "chunk_size":
            struct.pack_into("<I", buf, first + 4, 0x7FFFFFF0)
        elif which == "header_version":
            struct.pack_into("<I", buf, first + 12, 77)
        elif which == "star":
            buf[20:24] = b"STAR"
        elif which == "pcic_length":
            buf[5:14] = b"9999999x9"
        else:
            raise ValueError(f"unknown corrupt field {which!r}")
        conn.send(bytes(buf))


def wait_until(predicate: Callable[[], bool], timeout_s: float, poll_s: float = 0.01) -> bool:
    """Poll ``predicate`` until true or ``timeout_s`` elapses; returns its last value."""
    deadline = time.monotonic() + timeout_s
    while True:
        if predicate():
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(poll_s)


__all__ = ["FACTORY_OPTIC_TO_HEAD", "FAULT_KINDS", "RPC_PATH", "EmulatorOptions", "FrameSource", "O3REmulator",
           "wait_until"]
