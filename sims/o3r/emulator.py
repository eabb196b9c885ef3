"""A wire-level emulator of an ifm O3R VPU with one 3D head: XML-RPC + PCIC over TCP, on 127.0.0.1.

Frames come from any :class:`Camera3D` (e.g. ``SimCamera``)::

    emu = O3REmulator(SimCamera().connect(), state="IDLE").start()  # then emu.xmlrpc_port, emu.pcic_port
"""

from __future__ import annotations

import contextlib
import socket
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from socketserver import ThreadingMixIn
from typing import Any, Protocol
from xmlrpc.server import SimpleXMLRPCRequestHandler, SimpleXMLRPCServer

import numpy as np
from scipy.spatial.transform import Rotation

from cellcal.devices.geometry.camera_model import pixel_grid_rays
from cellcal.devices.types import Frame, Intrinsics

from .config_tree import FIRMWARE, ConfigTree, ConfigTreeError, default_tree
from .wire import DEFAULT_CHUNKS, FrameEncoder, message, models_from_intrinsics, schema_chunks

RPC_PATH = "/api/rpc/v1/com.ifm.efector/"
FAULT_KINDS = ("drop", "stall", "truncate", "corrupt", "async_error")


class FrameSource(Protocol):
    """What the emulator renders from (any :class:`Camera3D` qualifies)."""

    @property
    def intrinsics(self) -> Intrinsics: ...

    def capture(self, timeout: float | None = None) -> Frame: ...


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


class _Conn:
    """One PCIC client connection."""

    def __init__(self, sock: socket.socket, peer: Any) -> None:
        self.sock = sock
        self.peer = peer
        self.mask = 0
        self.chunks: tuple[int, ...] = DEFAULT_CHUNKS
        self.send_lock = threading.Lock()
        self.alive = True
        self.thread: threading.Thread | None = None

    def send(self, data: bytes) -> bool:
        try:
            with self.send_lock:
                self.sock.sendall(data)
            return True
        except OSError:
            self.kill()
            return False

    def kill(self) -> None:
        self.alive = False
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)


class O3REmulator:
    """Emulated O3R VPU.

    Serves, on 127.0.0.1 only:

    * XML-RPC at ``/api/rpc/v1/com.ifm.efector/``: ``get``, ``set``, ``getInit``,
      ``saveInit``, ``getInitStatus``, ``getSchema``, ``reset``, ``getSWVersion`` (what
      ifm3dpy 1.6 calls);
    * a PCIC server for the 3D port honouring ``p`` (output mask), ``c`` (schema: which
      of chunks 100/101/300/420 to send) and ``t`` (software trigger, only in state
      IDLE). In state RUN frames are rendered at ``/ports/<port>/acquisition/framerate``
      and sent to every connection whose mask has bit 0; in IDLE one frame is rendered
      per ``t`` and sent to the connection that triggered; CONF sends nothing.

    Exactly one ``source.capture`` is made per frame sent, so a simulated camera's
    random stream and clock advance exactly as if it were captured directly.

    Args:
        source: Frame source (see :class:`FrameSource`).
        xmlrpc_port: TCP port of the XML-RPC server (0: ephemeral).
        pcic_port: TCP port of the 3D head's PCIC server (0: ephemeral).
        port_name: VPU port of the 3D head, e.g. ``"port2"``.
        state: Initial port state: RUN, IDLE or CONF.
        frame_rate_hz: Frame rate in RUN.
        distance_resolution_m: Metres per distance count on the wire.
        optic_to_head: Optical frame in the head frame (transX/Y/Z m, rotX/Y/Z rad).
        header_version: Chunk header version 1..3.
        capture_timeout_s: Timeout passed to ``source.capture``.
        host: Interface to bind (127.0.0.1).
    """

    def __init__(self, source: FrameSource, *, xmlrpc_port: int = 0, pcic_port: int = 0,
                 port_name: str = "port2", state: str = "RUN", frame_rate_hz: float = 20.0,
                 distance_resolution_m: float = 0.000125,
                 optic_to_head: tuple[float, float, float, float, float, float] = (0, 0, 0, 0, 0, 0),
                 header_version: int = 2, capture_timeout_s: float = 5.0, host: str = "127.0.0.1") -> None:
        self.source = source
        self.port_name = port_name
        self.host = host
        self.capture_timeout_s = capture_timeout_s
        self._optic_to_head = tuple(float(v) for v in optic_to_head)
        intr = source.intrinsics
        rays = pixel_grid_rays(intr) if intr.has_distortion else None
        self.models = models_from_intrinsics(intr, rays)
        self.encoder = FrameEncoder(self.models, distance_resolution_m=distance_resolution_m,
                                    header_version=header_version)
        self._req_xmlrpc_port = xmlrpc_port
        self._req_pcic_port = pcic_port
        self._intr = intr
        self._state0 = state
        self._rate0 = frame_rate_hz
        self.tree: ConfigTree | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._conns: list[_Conn] = []
        self._conns_lock = threading.Lock()
        self._render_lock = threading.Lock()
        self._faults: list[_Fault] = []
        self._faults_lock = threading.Lock()
        self._frame_count = 0
        self._rpc: _RpcServer | None = None
        self._listener: socket.socket | None = None
        self._wake = threading.Event()
        self.frames_sent = 0
        self.offline = False
        self.commands: list[str] = []
        self.rpc_calls: list[str] = []

    # ------------------------------------------------------------------ life cycle
    @property
    def xmlrpc_port(self) -> int:
        """Bound XML-RPC port."""
        assert self._rpc is not None, "emulator not started"
        return int(self._rpc.server_address[1])

    @property
    def pcic_port(self) -> int:
        """Bound PCIC port of the 3D head."""
        assert self._listener is not None, "emulator not started"
        return int(self._listener.getsockname()[1])

    def start(self) -> O3REmulator:
        """Bind both ports and start serving; returns self."""
        lst = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        lst.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        lst.bind((self.host, self._req_pcic_port))
        lst.listen(8)
        lst.settimeout(0.1)
        self._listener = lst
        self.tree = ConfigTree(default_tree(port=self.port_name, pcic_port=self.pcic_port, width=self._intr.width,
                                            height=self._intr.height, state=self._state0,
                                            frame_rate_hz=self._rate0), self._on_change)
        self._update_extrinsic()
        try:
            rpc = _RpcServer((self.host, self._req_xmlrpc_port), requestHandler=_RpcHandler, allow_none=True,
                             logRequests=False)
        except OSError:
            lst.close()
            raise
        rpc.register_instance(self)
        self._rpc = rpc
        for target, name in ((self._serve_rpc, "o3r-emu-rpc"), (self._accept_loop, "o3r-emu-accept"),
                             (self._run_loop, "o3r-emu-run")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def close(self) -> None:
        """Stop serving, close every socket and join every thread."""
        self._stop.set()
        self._wake.set()
        if self._rpc is not None:
            self._rpc.shutdown()
            self._rpc.server_close()
        with self._conns_lock:
            conns = list(self._conns)
        for c in conns:
            c.kill()
        for t in self._threads:
            t.join(timeout=5.0)
        for c in conns:
            if c.thread is not None:
                c.thread.join(timeout=5.0)
            with contextlib.suppress(OSError):
                c.sock.close()
        if self._listener is not None:
            self._listener.close()
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
        """Set the port state as a client would over XML-RPC."""
        assert self.tree is not None
        self.tree.set(f'{{"ports": {{"{self.port_name}": {{"state": "{state}"}}}}}}')

    def _on_change(self, changed: set[str]) -> None:
        if any("extrinsicHeadToUser" in c for c in changed):
            self._update_extrinsic()
        self._wake.set()

    def _update_extrinsic(self) -> None:
        e = self._port("processing/extrinsicHeadToUser")
        r_hu = Rotation.from_euler("XYZ", [e["rotX"], e["rotY"], e["rotZ"]])
        t_hu = np.array([e["transX"], e["transY"], e["transZ"]])
        o = self._optic_to_head
        r_oh = Rotation.from_euler("XYZ", o[3:6])
        r = r_hu * r_oh
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
        """Fault injection: the head drops off the network for good.

        Every PCIC connection is closed and new ones are refused (the listening
        socket is shut down); XML-RPC keeps answering. A client then sees a lost
        link it cannot re-establish.
        """
        self.offline = True
        if self._listener is not None:
            with contextlib.suppress(OSError):
                self._listener.shutdown(socket.SHUT_RDWR)
        with self._conns_lock:
            conns = list(self._conns)
        for c in conns:
            c.kill()

    def connection_count(self) -> int:
        """Number of live PCIC connections."""
        with self._conns_lock:
            return sum(1 for c in self._conns if c.alive)

    # ------------------------------------------------------------------ XML-RPC
    def _serve_rpc(self) -> None:
        assert self._rpc is not None
        self._rpc.serve_forever(poll_interval=0.05)

    def _dispatch(self, method: str, params: tuple[Any, ...]) -> Any:
        from xmlrpc.client import Fault

        self.rpc_calls.append(method)
        assert self.tree is not None
        try:
            if method == "get":
                pointers = params[0] if params else []
                if not isinstance(pointers, list):
                    raise ConfigTreeError(101002, "get expects an array of JSON pointers")
                return self.tree.get(pointers)
            if method == "set":
                if len(params) != 1 or not isinstance(params[0], str):
                    raise ConfigTreeError(101002, "set expects one JSON string")
                self.tree.set(params[0])
                return ""
            if method in ("getInit",):
                return self.tree.get([])
            if method in ("saveInit", "reset", "remove", "lock", "unlock", "reboot"):
                return ""
            if method == "getInitStatus":
                return '{"status":"ok"}'
            if method == "getSchema":
                return '{"$schema":"http://json-schema.org/draft-07/schema#","type":"object"}'
            if method == "getSWVersion":
                return {"IFM_Software": FIRMWARE}
        except ConfigTreeError as exc:
            raise Fault(exc.code, str(exc)) from None
        raise Fault(-32601, f"method {method!r} not supported by the emulator")

    # ------------------------------------------------------------------ PCIC
    def _accept_loop(self) -> None:
        assert self._listener is not None
        while not self._stop.is_set():
            try:
                sock, peer = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                break
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn = _Conn(sock, peer)
            conn.thread = threading.Thread(target=self._conn_loop, args=(conn,), name="o3r-emu-conn", daemon=True)
            with self._conns_lock:
                self._conns = [c for c in self._conns if c.alive or (c.thread and c.thread.is_alive())]
                self._conns.append(conn)
            conn.thread.start()

    def _conn_loop(self, conn: _Conn) -> None:
        conn.sock.settimeout(0.1)
        buf = bytearray()
        try:
            while conn.alive and not self._stop.is_set():
                try:
                    data = conn.sock.recv(65536)
                except TimeoutError:
                    continue
                except OSError:
                    break
                if not data:
                    break
                buf += data
                while len(buf) >= 16:
                    head = bytes(buf[:16])
                    if not (head[:4].isdigit() and head[4:5] == b"L" and head[5:14].isdigit()):
                        conn.kill()  # unframeable input: a real device drops the client too
                        return
                    length = int(head[5:14])
                    if len(buf) < 16 + length:
                        break
                    payload = bytes(buf[16:16 + length])
                    del buf[:16 + length]
                    self._command(conn, head[:4].decode(), payload[4:-2])
        finally:
            conn.alive = False
            with contextlib.suppress(OSError):
                conn.sock.close()

    def _reply(self, conn: _Conn, ticket: str, code: bytes) -> None:
        conn.send(message(ticket, code))

    def _command(self, conn: _Conn, ticket: str, content: bytes) -> None:
        cmd = content[:1]
        self.commands.append(content[:1].decode("ascii", "replace"))
        if cmd == b"p":
            try:
                conn.mask = int(content[1:].decode("ascii"), 16)
            except ValueError:
                self._reply(conn, ticket, b"?")
                return
            self._reply(conn, ticket, b"*")
            self._wake.set()
        elif cmd == b"c":
            try:
                n = int(content[1:10])
                text = content[10:].decode("utf-8")
                if n != len(content) - 10:
                    raise ValueError("schema length mismatch")
                conn.chunks = schema_chunks(text)
            except (ValueError, UnicodeDecodeError):
                self._reply(conn, ticket, b"?")
                return
            self._reply(conn, ticket, b"*")
        elif cmd == b"t":
            if self.state != "IDLE":
                self._reply(conn, ticket, b"!")
                return
            self._reply(conn, ticket, b"*")
            self._send_frame([conn])
        else:
            self._reply(conn, ticket, b"?")

    def _run_loop(self) -> None:
        next_t = time.monotonic()
        while not self._stop.is_set():
            try:
                rate = float(self._port("acquisition/framerate"))
                state = self.state
            except ConfigTreeError:
                rate, state = 1.0, "CONF"
            with self._conns_lock:
                targets = [c for c in self._conns if c.alive and c.mask & 1]
            if state != "RUN" or not targets:
                self._wake.wait(0.05)
                self._wake.clear()
                next_t = time.monotonic()
                continue
            now = time.monotonic()
            if now < next_t:
                self._stop.wait(min(next_t - now, 0.05))
                continue
            next_t = max(next_t + 1.0 / max(rate, 0.1), now)
            self._send_frame(targets)

    def _render(self) -> tuple[int, Frame]:
        with self._render_lock:
            frame = self.source.capture(self.capture_timeout_s)
            self._frame_count += 1
            return self._frame_count, frame

    def _send_frame(self, targets: list[_Conn]) -> None:
        count, frame = self._render()  # first: a fault injected while rendering applies to this frame
        with self._faults_lock:
            fault = self._faults.pop(0) if self._faults else None
        if fault is not None and fault.kind == "async_error":
            code = int(fault.params.get("code", 104000005))
            text = str(fault.params.get("message", "emulated async error"))
            for c in targets:
                c.send(message("0001", b"%09d:%s" % (code, text.encode())))
            fault = None
        payloads: dict[tuple[int, ...], bytes] = {}
        for c in targets:
            if c.chunks not in payloads:
                payloads[c.chunks] = message("0000", self.encoder.payload(frame, count, c.chunks))
            data = payloads[c.chunks]
            if fault is not None:
                self._faulty_send(c, data, fault)
                continue
            if c.send(data):
                self.frames_sent += 1

    def _faulty_send(self, conn: _Conn, data: bytes, fault: _Fault) -> None:
        kind = fault.kind
        if kind == "drop":
            conn.kill()
        elif kind == "stall":
            conn.send(data[: len(data) // 2])
            self._stop.wait(float(fault.params.get("seconds", 1.0)))
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


__all__ = ["FAULT_KINDS", "RPC_PATH", "FrameSource", "O3REmulator", "wait_until"]
