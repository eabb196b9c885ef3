"""Backend ``xarm-emulated``: the real ``xarm`` driver talking to the xArm emulator on a pty or over TCP.

Every call goes through the whole wire stack (serial: framing, CRC; TCP: transaction ids,
the report stream; both: state polling, unit conversion) against the same simulated world
a ``sim`` camera sees. An emulated config is the simulated one with
``backend = "xarm-emulated"`` (and ``transport = "tcp"`` for Ethernet).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, Literal

from cellcal.devices.arm import RobotArm
from cellcal.devices.arrival import ArrivalTolerance
from cellcal.devices.base import BackendContext
from cellcal.devices.errors import ConfigError
from cellcal.sims.arm import SimArm, SimArmConfig
from cellcal.sims.emulated import EmulatedArm, emulated_arm_config, sim_arm_settings

from .emulator import XArmEmulator
from .tcp_server import XArmTcpServer

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


def _parse_firmware(text: str) -> tuple[int, int, int]:
    parts = text.strip().lstrip("vV").split(".")
    if len(parts) != 3 or not all(p.isdigit() for p in parts):
        raise ConfigError(f"firmware must look like 2.5.0, got {text!r}", key="firmware")
    return int(parts[0]), int(parts[1]), int(parts[2])


def _check_firmware(text: str) -> None:
    _parse_firmware(text)


class EmulatedXArmArm(EmulatedArm):
    """The xArm driver over a pty (or TCP) to the xArm emulator of the shared simulated arm.

    Builds the simulated arm of the shared sim world (:class:`~cellcal.sims.arm.SimArm`),
    serves it with an :class:`~cellcal.sims.xarm.emulator.XArmEmulator` on a
    pseudo-terminal or on two TCP ports, and delegates every call to the real xArm driver
    (the arm registered as ``"xarm"``, built by the registry from a config section as a
    cell config would build it). ``close()`` shuts down the driver, the emulator thread
    and the pty or sockets. Its config section accepts every key of the ``sim`` arm
    (``time_scale``, ``reach_m``, ...) plus the emulator/driver keys of ``_OWN_FIELDS``.
    A move's arrival is checked twice: by the driver (its read-back over the wire) and by
    this backend, both with this backend's tolerance.

    Args:
        config: Validated :attr:`Config`; None uses the defaults.
        context: Backend context; its shared sim world is the one the arm moves.

    Attributes:
        sim_arm: The simulated arm behind the emulator.
        emulator: The running emulator (None until connected).
        server: The TCP server in front of it (None unless connected over TCP).
        driver: The connected ``xarm`` driver (None until connected).
    """

    backend_name = "xarm-emulated"
    driver_backend = "xarm"
    Config = emulated_arm_config(
        backend_name, __name__, "EmulatedXArmArm.Config", _OWN_FIELDS,
        check=lambda cfg: _check_firmware(cfg.firmware),
        doc="The ``[arm]`` section for ``backend = \"xarm-emulated\"``: the sim arm's keys plus the emulator's.")

    def __init__(self, config: Any = None, context: BackendContext | None = None):
        super().__init__(config if config is not None else EmulatedXArmArm.Config(), context)
        self.sim_arm = SimArm(SimArmConfig(**sim_arm_settings(self.config)), context)
        self.emulator: XArmEmulator | None = None
        self.server: XArmTcpServer | None = None
        #: Fault injection (tests): called with the started emulator before the driver connects.
        self.on_emulator_started: Callable[[XArmEmulator], None] | None = None

    @property
    def path(self) -> str:
        """The emulator's pty path ("" when not connected or over TCP)."""
        return self.emulator.path if self.emulator is not None else ""

    def _start_emulator(self, timeout: float) -> dict[str, Any]:
        cfg = self.config
        self.sim_arm.connect(timeout)
        self.emulator = XArmEmulator(self.sim_arm, axes=cfg.axes, firmware=_parse_firmware(cfg.firmware))
        if cfg.transport == "tcp":
            self.server = XArmTcpServer(self.emulator, report_hz=cfg.report_hz)
            tcp_port, report_port = self.server.start()
            wire: dict[str, Any] = {"host": self.server.host, "tcp_port": tcp_port, "report_port": report_port}
        else:
            wire = {"port": self.emulator.start()}
        if self.on_emulator_started is not None:
            self.on_emulator_started(self.emulator)
        return {**wire, "axes": cfg.axes, "reply_timeout_s": cfg.reply_timeout_s, "retries": cfg.retries,
                "poll_interval_s": cfg.poll_interval_s}

    def _configure_driver(self, driver: RobotArm) -> None:
        driver.arrival_tolerance = self.arrival_tolerance

    def _stop_emulator(self) -> None:
        emulator, self.emulator = self.emulator, None
        server, self.server = self.server, None
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

    def recover(self, timeout: float | None = None) -> None:
        """The xArm recovery sequence (the driver's ``clear_errors``: clean warning, clean error,
        motion enable, mode 0, state 0)."""
        self.clear_errors(timeout)
