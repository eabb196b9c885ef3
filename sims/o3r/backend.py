"""Backend ``o3r-emulated``: the real ``o3r`` driver talking to an in-process O3R emulator.

The emulator serves a :class:`~cellcal.sims.camera.SimCamera3D` of the shared
simulated world on 127.0.0.1 ephemeral ports; every capture goes through XML-RPC,
PCIC framing, the O3R chunk layout and the driver's decoder. Its config is the
``sim`` camera's table plus the keys below, so ``configs/o3r_emulated.toml`` is
``configs/sim.toml`` with ``backend = "o3r-emulated"``.

With ``trigger = "software"`` (the default) the port is IDLE and each capture sends
one PCIC ``t``: the emulator renders exactly one frame from the world's current
camera pose, drawing the simulated camera's random numbers exactly as the pure
``sim`` backend does — so both give the same calibration for the same seed, up to
the wire's float32 / distance quantisation. ``"free_run"`` streams at the camera's
``frame_rate_hz`` (this advances the simulated clock on its own, so it is not
deterministic).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

from cellcal.devices.base import BackendContext
from cellcal.devices.camera import Camera3D
from cellcal.devices.types import DeviceInfo, Frame, Intrinsics
from cellcal.drivers.o3r.camera import O3RCamera, O3RConfig
from cellcal.drivers.o3r.tofinfo import IntrinsicModel, TofInfo, intrinsics_from_models

from ..camera import SimCamera3D, SimCamera3DConfig
from .emulator import O3REmulator


@dataclass(frozen=True)
class EmulatedO3RConfig(SimCamera3DConfig):
    """The ``sim`` camera keys plus the emulator / driver keys."""

    trigger: Literal["software", "free_run"] = field(
        default="software", metadata={"doc": "IDLE + PCIC t per capture (deterministic) or RUN"})
    port_name: str = field(default="port2", metadata={"doc": "VPU port of the emulated 3D head"})
    distance_resolution_m: float = field(default=0.000125, metadata={"gt": 0.0, "le": 0.01,
                                                                     "doc": "metres per distance count on the wire"})
    header_version: int = field(default=2, metadata={"ge": 1, "le": 3, "doc": "chunk header version"})
    io_timeout_s: float = field(default=5.0, metadata={"gt": 0.0, "le": 600.0, "doc": "driver I/O timeout, s"})


class EmulatedO3RCamera(Camera3D):
    """``O3RCamera`` connected to an in-process O3R emulator around ``SimCamera3D``.

    Args:
        config: Backend config; None uses the defaults.
        context: Backend context (gives the shared simulated world).
    """

    backend_name = "o3r-emulated"
    Config = EmulatedO3RConfig

    def __init__(self, config: EmulatedO3RConfig | None = None, context: BackendContext | None = None) -> None:
        super().__init__()
        self.config = config or EmulatedO3RConfig()
        sim_keys = {f.name for f in dataclasses.fields(SimCamera3DConfig)}
        sim_cfg = SimCamera3DConfig(**{k: getattr(self.config, k) for k in sim_keys})
        self.sim = SimCamera3D(sim_cfg, context)
        self.default_timeout_s: float = max(2.0, self.config.io_timeout_s)
        self.emulator: O3REmulator | None = None
        self.driver: O3RCamera | None = None
        #: Fault injection (tests): called with the started emulator before the driver connects.
        self.on_emulator_started: Callable[[O3REmulator], None] | None = None

    def _connect(self, timeout: float) -> None:
        cfg = self.config
        self.sim.connect(timeout)
        self.emulator = O3REmulator(self.sim, port_name=cfg.port_name,
                                    state="IDLE" if cfg.trigger == "software" else "RUN",
                                    frame_rate_hz=cfg.frame_rate_hz, distance_resolution_m=cfg.distance_resolution_m,
                                    header_version=cfg.header_version).start()
        if self.on_emulator_started is not None:
            self.on_emulator_started(self.emulator)
        self.driver = O3RCamera(O3RConfig(host="127.0.0.1", xmlrpc_port=self.emulator.xmlrpc_port,
                                          port=cfg.port_name, trigger=cfg.trigger, set_state=False,
                                          io_timeout_s=cfg.io_timeout_s,
                                          connect_timeout_s=min(cfg.io_timeout_s, timeout)))
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
        assert self.driver is not None
        return self.driver.capture(timeout)

    def _intrinsics(self) -> Intrinsics:
        """The intrinsics exactly as the driver decodes them, without triggering a frame."""
        assert self.driver is not None and self.emulator is not None
        if self.driver.tof_info is not None:
            return self.driver.intrinsics
        m = self.emulator.models
        info = TofInfo(version=3, distance_resolution_m=self.config.distance_resolution_m, amplitude_resolution=1.0,
                       amp_norm_factors=(1.0, 1.0, 1.0), extrinsic_optic_to_user=(0.0,) * 6,  # type: ignore[arg-type]
                       intrinsic=IntrinsicModel(0, m.forward), inverse_intrinsic=IntrinsicModel(1, m.inverse))
        intr = self.sim.intrinsics
        return intrinsics_from_models(info, intr.width, intr.height)
