"""Backend ``o3r-emulated``: the real ``o3r`` driver talking to an in-process O3R emulator.

Every capture goes through XML-RPC, PCIC framing, the O3R chunk layout and the
driver's decoder. ``configs/o3r_emulated.toml`` is ``configs/sim.toml`` with
``backend = "o3r-emulated"``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

from cellcal.devices.base import BackendContext
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import NotConnectedError
from cellcal.devices.measurement import MeasurementModel
from cellcal.devices.registry import default_registry
from cellcal.devices.types import DeviceInfo, Frame, Intrinsics

from ..camera import SimCamera, SimCameraConfig
from .emulator import O3REmulator
from .wire import DISTANCE_RESOLUTION_M, O3RModels

DRIVER_BACKEND = "o3r"
"""Registry name of the driver the emulated camera connects (never imported by name: sims
depend on devices only)."""


def intrinsics_from_inverse_model(models: O3RModels, width: int, height: int) -> Intrinsics:
    """The OpenCV intrinsics the emulator's inverse model 1 (ray -> pixel) carries.

    Undoes :func:`~cellcal.sims.o3r.wire.models_from_intrinsics` on the float32 values
    it put on the wire: ``cx = mx - 0.5``, ``cy = my - 0.5``, and the ifm coefficients
    ``k1, k2, k3, k4, k5`` are OpenCV's ``k1, k2, p1, p2, k3``.

    Args:
        models: The emulator's models.
        width: Image width, pixels.
        height: Image height, pixels.
    """
    fx, fy, mx, my, _alpha, k1, k2, p1, p2, k3 = models.inverse[:10]
    return Intrinsics(width=width, height=height, fx=fx, fy=fy, cx=mx - 0.5, cy=my - 0.5,
                      k1=k1, k2=k2, k3=k3, p1=p1, p2=p2)


@dataclass(frozen=True)
class EmulatedO3RConfig(SimCameraConfig):
    """The ``sim`` camera keys plus the emulator / driver keys.

    With ``trigger = "software"`` (the default) the port is IDLE and each capture sends
    one PCIC ``t``: the emulator renders exactly one frame from the world's current
    camera pose, drawing the simulated camera's random numbers exactly as the pure
    ``sim`` backend does, so both give the same calibration for the same seed, up to
    the wire's float32 / distance quantisation. ``"free_run"`` streams at the camera's
    ``frame_rate_hz`` (this advances the simulated clock on its own, so it is not
    deterministic).
    """

    trigger: Literal["software", "free_run"] = field(
        default="software", metadata={"doc": "IDLE + PCIC t per capture (deterministic) or RUN"})
    port_name: str = field(default="port2", metadata={"doc": "VPU port of the emulated 3D head"})
    distance_resolution_m: float = field(default=DISTANCE_RESOLUTION_M, metadata={
        "gt": 0.0, "le": 0.01, "doc": "metres per distance count on the wire (10/65535 as on a VPU)"})
    header_version: int = field(default=0, metadata={
        "ge": 0, "le": 3, "doc": "chunk header version for all chunks; 0 = the mix a real VPU sends"})
    confidence_bits: Literal[8, 16] = field(default=16, metadata={"doc": "confidence image: 8 or 16 bit"})
    io_timeout_s: float = field(default=5.0, metadata={"gt": 0.0, "le": 600.0, "doc": "driver I/O timeout, s"})


class EmulatedO3RCamera(Camera3D):
    """``O3RCamera`` connected to an in-process O3R emulator around ``SimCamera``.

    The emulator serves a :class:`~cellcal.sims.camera.SimCamera` of the shared
    simulated world on 127.0.0.1 ephemeral ports. The driver is the camera registered
    as :data:`DRIVER_BACKEND` (``"o3r"``), built by the registry from a config section,
    as a cell config would build it.

    Args:
        config: Backend config; None uses the defaults.
        context: Backend context (gives the shared simulated world).

    Attributes:
        sim: The simulated camera behind the emulator.
        emulator: The running emulator (None until connected).
        driver: The connected ``o3r`` driver (None until connected).
    """

    backend_name = "o3r-emulated"
    Config = EmulatedO3RConfig

    def __init__(self, config: EmulatedO3RConfig | None = None, context: BackendContext | None = None) -> None:
        super().__init__()
        self.config = config or EmulatedO3RConfig()
        sim_keys = {f.name for f in dataclasses.fields(SimCameraConfig)}
        sim_cfg = SimCameraConfig(**{k: getattr(self.config, k) for k in sim_keys})
        self.sim = SimCamera(sim_cfg, context)
        self.default_timeout_s: float = max(2.0, self.config.io_timeout_s)
        self.emulator: O3REmulator | None = None
        self.driver: Camera3D | None = None
        #: Fault injection (tests): called with the started emulator before the driver connects.
        self.on_emulator_started: Callable[[O3REmulator], None] | None = None
        self._captured = False

    def _connect(self, timeout: float) -> None:
        cfg = self.config
        self._captured = False
        self.sim.connect(timeout)
        # the sim's clock is the device clock (clock "unix" + a driver that trusts it), so frames carry
        # the simulated time exactly as the pure sim backend stamps them
        self.emulator = O3REmulator(self.sim, port_name=cfg.port_name,
                                    state="IDLE" if cfg.trigger == "software" else "RUN",
                                    frame_rate_hz=cfg.frame_rate_hz, max_frame_rate_hz=max(30.0, cfg.frame_rate_hz),
                                    distance_resolution_m=cfg.distance_resolution_m,
                                    header_version=cfg.header_version or None, confidence_bits=cfg.confidence_bits,
                                    clock="unix").start()
        if self.on_emulator_started is not None:
            self.on_emulator_started(self.emulator)
        section = {"backend": DRIVER_BACKEND, "host": "127.0.0.1", "xmlrpc_port": self.emulator.xmlrpc_port,
                   "port": cfg.port_name, "trigger": cfg.trigger, "set_state": False,
                   "io_timeout_s": cfg.io_timeout_s, "connect_timeout_s": min(cfg.io_timeout_s, timeout),
                   "clock_tolerance_s": 1e9}
        self.driver = default_registry().create_camera(section, BackendContext(section="camera.driver"))
        self.driver.connect(timeout)

    def _close(self) -> None:
        if self.driver is not None:
            self.driver.close()
            self.driver = None
        if self.emulator is not None:
            self.emulator.close()
            self.emulator = None
        self.sim.close()

    def _info(self) -> DeviceInfo:
        assert self.driver is not None and self.emulator is not None
        inner = self.driver.info()
        return DeviceInfo(backend="o3r-emulated", vendor="cellcal (emulated ifm)", model="O3R222 (emulated)",
                          serial=inner.serial, firmware=inner.firmware,
                          extra={**inner.extra, "xmlrpc_port": self.emulator.xmlrpc_port,
                                 "pcic_port": self.emulator.pcic_port})

    def _capture(self, timeout: float) -> Frame:
        if self.driver is None:
            raise NotConnectedError("o3r-emulated: not connected")
        frame = self.driver.capture(timeout)
        self._captured = True
        # the driver stamps its own (data-sheet) model; the noise on the wire is the sim's
        return dataclasses.replace(frame, measurement=self._measurement_model())

    def _measurement_model(self) -> MeasurementModel:
        """ToF: the model of the simulated camera behind the emulator (the noise law it draws, 1 mm steps).

        Not the driver's data-sheet model: the emulated camera's noise is the sim's, so its
        frames carry the sim's model (:meth:`_capture`) and it calibrates as ``sim`` does.
        """
        return self.sim.measurement_model

    def _configured_intrinsics(self) -> Intrinsics | None:
        """The simulated camera's (the driver decodes them from float32 models: the same to about 1e-5 px)."""
        return self.sim.configured_intrinsics()

    def _intrinsics(self) -> Intrinsics:
        """The intrinsics exactly as the driver decodes them, without triggering a frame.

        After the first capture they are the driver's (decoded from the frames' TOF_INFO);
        before it, asking the driver would trigger a frame and draw the simulated camera's
        random numbers, so they are read back from the models the emulator sends, as the
        driver will decode them.
        """
        if self.driver is None or self.emulator is None:
            raise NotConnectedError("o3r-emulated: not connected")
        if self._captured:
            return self.driver.intrinsics
        intr = self.sim.intrinsics
        return intrinsics_from_inverse_model(self.emulator.models, intr.width, intr.height)
