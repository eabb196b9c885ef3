"""A real arm driver against a wire emulator of the simulated arm: the shell the ``*-emulated`` arms share.

An emulated arm backend builds its ``[arm]`` section from the sim arm's keys plus its own
(:func:`emulated_arm_config`), starts an emulator in ``_start_emulator``, builds the real
driver from the registry by name (sims never import drivers) and forwards every call to
it. What differs per vendor is only how the emulator runs and what it needs.
"""

from __future__ import annotations

import dataclasses
import time
from abc import abstractmethod
from collections.abc import Callable, Mapping
from typing import Any, get_type_hints

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.arm import RobotArm
from cellcal.devices.arm_model import ArmModel
from cellcal.devices.base import BackendContext
from cellcal.devices.errors import DeviceTimeoutError, NotConnectedError
from cellcal.devices.pose import Pose
from cellcal.devices.registry import default_registry
from cellcal.devices.types import ArmStatus, DeviceInfo
from cellcal.sims.arm import SimArmConfig
from cellcal.sims.kinematics import rms_error
from cellcal.sims.world import world_from_context

#: Names of the sim arm's config keys, which every emulated arm's section accepts too.
SIM_ARM_KEYS = tuple(f.name for f in dataclasses.fields(SimArmConfig))


def sim_arm_settings(config: Any) -> dict[str, Any]:
    """The sim arm's keys of an emulated arm's ``config``, as a dict."""
    return {name: getattr(config, name) for name in SIM_ARM_KEYS}


def emulated_arm_config(backend: str, module: str, qualname: str, own_fields: list[tuple[str, Any, Any]], *,
                        sim_defaults: Mapping[str, Any] | None = None,
                        check: Callable[[Any], None] | None = None, doc: str = "") -> type[Any]:
    """The frozen ``Config`` dataclass of an emulated arm: the sim arm's fields, then ``own_fields``.

    Args:
        backend: Registry name, for messages.
        module: The module the class is defined in (the caller's ``__name__``).
        qualname: The class's qualified name (``EmulatedXArmArm.Config``).
        own_fields: ``(name, type, dataclasses.field(...))`` of the emulator's and driver's keys.
        sim_defaults: Defaults that replace the sim arm's for this arm class (UR-like limits).
        check: Extra validation of a built config (raises ConfigError); the sim part is
            always validated by building a :class:`SimArmConfig` from it.
        doc: The class docstring.

    Raises:
        RuntimeError: If one of ``own_fields`` has the name of a sim arm key.
    """
    hints = get_type_hints(SimArmConfig)
    defaults = dict(sim_defaults or {})
    sim_fields = [(f.name, hints[f.name], dataclasses.field(default=defaults.get(f.name, f.default),
                                                            metadata=f.metadata))
                  for f in dataclasses.fields(SimArmConfig)]
    clash = {name for name, _, _ in own_fields}.intersection(SIM_ARM_KEYS)
    if clash:  # pragma: no cover - guards a future change of the sim arm's config
        raise RuntimeError(f"{backend} config keys clash with the sim arm's: {sorted(clash)}")

    def post_init(self: Any) -> None:
        SimArmConfig(**sim_arm_settings(self))  # validates the sim part
        if check is not None:
            check(self)

    cls = dataclasses.make_dataclass("Config", [*sim_fields, *own_fields], frozen=True,
                                     namespace={"__post_init__": post_init, "__doc__": doc})
    cls.__module__ = module
    cls.__qualname__ = qualname
    return cls


class EmulatedArm(RobotArm):
    """Base of the ``*-emulated`` arms: an emulator, the real driver connected to it, calls forwarded.

    Subclasses set :attr:`driver_backend` (the registry name of the real driver), start
    their emulator in :meth:`_start_emulator` (returning the driver's section keys that
    reach it) and stop it in :meth:`_stop_emulator`. A move or stop is followed by
    :meth:`_after_motion` (e.g. to copy the emulated arm's pose into the shared world),
    whether it succeeded or not.

    Args:
        config: Validated ``Config``.
        context: Backend context; its shared sim world is the one the arm moves.

    Attributes:
        driver: The connected real driver (None until connected).
    """

    driver_backend = ""

    def __init__(self, config: Any, context: BackendContext | None = None):
        super().__init__()
        self.config = config
        self.context = context
        self.driver: RobotArm | None = None

    # ------------------------------------------------------------------ what subclasses provide
    @abstractmethod
    def _start_emulator(self, timeout: float) -> dict[str, Any]:
        """Start the emulator; the driver's section keys that reach it (and its own settings)."""

    @abstractmethod
    def _stop_emulator(self) -> None:
        """Stop the emulator; safe when it never started."""

    def _after_motion(self) -> None:
        """Called after every move and stop, successful or not."""

    def _arm_model(self) -> ArmModel:
        """The simulated arm's figures: its read-back repeatability and the RMS of the world's kinematic errors."""
        distance, angle = rms_error(world_from_context(self.context).arm_errors)
        return ArmModel(float(self.config.repeatability_m), distance, angle, "sim")

    def _start_allowance_s(self) -> float:
        """Seconds starting the emulator may take (0: it starts at once)."""
        return 0.0

    # ------------------------------------------------------------------ the shell
    @property
    def connect_timeout_s(self) -> float:
        """Starting the emulator's allowance plus the driver's connect timeout, s."""
        return self._start_allowance_s() + float(self.default_timeout_s)

    def _connect(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout  # the emulator's start and the driver's connect share it
        section = {"backend": self.driver_backend, **self._start_emulator(timeout)}
        self.driver = default_registry().create_arm(section, self.context)
        self.driver.default_motion_timeout_s = self.default_motion_timeout_s
        self._configure_driver(self.driver)
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise DeviceTimeoutError(f"arm backend '{self.backend_name}': its emulator took the whole connect "
                                     f"timeout of {timeout:g} s to start")
        self.driver.connect(remaining)

    def _configure_driver(self, driver: RobotArm) -> None:
        """Settings passed on to the driver before it connects (none by default)."""

    def _close(self) -> None:
        driver, self.driver = self.driver, None
        try:
            if driver is not None:
                driver.close()
        finally:
            self._stop_emulator()

    def _drv(self) -> RobotArm:
        if self.driver is None:
            raise NotConnectedError(f"{self.backend_name}: not connected")
        return self.driver

    def _info(self) -> DeviceInfo:
        inner = self._drv().info()
        return DeviceInfo(backend=self.backend_name, vendor=inner.vendor, model=f"{inner.model} (emulated)",
                          serial=inner.serial, firmware=inner.firmware, extra={**inner.extra, "emulated": True})

    def _get_pose(self, timeout: float) -> Pose:
        return self._drv().get_pose(timeout)

    def _move_linear(self, pose: Pose, speed: float, acceleration: float, timeout: float) -> None:
        try:
            self._drv().move_linear(pose, speed=speed, acceleration=acceleration, timeout=timeout)
        finally:
            self._after_motion()

    def _stop(self, timeout: float) -> None:
        try:
            self._drv().stop(timeout)
        finally:
            self._after_motion()

    def _joint_positions(self, timeout: float) -> NDArray[np.float64]:
        return self._drv().joint_positions(timeout)

    def _status(self, timeout: float) -> ArmStatus:
        return self._drv().status(timeout)

    def _clear_errors(self, timeout: float) -> None:
        self._drv().clear_errors(timeout)
