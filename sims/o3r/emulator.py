"""A wire-level emulator of an ifm O3R VPU: XML-RPC + PCIC over TCP, on 127.0.0.1, with one or more 3D heads.

Made like the device by default (ADR 0024): PCIC ports numbered as a VPU numbers them
(``portN`` on base + N, the IMU on port6, an application instance on base + 1000) when
given a base port, chunk header versions as in a real capture, TOF_INFO version 4, a
realistic distance resolution, a non-zero factory optic-to-head extrinsic, state
changes that take time, a CONF-only mode, a schema-like read-only table, a clock that
counts from boot unless asked for Unix time, and XML-RPC faults labelled as its own.
Frames come from any :class:`~.frames.FrameSource` (e.g. ``SimCamera``); further 3D heads
(``heads``, VPU port -> source) each serve their own source on their own PCIC port::

    emu = O3REmulator(SimCamera().connect(), state="IDLE").start()  # then emu.xmlrpc_port, emu.pcic_port
    two = O3REmulator(cam_a, heads={"port3": cam_b}).start()        # 3D heads on port2 and port3
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import replace
from socketserver import ThreadingMixIn
from typing import Any
from xmlrpc.server import SimpleXMLRPCRequestHandler, SimpleXMLRPCServer

from .config_tree import FIRMWARE, RULES, ConfigTree, ConfigTreeError, Rule, default_tree
from .encoder import FrameEncoder
from .frames import FrameSource
from .head import FAULT_KINDS, Head3D
from .options import BOOT_UPTIME_S, FACTORY_OPTIC_TO_HEAD, HEAD_PORTS, EmulatorOptions, two_d_partners
from .pcic_server import PcicPort
from .wire import O3RModels

RPC_PATH = "/api/rpc/v1/com.ifm.efector/"
_PORT_NAME = re.compile(r"port[0-5]")


class _RpcHandler(SimpleXMLRPCRequestHandler):
    rpc_paths = (RPC_PATH, RPC_PATH.rstrip("/"))

    def log_message(self, format: str, *args: Any) -> None:
        return None


class _RpcServer(ThreadingMixIn, SimpleXMLRPCServer):
    daemon_threads = True
    block_on_close = True
    allow_reuse_address = True


class O3REmulator:
    """Emulated O3R VPU.

    Serves, on ``host`` only:

    * XML-RPC at ``/api/rpc/v1/com.ifm.efector/``: ``get``, ``set``, ``getInit``,
      ``saveInit``, ``getInitStatus``, ``getSchema``, ``reset``, ``getSWVersion`` (what
      ifm3dpy 1.6 calls); faults carry the emulator's own codes, labelled as such;
    * a PCIC server per VPU port (each 3D head, their 2D heads, port6 IMU, application
      ``app0``); only the 3D ports send frames, each its own source's. A 3D port honours
      ``p``, ``c`` (chunks 100/101/300/420; other O3R blob ids accepted and not sent,
      unknown ones refused) and ``t`` (only in IDLE). In RUN frames are sent at
      ``/ports/<port>/acquisition/framerate`` to every connection whose mask has bit 0; in
      IDLE one frame per ``t`` to the connection that triggered; CONF sends nothing. A
      state change takes ``state_change_s``; that head sends no frame meanwhile.

    The first head (``source`` on ``options.port_name``) is the one the single-head
    attributes (:attr:`pcic_port`, :attr:`state`, :meth:`inject_fault`, ...) speak of;
    :attr:`heads` holds every head (:class:`~.head.Head3D`) by port.

    Args:
        source: Frame source of the first 3D head.
        xmlrpc_port: TCP port of the XML-RPC server (0: ephemeral).
        pcic_port: TCP port of the first head's PCIC server (0: ephemeral) when ``pcic_base_port``
            is None (every other port is then ephemeral).
        pcic_base_port: If given, every port is numbered as on a VPU from this base
            (50010 on a device): ``portN`` = base + N, port6 = base + 6, app0 = base + 1000.
        options: Behaviour (:class:`EmulatorOptions`); keyword arguments override its fields.
        host: Interface to bind (127.0.0.1).
        heads: Further 3D heads: VPU port (``port0``..``port5``, not the first head's) -> frame source.

    Raises:
        ValueError: If a head's port is not ``port0``..``port5`` or is given twice.
    """

    def __init__(self, source: FrameSource, *, xmlrpc_port: int = 0, pcic_port: int = 0,
                 pcic_base_port: int | None = None, options: EmulatorOptions | None = None,
                 host: str = "127.0.0.1", heads: Mapping[str, FrameSource] | None = None, **overrides: Any) -> None:
        self.options = opts = replace(options or EmulatorOptions(), **overrides)
        self.port_name = opts.port_name
        sources = {opts.port_name: source}
        for name, src in (heads or {}).items():
            if name in sources:
                raise ValueError(f"{name} is given twice as a 3D head")
            sources[name] = src
        bad = [n for n in sources if not _PORT_NAME.fullmatch(n)]
        if bad:
            raise ValueError(f"3D heads go on {', '.join(HEAD_PORTS)}, got {', '.join(map(repr, bad))}")
        self.host = host
        self._stop = threading.Event()
        self._render_lock = threading.Lock()  # the heads' sources may share one simulated world
        self._boot_mono = time.monotonic()
        #: Every 3D head by VPU port, the first head first.
        self.heads: dict[str, Head3D] = {
            name: Head3D(name, src, opts, stop=self._stop, clock_ns=self._timestamp_ns,
                         render_lock=self._render_lock, seed=i)
            for i, (name, src) in enumerate(sources.items())}
        self._req_xmlrpc_port = xmlrpc_port
        self._port_numbers = self._numbering(pcic_port, pcic_base_port)
        self.tree: ConfigTree | None = None
        self.ports: dict[str, PcicPort] = {}
        self._threads: list[threading.Thread] = []
        self._rpc: _RpcServer | None = None
        self.rpc_calls: list[str] = []

    def _numbering(self, pcic_port: int, base: int | None) -> dict[str, int]:
        """Requested TCP port per served VPU port (0: ephemeral)."""
        names = [*self.heads, *two_d_partners(list(self.heads)), "port6"]
        if base is None:
            return {**dict.fromkeys(names, 0), self.port_name: pcic_port, "app0": 0}
        return {**{n: base + int(n.removeprefix("port")) for n in names}, "app0": base + 1000}

    # ------------------------------------------------------------------ the first head
    @property
    def head(self) -> Head3D:
        """The first 3D head (on ``options.port_name``)."""
        return self.heads[self.port_name]

    @property
    def source(self) -> FrameSource:
        """The first head's frame source."""
        return self.head.source

    @property
    def encoder(self) -> FrameEncoder:
        """The first head's frame encoder."""
        return self.head.encoder

    @property
    def models(self) -> O3RModels:
        """The first head's O3R intrinsic models."""
        return self.head.models

    @property
    def frames_sent(self) -> int:
        """Frame messages the first head sent whole."""
        return self.head.frames_sent

    @property
    def offline(self) -> bool:
        """True after :meth:`go_offline`."""
        return self.head.offline

    # ------------------------------------------------------------------ life cycle
    @property
    def xmlrpc_port(self) -> int:
        """Bound XML-RPC port."""
        assert self._rpc is not None, "emulator not started"
        return int(self._rpc.server_address[1])

    @property
    def pcic_port(self) -> int:
        """Bound PCIC port of the first 3D head."""
        return self.ports[self.port_name].port

    def pcic_port_of(self, port: str) -> int:
        """Bound PCIC port of VPU port ``port`` (``port3``, ``port6``, ``app0``)."""
        return self.ports[port].port

    @property
    def commands(self) -> list[str]:
        """PCIC commands (first letter) the first head's port received, in order."""
        return self.head.commands

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
        t = threading.Thread(target=self._serve_rpc, name="o3r-emu-rpc", daemon=True)
        t.start()
        self._threads.append(t)
        for h in self.heads.values():
            h.start()
        for p in self.ports.values():
            p.start()
        return self

    def _bind(self) -> None:
        opts = self.options
        for name, number in self._port_numbers.items():
            head = self.heads.get(name)
            self.ports[name] = head.bind(self.host, number) if head is not None else PcicPort(name, self.host, number)
        rules = tuple(Rule(r.pattern, minimum=0.1, maximum=max(opts.max_frame_rate_hz, opts.frame_rate_hz))
                      if r.pattern.endswith("/framerate") else r for r in RULES)
        sizes = {n: (h.intrinsics.width, h.intrinsics.height) for n, h in self.heads.items()}
        self.tree = ConfigTree(default_tree(heads=sizes, pcic_ports={k: p.port for k, p in self.ports.items()},
                                            state=opts.state, frame_rate_hz=opts.frame_rate_hz, mode=opts.mode),
                               self._on_change, rules)
        for h in self.heads.values():
            h.attach(self.tree)
        rpc = _RpcServer((self.host, self._req_xmlrpc_port), requestHandler=_RpcHandler, allow_none=True,
                         logRequests=False)
        rpc.register_instance(self)
        self._rpc = rpc

    def close(self) -> None:
        """Stop serving, close every socket and join every thread."""
        self._stop.set()
        if self._rpc is not None:
            if self._threads:
                self._rpc.shutdown()
            self._rpc.server_close()
        for p in self.ports.values():
            p.close()
        for h in self.heads.values():
            h.close()
        for t in self._threads:
            t.join(timeout=5.0)
        self._threads.clear()

    def __enter__(self) -> O3REmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ state helpers
    @property
    def state(self) -> str:
        """Current state of the first head's port (RUN / IDLE / CONF)."""
        return self.head.state

    def set_state(self, state: str, port: str | None = None) -> None:
        """Set a head's port state at once (no state-change time: a test's back door); default: the first head."""
        assert self.tree is not None
        self.tree.set(f'{{"ports": {{"{port or self.port_name}": {{"state": "{state}"}}}}}}')

    def _on_change(self, changed: set[str]) -> None:
        for h in self.heads.values():
            h.on_change(changed)

    def inject_fault(self, kind: str, *, port: str | None = None, **params: Any) -> None:
        """Arm a one-shot fault applied to the next frame a head sends (default: the first head).

        Kinds: ``drop`` (close the connection instead of sending), ``stall`` (send half
        the frame, then nothing for ``seconds``, then close), ``truncate`` (announce the
        full length, send half, continue with the next message), ``corrupt`` (a header
        field: ``field`` = ``chunk_size`` | ``header_version`` | ``star`` |
        ``pcic_length``) and ``async_error`` (an ifm async error message, ticket 0001,
        with ``code`` and ``message``). A fault injected while a frame is being rendered
        (e.g. from the frame source's own fault hook) applies to that frame.
        """
        self.heads[port or self.port_name].inject_fault(kind, **params)

    def go_offline(self) -> None:
        """Fault injection: the first head drops off the network for good (PCIC closed and refused; XML-RPC answers)."""
        self.head.go_offline()

    def connection_count(self) -> int:
        """Number of live PCIC connections to the first head's port."""
        return self.head.connection_count()

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
        """Apply a ``set``; a state change holds the switching heads' frames and the answer for ``state_change_s``."""
        assert self.tree is not None
        changed = self.tree.set(text)
        if any(p.startswith("/ports/") and p.endswith("/state") for p in changed):
            wait = self.options.state_change_s
            switching = [h for h in self.heads.values() if f"/ports/{h.name}/state" in changed]
            for h in switching:
                h.busy_until = time.monotonic() + wait  # no frame while the head switches
            self._stop.wait(wait)
            for h in switching:
                h.busy_until = 0.0
        for h in self.heads.values():
            h.wake.set()

    def _timestamp_ns(self, source_s: float) -> int:
        """A frame's device time: since boot (``clock = "boot"``) or the source's Unix time."""
        if self.options.clock == "boot":
            return round((BOOT_UPTIME_S + time.monotonic() - self._boot_mono) * 1e9)
        if self.options.frames == "per_pose":
            return round(time.time() * 1e9)
        return max(0, round(source_s * 1e9))


def wait_until(predicate: Callable[[], bool], timeout_s: float, poll_s: float = 0.01) -> bool:
    """Poll ``predicate`` until true or ``timeout_s`` elapses; returns its last value."""
    deadline = time.monotonic() + timeout_s
    while True:
        if predicate():
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(poll_s)


__all__ = ["BOOT_UPTIME_S", "FACTORY_OPTIC_TO_HEAD", "FAULT_KINDS", "RPC_PATH", "EmulatorOptions", "FrameSource",
           "Head3D", "O3REmulator", "wait_until"]
