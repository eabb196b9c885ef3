"""Backend ``ur-emulated``: the real ``ur`` driver (ur_rtde) talking to the UR emulator on a free 127.0.0.N.

The emulator runs as a child process (ur_rtde's constructors hold the GIL, see
:mod:`.process`) with its own copy of the simulated arm; after every call that can
move the arm, the true flange pose and the simulated time of the motion are copied
into the shared sim world, so a ``sim`` camera sees what it would see in a pure sim.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, get_type_hints

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.arm import RobotArm
from cellcal.devices.base import BackendContext
from cellcal.devices.errors import NotConnectedError
from cellcal.devices.geometry.vendor_poses import pose_from_ur, pose_to_ur
from cellcal.devices.pose import Pose
from cellcal.devices.registry import default_registry
from cellcal.devices.types import ArmStatus, DeviceInfo
from cellcal.sims.arm import SimArmConfig
from cellcal.sims.world import SimWorld, world_from_context

from .emulator import UR_LIKE
from .process import UREmulatorProcess

DRIVER_BACKEND = "ur"
"""Registry name of the driver the emulated arm connects (never imported by name: sims
depend on devices only)."""

_OWN_FIELDS: list[tuple[str, Any, Any]] = [
    ("timeout_s", float, dataclasses.field(default=5.0, metadata={"gt": 0, "le": 60,
                                                                  "doc": "driver I/O timeout, s"})),
    ("stale_after_s", float, dataclasses.field(default=0.5, metadata={
        "gt": 0, "le": 10, "doc": "driver: receive timestamp unchanged this long is a stale stream, s"})),
    ("poll_interval_s", float, dataclasses.field(default=0.005, metadata={"gt": 0, "le": 1,
                                                                           "doc": "driver status polling period, s"})),
    ("unlock_delay_s", float, dataclasses.field(default=5.0, metadata={
        "ge": 0, "le": 60, "doc": "emulator: a protective stop can be unlocked this long after it, s"})),
    ("start_timeout_s", float, dataclasses.field(default=30.0, metadata={
        "gt": 0, "le": 300, "doc": "time allowed for the emulator process to start, s"})),
]
_SIM_NAMES = tuple(f.name for f in dataclasses.fields(SimArmConfig))


def _post_init(self: Any) -> None:
    SimArmConfig(**{name: getattr(self, name) for name in _SIM_NAMES})  # validates the sim part


def _make_config() -> type[Any]:
    hints = get_type_hints(SimArmConfig)
    sim_fields = [(f.name, hints[f.name], dataclasses.field(default=UR_LIKE.get(f.name, f.default),
                                                            metadata=f.metadata))
                  for f in dataclasses.fields(SimArmConfig)]
    clash = {name for name, _, _ in _OWN_FIELDS}.intersection(_SIM_NAMES)
    if clash:  # pragma: no cover - guards a future change of the sim arm's config
        raise RuntimeError(f"ur-emulated config keys clash with the sim arm's: {sorted(clash)}")
    cls = dataclasses.make_dataclass("Config", [*sim_fields, *_OWN_FIELDS], frozen=True,
                                     namespace={"__post_init__": _post_init,
                                                "__doc__": "The ``[arm]`` section for ``backend = \"ur-emulated\"``: "
                                                           "the sim arm's keys (UR5e-like defaults) plus the "
                                                           "driver's and the emulator's."})
    cls.__module__ = __name__
    cls.__qualname__ = "EmulatedURArm.Config"
    return cls


class EmulatedURArm(RobotArm):
    """The ``ur`` driver over ur_rtde to a UR emulator process moving the shared sim world's arm.

    ``connect()`` starts ``python -m cellcal.sims.ur --host auto`` (a free 127.0.0.N) with
    the sim arm's settings and the world's current flange pose, then builds the ``ur``
    driver from the registry (as a cell config would) and connects it. ``close()``
    closes the driver and ends the child process.

    Args:
        config: Validated :attr:`Config`; None uses the defaults.
        context: Backend context; its shared sim world is kept in step with the emulated arm.

    Attributes:
        emulator: The emulator process (None until connected).
        driver: The connected ``ur`` driver (None until connected).
    """

    backend_name = "ur-emulated"
    Config = _make_config()

    def __init__(self, config: Any = None, context: BackendContext | None = None):
        super().__init__()
        self.config = config if config is not None else EmulatedURArm.Config()
        self.context = context
        self.world: SimWorld = world_from_context(context)
        self.emulator: UREmulatorProcess | None = None
        self.driver: RobotArm | None = None
        self._sim_elapsed = 0.0
        #: Fault injection (tests): called with the started emulator before the driver connects.
        self.on_emulator_started: Callable[[UREmulatorProcess], None] | None = None

    @property
    def host(self) -> str:
        """The emulator's address ("" when not connected)."""
        return self.emulator.host if self.emulator is not None else ""

    def _connect(self, timeout: float) -> None:
        cfg = self.config
        emulator = UREmulatorProcess(
            "auto", arm_config={name: getattr(cfg, name) for name in _SIM_NAMES},
            flange_pose=[float(v) for v in pose_to_ur(self.world.arm.flange_pose())],
            unlock_delay_s=cfg.unlock_delay_s, seed=self.world.seed)
        self.emulator = emulator
        emulator.start(cfg.start_timeout_s)
        self._sim_elapsed = 0.0
        if self.on_emulator_started is not None:
            self.on_emulator_started(emulator)
        section = {"backend": DRIVER_BACKEND, "host": emulator.host, "timeout_s": cfg.timeout_s,
                   "stale_after_s": cfg.stale_after_s, "poll_interval_s": cfg.poll_interval_s}
        self.driver = default_registry().create_arm(section, self.context)
        self.driver.default_motion_timeout_s = self.default_motion_timeout_s
        self.driver.connect(timeout)

    def _close(self) -> None:
        driver, self.driver = self.driver, None
        emulator, self.emulator = self.emulator, None
        try:
            if driver is not None:
                driver.close()
        finally:
            if emulator is not None:
                emulator.close()

    def _drv(self) -> RobotArm:
        if self.driver is None:
            raise NotConnectedError("ur-emulated: not connected")
        return self.driver

    def _sync_world(self) -> None:
        """Copy the emulated arm's true flange pose, and the simulated time its motions took, into the world."""
        if self.emulator is None:
            return
        snap = self.emulator.snapshot()
        self.world.arm.set_flange_pose(pose_from_ur(snap["flange"]))
        elapsed = float(snap["sim_elapsed_s"])
        self.world.clock.advance(elapsed - self._sim_elapsed)
        self._sim_elapsed = elapsed

    def _info(self) -> DeviceInfo:
        inner = self._drv().info()
        return DeviceInfo(backend=self.backend_name, vendor=inner.vendor, model=f"{inner.model} (emulated)",
                          serial=inner.serial, firmware=inner.firmware,
                          extra={**inner.extra, "emulated": True})

    def _get_pose(self, timeout: float) -> Pose:
        return self._drv().get_pose(timeout)

    def _move_linear(self, pose: Pose, speed: float, acceleration: float, timeout: float) -> None:
        try:
            self._drv().move_linear(pose, speed=speed, acceleration=acceleration, timeout=timeout)
        finally:
            self._sync_world()

    def _stop(self, timeout: float) -> None:
        try:
            self._drv().stop(timeout)
        finally:
            self._sync_world()

    def _joint_positions(self, timeout: float) -> NDArray[np.float64]:
        return self._drv().joint_positions(timeout)

    def _status(self, timeout: float) -> ArmStatus:
        return self._drv().status(timeout)

    def _clear_errors(self, timeout: float) -> None:
        self._drv().clear_errors(timeout)
