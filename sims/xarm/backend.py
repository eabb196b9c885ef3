"""Backend ``xarm-emulated``: the real ``xarm`` driver talking to the xArm emulator on a pty or over TCP.

Every call goes through the whole wire stack (serial: framing, CRC; TCP: transaction ids,
the report stream; both: state polling, unit conversion) against the same simulated world
a ``sim`` camera sees. An emulated config is the simulated one with
``backend = "xarm-emulated"`` (and ``transport = "tcp"`` for Ethernet).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, Literal, get_type_hints

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.arm import RobotArm
from cellcal.devices.arrival import ArrivalTolerance
from cellcal.devices.base import BackendContext
from cellcal.devices.errors import ConfigError, NotConnectedError
from cellcal.devices.pose import Pose
from cellcal.devices.registry import default_registry
from cellcal.devices.types import ArmStatus, DeviceInfo
from cellcal.sims.arm import SimArm, SimArmConfig

from .emulator import XArmEmulator
from .tcp_server import XArmTcpServer

DRIVER_BACKEND = "xarm"
"""Registry name of the driver the emulated arm connects (never imported by name: sims
depend on devices only)."""

_OWN_FIELDS: list[tuple[str, Any, Any]] = [
    ("axes", Literal[5, 6, 7], dataclasses.field(default=5, metadata={"doc": "axis count the emulator reports"})),
    ("firmware", str, dataclasses.field(default="2.5.0", metadata={"doc": "firmware version reported, X.Y.Z"})),
    ("transport", Literal["serial", "tcp"], dataclasses.field(
        default="serial", metadata={"doc": "serial: a pty; tcp: control and report ports on 127.0.0.1 (free ports)"})),
    ("report_hz", float, dataclasses.field(default=50.0, metadata={"ge": 0.5, "le": 1000,
                                                                   "doc": "report stream rate over TCP, 1/s"})),
    ("reply_timeout_s", float, dataclasses.field(
        default=0.5, metadata={"ge": 0.001, "le": 10, "doc": "driver per-attempt reply timeout, s"})),
    ("retries", int, dataclasses.field(default=2, metadata={"ge": 0, "le": 10,
                                                            "doc": "driver retries on a bad/missing reply"})),
    ("poll_interval_s", float, dataclasses.field(default=0.005, metadata={"ge": 0.001, "le": 1,
                                                                           "doc": "driver state polling period, s"})),
]
_SIM_NAMES = tuple(f.name for f in dataclasses.fields(SimArmConfig))


def _parse_firmware(text: str) -> tuple[int, int, int]:
    parts = text.strip().lstrip("vV").split(".")
    if len(parts) != 3 or not all(p.isdigit() for p in parts):
        raise ConfigError(f"firmware must look like 2.5.0, got {text!r}", key="firmware")
    return int(parts[0]), int(parts[1]), int(parts[2])


def _post_init(self: Any) -> None:
    SimArmConfig(**{name: getattr(self, name) for name in _SIM_NAMES})  # validates the sim part
    _parse_firmware(self.firmware)


def _make_config() -> type[Any]:
    hints = get_type_hints(SimArmConfig)
    sim_fields = [(f.name, hints[f.name], dataclasses.field(default=f.default, metadata=f.metadata))
                  for f in dataclasses.fields(SimArmConfig)]
    own_names = {name for name, _, _ in _OWN_FIELDS}
    clash = own_names.intersection(_SIM_NAMES)
    if clash:  # pragma: no cover - guards a future change of the sim arm's config
        raise RuntimeError(f"xarm-emulated config keys clash with the sim arm's: {sorted(clash)}")
    cls = dataclasses.make_dataclass("Config", [*sim_fields, *_OWN_FIELDS], frozen=True,
                                     namespace={"__post_init__": _post_init,
                                                "__doc__": "The ``[arm]`` section for ``backend = \"xarm-emulated\"``: "
                                                           "the sim arm's keys plus the emulator's."})
    cls.__module__ = __name__
    cls.__qualname__ = "EmulatedXArmArm.Config"
    return cls


class EmulatedXArmArm(RobotArm):
    """The xArm driver over a pty to the xArm emulator of the shared simulated arm.

    Builds the simulated arm of the shared sim world (:class:`~cellcal.sims.arm.SimArm`),
    serves it with an :class:`~cellcal.sims.xarm.emulator.XArmEmulator` on a
    pseudo-terminal, and delegates every call to the real xArm driver (the arm
    registered as ``"xarm"``, built by the registry from a config section as a cell
    config would build it) connected to that pty. ``close()`` shuts down the driver,
    the emulator thread and the pty. Its config section accepts every key of the
    ``sim`` arm (``time_scale``, ``reach_m``, ...) plus the emulator/driver keys of
    ``_OWN_FIELDS``. A move's arrival is checked twice: by the driver (its read-back over
    the wire) and by this backend, both with this backend's tolerance.

    Args:
        config: Validated :attr:`Config`; None uses the defaults.
        context: Backend context; its shared sim world is the one the arm moves.

    Attributes:
        sim_arm: The simulated arm behind the emulator.
        emulator: The running emulator (None until connected).
        driver: The connected ``xarm`` driver (None until connected).
    """

    backend_name = "xarm-emulated"
    Config = _make_config()

    def __init__(self, config: Any = None, context: BackendContext | None = None):
        super().__init__()
        self.config = config if config is not None else EmulatedXArmArm.Config()
        self.context = context
        sim_cfg = SimArmConfig(**{name: getattr(self.config, name) for name in _SIM_NAMES})
        self.sim_arm = SimArm(sim_cfg, context)
        self.emulator: XArmEmulator | None = None
        self.server: XArmTcpServer | None = None
        self.driver: RobotArm | None = None
        #: Fault injection (tests): called with the started emulator before the driver connects.
        self.on_emulator_started: Callable[[XArmEmulator], None] | None = None

    @property
    def path(self) -> str:
        """The emulator's pty path ("" when not connected or over TCP)."""
        return self.emulator.path if self.emulator is not None else ""

    def _wire_section(self) -> dict[str, Any]:
        """Start the emulator on the configured transport; the driver's section keys that reach it."""
        assert self.emulator is not None
        if self.config.transport == "tcp":
            self.server = XArmTcpServer(self.emulator, report_hz=self.config.report_hz)
            tcp_port, report_port = self.server.start()
            return {"host": self.server.host, "tcp_port": tcp_port, "report_port": report_port}
        return {"port": self.emulator.start()}

    def _connect(self, timeout: float) -> None:
        cfg = self.config
        self.sim_arm.connect(timeout)
        self.emulator = XArmEmulator(self.sim_arm, axes=cfg.axes, firmware=_parse_firmware(cfg.firmware))
        wire = self._wire_section()
        if self.on_emulator_started is not None:
            self.on_emulator_started(self.emulator)
        section = {"backend": DRIVER_BACKEND, **wire, "axes": cfg.axes, "reply_timeout_s": cfg.reply_timeout_s,
                   "retries": cfg.retries, "poll_interval_s": cfg.poll_interval_s}
        self.driver = default_registry().create_arm(section, self.context)
        self.driver.default_motion_timeout_s = self.default_motion_timeout_s
        self.driver.arrival_tolerance = self.arrival_tolerance
        self.driver.connect(timeout)

    def _close(self) -> None:
        driver, self.driver = self.driver, None
        emulator, self.emulator = self.emulator, None
        server, self.server = self.server, None
        if driver is not None:
            driver.close()
        if server is not None:
            server.close()
        if emulator is not None:
            emulator.close()
        self.sim_arm.close()

    def default_arrival_tolerance(self) -> ArrivalTolerance:
        """The sim arm's (which widens with its read-back repeatability); the driver gets the same."""
        return self.sim_arm.default_arrival_tolerance()

    def _set_arrival_tolerance(self, value: ArrivalTolerance) -> None:
        super()._set_arrival_tolerance(value)
        if self.driver is not None:
            self.driver.arrival_tolerance = value

    def _drv(self) -> RobotArm:
        if self.driver is None:
            raise NotConnectedError("xarm-emulated: not connected")
        return self.driver

    def _info(self) -> DeviceInfo:
        inner = self._drv().info()
        return DeviceInfo(backend=self.backend_name, vendor=inner.vendor, model=f"{inner.model} (emulated)",
                          serial=inner.serial, firmware=inner.firmware, extra={**inner.extra, "emulated": True})

    def _get_pose(self, timeout: float) -> Pose:
        return self._drv().get_pose(timeout)

    def _move_linear(self, pose: Pose, speed: float, acceleration: float, timeout: float) -> None:
        self._drv().move_linear(pose, speed=speed, acceleration=acceleration, timeout=timeout)

    def _stop(self, timeout: float) -> None:
        self._drv().stop(timeout)

    def _joint_positions(self, timeout: float) -> NDArray[np.float64]:
        return self._drv().joint_positions(timeout)

    def _status(self, timeout: float) -> ArmStatus:
        return self._drv().status(timeout)

    def _clear_errors(self, timeout: float) -> None:
        self._drv().clear_errors(timeout)

    def recover(self, timeout: float | None = None) -> None:
        """The xArm recovery sequence (the driver's ``clear_errors``: clean warning, clean error,
        motion enable, mode 0, state 0)."""
        self.clear_errors(timeout)
