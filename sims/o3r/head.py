"""One 3D head of the emulated O3R VPU (:class:`Head3D`): its PCIC server, encoder, frame loop and faults.

The VPU (:class:`~.emulator.O3REmulator`) owns the configuration tree and the XML-RPC
server; each head reads its own ``/ports/<name>/...`` values from that tree (state, frame
rate, mode, extrinsic) and serves frames of its own source on its own PCIC port.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from cellcal.devices.geometry.camera_model import pixel_grid_rays

from .config_tree import ConfigTree, ConfigTreeError
from .encoder import FrameEncoder
from .frames import FrameSource, PerFrame, PerPose
from .options import EmulatorOptions
from .pcic_server import Conn, PcicPort
from .wire import DEFAULT_CHUNKS, message, models_from_intrinsics

FAULT_KINDS = ("drop", "stall", "truncate", "corrupt", "async_error")


@dataclass
class Fault:
    """A one-shot fault armed for the next frame (see :meth:`Head3D.inject_fault`)."""

    kind: str
    params: dict[str, Any] = field(default_factory=dict)


class Head3D:
    """One emulated 3D head.

    Args:
        name: Its VPU port, ``portN``.
        source: Where its frames come from.
        options: The VPU's behaviour (encoding, frames, timeouts).
        stop: Set when the VPU closes.
        clock_ns: The VPU's device time (ns) of a frame whose source time is the argument (s).
        render_lock: Held while the source renders (heads whose sources share one simulated world).
        seed: Seed of the ``per_pose`` noise (one per head, so two heads' noise differs).

    Attributes:
        models: The O3R intrinsic models of the source's intrinsics.
        encoder: The frame encoder.
        pcic: Its PCIC server (None until :meth:`bind`).
        tree: The VPU's configuration tree (None until :meth:`attach`).
        frames_sent: Frame messages sent whole.
        busy_until: ``time.monotonic()`` until which the head is switching state (no frame, no trigger).
        offline: True after :meth:`go_offline`.
    """

    def __init__(self, name: str, source: FrameSource, options: EmulatorOptions, *, stop: threading.Event,
                 clock_ns: Callable[[float], int], render_lock: threading.Lock, seed: int = 0) -> None:
        self.name = name
        self.source = source
        self.options = opts = options
        intr = source.intrinsics
        rays = pixel_grid_rays(intr) if intr.has_distortion else None
        self.intrinsics = intr
        self.models = models_from_intrinsics(intr, rays)
        self.encoder = FrameEncoder(self.models, distance_resolution_m=opts.distance_resolution_m,
                                    header_version=opts.header_version, tof_info_version=opts.tof_info_version,
                                    confidence_bits=opts.confidence_bits, mode=opts.mode)
        self._frames = (PerPose(source, self.encoder, opts.capture_timeout_s, noise_scale=opts.noise_scale, seed=seed)
                        if opts.frames == "per_pose" else PerFrame(source, self.encoder, opts.capture_timeout_s))
        self._stop = stop
        self._clock_ns = clock_ns
        self._render_lock = render_lock
        self.pcic: PcicPort | None = None
        self.tree: ConfigTree | None = None
        self.wake = threading.Event()
        self._send_lock = threading.Lock()
        self._faults: list[Fault] = []
        self._faults_lock = threading.Lock()
        self._frame_count = 0
        self._acquisition_read: tuple[int, float, str] | None = None  # (tree generation, frame rate Hz, state)
        self._thread: threading.Thread | None = None
        self.frames_sent = 0
        self.busy_until = 0.0
        self.offline = False

    # ------------------------------------------------------------------ life cycle
    def bind(self, host: str, number: int) -> PcicPort:
        """Bind its PCIC server on ``host:number`` (0: ephemeral).

        Raises:
            OSError: If the port cannot be bound.
        """
        self.pcic = PcicPort(self.name, host, number, trigger_allowed=self._trigger_allowed,
                             on_trigger=self._on_trigger, on_mask=self.wake.set)
        return self.pcic

    def attach(self, tree: ConfigTree) -> None:
        """Read its settings from the VPU's tree from now on."""
        self.tree = tree
        self.update_extrinsic()

    def start(self) -> None:
        """Start the frame loop (the PCIC server is started by the VPU with every other port)."""
        self._thread = threading.Thread(target=self._run_loop, name=f"o3r-emu-run-{self.name}", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Wake and join the frame loop (the VPU closes the PCIC server and sets ``stop``)."""
        self.wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None

    # ------------------------------------------------------------------ its settings
    def setting(self, leaf: str) -> Any:
        """``/ports/<name>/<leaf>`` of the tree."""
        assert self.tree is not None
        return self.tree.resolve(f"/ports/{self.name}/{leaf}")

    @property
    def state(self) -> str:
        """Current port state (RUN / IDLE / CONF)."""
        return str(self.setting("state"))

    @property
    def commands(self) -> list[str]:
        """PCIC commands (first letter) its port received, in order."""
        assert self.pcic is not None
        return self.pcic.commands

    def on_change(self, changed: set[str]) -> None:
        """Follow a ``set`` of the tree: its extrinsic and mode; wake the frame loop."""
        own = f"/ports/{self.name}/"
        if any(c.startswith(own + "processing/extrinsicHeadToUser") for c in changed):
            self.update_extrinsic()
        if own + "mode" in changed:
            self.encoder.mode = str(self.setting("mode"))
            self.encoder._layouts.clear()
        self.wake.set()

    def update_extrinsic(self) -> None:
        """extrinsicOpticToUser = extrinsicHeadToUser after the factory optic-to-head transform."""
        e = self.setting("processing/extrinsicHeadToUser")
        r_hu = Rotation.from_euler("XYZ", [e["rotX"], e["rotY"], e["rotZ"]])
        t_hu = np.array([e["transX"], e["transY"], e["transZ"]])
        o = self.options.optic_to_head
        r = r_hu * Rotation.from_euler("XYZ", o[3:6])
        t = r_hu.apply(np.array(o[:3])) + t_hu  # metres, user frame
        rx, ry, rz = r.as_euler("XYZ")
        self.encoder.extrinsic_optic_to_user = (float(t[0]), float(t[1]), float(t[2]), float(rx), float(ry),
                                                float(rz))

    # ------------------------------------------------------------------ faults
    def inject_fault(self, kind: str, **params: Any) -> None:
        """Arm a one-shot fault applied to its next frame (kinds: :meth:`O3REmulator.inject_fault`)."""
        if kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault {kind!r}; one of {FAULT_KINDS}")
        with self._faults_lock:
            self._faults.append(Fault(kind, params))
        self.wake.set()

    def go_offline(self) -> None:
        """The head drops off the network for good (its PCIC port closed and refused)."""
        self.offline = True
        assert self.pcic is not None
        self.pcic.go_offline()

    def connection_count(self) -> int:
        """Number of live PCIC connections to its port."""
        assert self.pcic is not None
        return len(self.pcic.connections())

    # ------------------------------------------------------------------ frames
    def _trigger_allowed(self) -> bool:
        return self.state == "IDLE" and time.monotonic() >= self.busy_until

    def _on_trigger(self, conn: Conn) -> None:
        self._send_frame([conn])

    def _acquisition(self) -> tuple[float, str]:
        """Its frame rate (Hz) and state, read from the tree again only after it changed."""
        assert self.tree is not None
        generation = self.tree.generation  # first: a set landing during the reads is read again next time
        read = self._acquisition_read
        if read is None or read[0] != generation:
            try:
                read = (generation, float(self.setting("acquisition/framerate")), self.state)
            except ConfigTreeError:
                read = (generation, 1.0, "CONF")
            self._acquisition_read = read
        return read[1], read[2]

    def _run_loop(self) -> None:
        next_t = time.monotonic()
        port = self.pcic
        assert port is not None
        targets: list[Conn] = []
        seen = -1
        while not self._stop.is_set():
            rate, state = self._acquisition()
            if seen != port.generation or not all(c.alive for c in targets):
                seen = port.generation  # first: a client arriving during the look is seen next time
                targets = port.connections(mask_bit=1)
            now = time.monotonic()
            if state != "RUN" or not targets or now < self.busy_until:
                self.wake.wait(0.05)
                self.wake.clear()
                next_t = time.monotonic()
                continue
            if now < next_t:
                self._stop.wait(min(next_t - now, 0.05))
                continue
            next_t = max(next_t + 1.0 / max(rate, 0.1), now)  # the frame period, s
            self._send_frame(targets)

    def _send_frame(self, targets: list[Conn]) -> None:
        with self._send_lock:  # one reused encode buffer per chunk selection
            with self._render_lock:  # first: a fault injected while rendering applies here
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
            ts_ns = self._clock_ns(source_s)
            for c in targets:
                data = self.encoder.encode(counts, self._frame_count, ts_ns, c.chunks)
                if fault is not None:
                    faulty_send(c, bytes(data), fault, self._stop)
                elif c.send(data):
                    self.frames_sent += 1


def faulty_send(conn: Conn, data: bytes, fault: Fault, stop: threading.Event) -> None:
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


__all__ = ["FAULT_KINDS", "Fault", "Head3D", "faulty_send"]
