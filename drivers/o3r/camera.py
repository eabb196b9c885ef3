"""The ifm O3R 3D head as a cellcal :class:`Camera3D` (backend ``o3r``): XML-RPC set-up, PCIC over TCP.

XYZ in the camera optical frame by default (``xyz_frame = "optical"``); intrinsics
from TOF_INFO's inverse model 1, which is OpenCV's projection (see :mod:`.tofinfo`).
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import ClassVar, Literal

from cellcal.devices.base import BackendContext
from cellcal.devices.camera import Camera3D
from cellcal.devices.discovery import HostScan
from cellcal.devices.errors import ConfigError, DeviceConnectionError, ProtocolError
from cellcal.devices.measurement import MeasurementModel
from cellcal.devices.types import DeviceInfo, Frame, Intrinsics

from . import discover
from .client import PcicStream
from .decode import FrameDecoder
from .tofinfo import TofInfo
from .xmlrpc_config import O3RConfigClient, PortInfo

#: The O3R 3D head's range noise, 1-sigma at 1 m and normal incidence, metres: ifm's O3R222
#: data sheet quotes a repeatability of < 7 mm at distances below 1 m (the figure the simulated
#: camera is built on, docs/adr/0014-simulated-cell.md), read as 2 sigma: 3.5 mm. A data-sheet
#: figure (a real frame agrees, see the exponent below); change it here and in
#: drivers/o3r_ifm3d/camera.py (which must state the same model; a test checks both).
O3R_SIGMA_AT_1M_M = 0.0035
#: Exponent of the range in the O3R's noise law, set against a real O3R frame (ifm's own test
#: capture, tests/data/o3r): its pixel scatter is flat with range, 3.0 mm on a face 0.28 m away at
#: 50 deg incidence and 3-4.2 mm over 0.2-0.8 m, which with 3.5 mm at 1 m gives 0.3. Beyond ~1.5 m the
#: data sheet's figures grow faster (2 sigma 15 mm at 2 m, 51 mm at 4 m): the residual gate's
#: factor of 4 still covers 2 m; state a steeper law in [camera.model] for a cell working farther.
O3R_DISTANCE_EXPONENT = 0.3


def o3r_measurement_model() -> MeasurementModel:
    """The O3R head's ToF model from the data sheet (``source = "backend"``)."""
    return MeasurementModel(kind="tof", sigma_at_1m_m=O3R_SIGMA_AT_1M_M, distance_exponent=O3R_DISTANCE_EXPONENT,
                            source="backend", settings={"basis": "O3R222 data sheet repeatability, read as 2 sigma"})


@dataclass(frozen=True)
class O3RConfig:
    """The ``[camera]`` table of the ``o3r`` backend."""

    host: str = field(default="192.168.0.69", metadata={"doc": "VPU address"})
    xmlrpc_port: int = field(default=80, metadata={"ge": 1, "le": 65535, "doc": "XML-RPC TCP port"})
    port: str = field(default="port2", metadata={"doc": "VPU port of the 3D head: port0..port5 (several heads on one "
                                                        "VPU: one camera entry per head; '' = no XML-RPC, use "
                                                        "pcic_port)"})
    pcic_port: int = field(default=0, metadata={"ge": 0, "le": 65535,
                                                "doc": "PCIC TCP port; 0 = read /ports/<port>/data/pcicTCPPort"})
    trigger: Literal["free_run", "software"] = field(default="free_run",
                                                     metadata={"doc": "RUN (free_run) or IDLE + PCIC t (software)"})
    set_state: bool = field(default=True, metadata={"doc": "switch the port between RUN and IDLE as needed"})
    connect_timeout_s: float = field(default=3.0, metadata={"ge": 0.01, "le": 120.0, "doc": "TCP connect, s"})
    io_timeout_s: float = field(default=2.0, metadata={"ge": 0.01, "le": 120.0,
                                                        "doc": "whole XML-RPC call / mid-message stall timeout, s"})
    reconnect_backoff_s: float = field(default=0.1, metadata={"ge": 0.001, "le": 10.0,
                                                              "doc": "first retry delay, s"})
    reconnect_backoff_max_s: float = field(default=2.0, metadata={"ge": 0.001, "le": 120.0,
                                                                  "doc": "longest retry delay, s"})
    max_frame_bytes: int = field(default=32 * 1024 * 1024, metadata={"ge": 4096, "le": 256 * 1024 * 1024,
                                                                      "doc": "cap on one PCIC message, bytes"})
    max_buffered_bytes: int = field(default=1024 * 1024, metadata={
        "ge": 4096, "le": 256 * 1024 * 1024, "doc": "cap on PCIC replies + notifications held at once, bytes"})
    max_rpc_reply_bytes: int = field(default=4 * 1024 * 1024, metadata={
        "ge": 4096, "le": 256 * 1024 * 1024, "doc": "cap on one XML-RPC reply, bytes"})
    xyz_frame: Literal["optical", "user"] = field(default="optical",
                                                  metadata={"doc": "XYZ in the optical frame or ifm's user frame"})
    set_timeout_s: float = field(default=15.0, metadata={"ge": 1.0, "le": 600.0,
                                                         "doc": "timeout of one XML-RPC set (state changes), s"})
    first_frame_timeout_s: float = field(default=10.0, metadata={
        "ge": 0.01, "le": 600.0, "doc": "longest wait for the first frame after a state change, s"})
    clock_tolerance_s: float = field(default=30.0, metadata={
        "ge": 0.001, "le": 1e9, "doc": "device clock this far from host time is not Unix time (receive time used), s"})

    def __post_init__(self) -> None:
        if not self.port and self.pcic_port == 0:
            raise ValueError("give a VPU port name ('port') or a PCIC port ('pcic_port')")
        if self.reconnect_backoff_max_s < self.reconnect_backoff_s:
            raise ValueError("reconnect_backoff_max_s must be >= reconnect_backoff_s")
        if self.port and self.pcic_port == self.xmlrpc_port:
            raise ConfigError(f"{self.pcic_port} is also the XML-RPC port, which does not answer as PCIC "
                              f"(the VPU's PCIC ports are 50010 and up)", key="pcic_port")


class O3RCamera(Camera3D):
    """ifm O3R 3D head over PCIC/TCP.

    On connect the port's PCIC TCP port, type and state are read over XML-RPC; the
    port must be a 3D head (a port the VPU lacks, or one of another type, is a
    :class:`ConfigError` naming the VPU's 3D heads, before any frame is asked for). A VPU
    drives up to six heads: each is a camera of its own (``port = "port3"``); several
    cameras with one ``host`` and different ports connect, switch state and capture
    independently, each on its head's PCIC port. ``trigger = "free_run"`` wants the port in RUN (``capture``
    returns the newest frame received after the previous capture, never one older than
    the timeout); ``"software"`` wants IDLE (``capture`` sends one PCIC ``t`` and
    returns exactly the frame it produced). With ``set_state = true`` the driver
    switches a port in RUN, IDLE or CONF to the state it needs itself (as ifm's own
    examples do); the ``set`` has its own timeout (``set_timeout_s``, 15 s as in ifm3d:
    a VPU answers only once the head has changed state) and the first frame after it is
    awaited for up to ``first_frame_timeout_s``.

    Time: ``Frame.timestamp`` is the device's time when its clock is Unix time (SNTP set
    up on the VPU), else the receive time; ``Frame.metadata`` keeps the device time and
    the TOF_INFO facts of the frame (version, mode, the measurement block and its range
    in a cycling mode), see :class:`~.decode.FrameDecoder`.

    XYZ: the model-0 (or fisheye 2) unit vectors of TOF_INFO times the radial
    distance, in the camera optical frame (``xyz_frame = "optical"``, what
    :class:`Frame` documents), or additionally transformed by extrinsicOpticToUser
    into ifm's user frame (``"user"``, equal to ifm3d's XYZ buffer).

    Args:
        config: Backend config; None uses the defaults.
        context: Backend context (unused; accepted for the registry).
    """

    backend_name = "o3r"
    Config = O3RConfig

    # ------------------------------------------------------------ network discovery
    #: Standard ports by service name (``cellcal devices --scan --ports NAME=PORT``).
    scan_ports: ClassVar[Mapping[str, int]] = discover.PORTS
    #: Where a scan without ``--hosts`` / ``--subnet`` looks (``--factory``).
    factory_hosts: ClassVar[tuple[str, ...]] = discover.FACTORY_HOSTS

    @classmethod
    def scan_hosts(cls, hosts: Sequence[str] | None, timeout: float,
                   ports: Mapping[str, int] | None = None) -> HostScan:
        """O3R VPUs among ``hosts`` (None: :attr:`factory_hosts`) within ``timeout`` seconds (:mod:`.discover`)."""
        return discover.scan_hosts(hosts, timeout, ports)

    def __init__(self, config: O3RConfig | None = None, context: BackendContext | None = None) -> None:
        super().__init__()
        self.config = config or O3RConfig()
        self.default_timeout_s = max(2.0, self.config.io_timeout_s)
        self._rpc: O3RConfigClient | None = None
        self._stream: PcicStream | None = None
        self._decoder = FrameDecoder(apply_extrinsic=self.config.xyz_frame == "user",
                                     clock_tolerance_s=self.config.clock_tolerance_s)
        self._state_changed = False
        self._port_info: PortInfo | None = None
        self._firmware = ""
        self._last_mono = 0.0
        self._last_info: TofInfo | None = None
        self._last_intr: Intrinsics | None = None

    # ------------------------------------------------------------------ hooks
    def _connect(self, timeout: float) -> None:
        cfg = self.config
        deadline = time.monotonic() + timeout
        pcic_port = cfg.pcic_port
        if cfg.port:
            info = self._set_up_port(deadline)
            pcic_port = pcic_port or info.pcic_port
        stream = PcicStream(cfg.host, pcic_port, io_timeout_s=cfg.io_timeout_s,
                            connect_timeout_s=min(cfg.connect_timeout_s, timeout),
                            backoff_s=cfg.reconnect_backoff_s, backoff_max_s=cfg.reconnect_backoff_max_s,
                            max_payload=cfg.max_frame_bytes, max_buffered_bytes=cfg.max_buffered_bytes)
        self._stream = stream
        stream.start(max(deadline - time.monotonic(), 0.001))
        self._last_mono = 0.0

    def _set_up_port(self, deadline: float) -> PortInfo:
        """Read (and check) the port's configuration, switch its state if needed; all before ``deadline``."""
        cfg = self.config
        rpc = O3RConfigClient(cfg.host, cfg.xmlrpc_port, cfg.io_timeout_s, cfg.max_rpc_reply_bytes,
                              set_timeout_s=cfg.set_timeout_s)
        # a port the VPU lacks, or one that is not a 3D head, is one line naming the VPU's 3D heads
        info = rpc.port_info(cfg.port, timeout=deadline - time.monotonic(), kind="3D")
        if not cfg.pcic_port and info.pcic_port == cfg.xmlrpc_port:
            raise ProtocolError(f"O3R {cfg.host}: /ports/{cfg.port}/data/pcicTCPPort is {info.pcic_port}, the "
                                f"XML-RPC port; it does not answer as PCIC")
        want = "RUN" if cfg.trigger == "free_run" else "IDLE"
        if info.state != want:
            if not cfg.set_state:
                why = " (sends no data)" if info.state == "CONF" else ""
                raise DeviceConnectionError(f"O3R {cfg.host} {cfg.port} is in {info.state}{why}, trigger "
                                            f"'{cfg.trigger}' needs {want} (or set_state = true)")
            # the set has its own, longer timeout: the VPU answers once the head has switched
            rpc.set_state(cfg.port, want, timeout=cfg.set_timeout_s)
            self._state_changed = True
        self._port_info = info
        self._firmware = rpc.firmware(timeout=deadline - time.monotonic())
        self._rpc = rpc
        return info

    def _close(self) -> None:
        if self._stream is not None:
            self._stream.close()
            self._stream = None

    def _info(self) -> DeviceInfo:
        cfg = self.config
        stream = self._stream
        return DeviceInfo(
            backend="o3r", vendor="ifm electronic", model="O3R 3D head", serial="", firmware=self._firmware,
            extra={"host": cfg.host, "port": cfg.port, "pcic_port": stream.port if stream else cfg.pcic_port,
                   "trigger": cfg.trigger, "reconnects": stream.reconnects if stream else 0,
                   "imager": self._last_info.imager if self._last_info else "",
                   "mode": self._last_info.mode if self._last_info else ""})

    def _capture(self, timeout: float) -> Frame:
        stream = self._stream
        assert stream is not None
        if self._state_changed:  # a head just switched state: its first frame takes a while
            timeout = max(timeout, self.config.first_frame_timeout_s)
        if self.config.trigger == "software":
            raw = stream.trigger(timeout)
        else:
            raw = stream.next_frame(timeout, self._last_mono)
        self._last_mono = raw.received_mono
        self._state_changed = False
        decoded = self._decoder.decode(raw.payload, raw.chunks, offset=raw.offset, received_at=raw.received_epoch)
        self._last_info = decoded.tof_info
        self._last_intr = decoded.frame.intrinsics
        return decoded.frame

    def _measurement_model(self) -> MeasurementModel:
        return o3r_measurement_model()

    def _intrinsics(self) -> Intrinsics:
        if self._last_intr is None:
            self._capture(self.default_timeout_s)  # the intrinsics travel with the frames
        assert self._last_intr is not None
        return self._last_intr

    # ------------------------------------------------------------------ extras
    @property
    def tof_info(self) -> TofInfo | None:
        """TOF_INFO of the last captured frame (None before the first)."""
        return self._last_info

    @property
    def stream(self) -> PcicStream | None:
        """The PCIC stream (for diagnostics and tests)."""
        return self._stream
