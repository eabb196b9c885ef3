"""Backend ``ur-emulated``: the real ``ur`` driver (ur_rtde) talking to the UR emulator on a free 127.0.0.N.

The emulator runs as a child process (ur_rtde's constructors hold the GIL, see
:mod:`.process`) with its own copy of the simulated arm; after every call that can
move the arm, the true flange pose and the simulated time of the motion are copied
into the shared sim world, so a ``sim`` camera sees what it would see in a pure sim.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

from cellcal.devices.base import BackendContext
from cellcal.devices.geometry.vendor_poses import pose_from_ur, pose_to_ur
from cellcal.sims.emulated import EmulatedArm, emulated_arm_config, sim_arm_settings
from cellcal.sims.world import SimWorld, world_from_context

from .emulator import UR_LIKE
from .process import UREmulatorProcess

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


class EmulatedURArm(EmulatedArm):
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
    driver_backend = "ur"
    Config = emulated_arm_config(
        backend_name, __name__, "EmulatedURArm.Config", _OWN_FIELDS, sim_defaults=UR_LIKE,
        doc="The ``[arm]`` section for ``backend = \"ur-emulated\"``: the sim arm's keys (UR5e-like defaults) "
            "plus the driver's and the emulator's.")

    def __init__(self, config: Any = None, context: BackendContext | None = None):
        super().__init__(config if config is not None else EmulatedURArm.Config(), context)
        self.world: SimWorld = world_from_context(context)
        self.emulator: UREmulatorProcess | None = None
        self._sim_elapsed = 0.0
        #: Fault injection (tests): called with the started emulator before the driver connects.
        self.on_emulator_started: Callable[[UREmulatorProcess], None] | None = None

    @property
    def host(self) -> str:
        """The emulator's address ("" when not connected)."""
        return self.emulator.host if self.emulator is not None else ""

    def _start_allowance_s(self) -> float:
        """The emulator process's start allowance (``start_timeout_s``)."""
        return float(self.config.start_timeout_s)

    def _start_emulator(self, timeout: float) -> dict[str, Any]:
        cfg = self.config
        emulator = UREmulatorProcess(
            "auto", arm_config=sim_arm_settings(cfg),
            flange_pose=[float(v) for v in pose_to_ur(self.world.arm.flange_pose())],
            unlock_delay_s=cfg.unlock_delay_s, seed=self.world.seed)
        self.emulator = emulator
        emulator.start(min(cfg.start_timeout_s, timeout))  # within the connect's timeout
        self._sim_elapsed = 0.0
        if self.on_emulator_started is not None:
            self.on_emulator_started(emulator)
        return {"host": emulator.host, "timeout_s": cfg.timeout_s, "stale_after_s": cfg.stale_after_s,
                "poll_interval_s": cfg.poll_interval_s}

    def _stop_emulator(self) -> None:
        emulator, self.emulator = self.emulator, None
        if emulator is not None:
            emulator.close()

    def _after_motion(self) -> None:
        """Copy the emulated arm's true flange pose, and the simulated time its motions took, into the world."""
        if self.emulator is None:
            return
        snap = self.emulator.snapshot()
        self.world.arm.set_flange_pose(pose_from_ur(snap["flange"]))
        elapsed = float(snap["sim_elapsed_s"])
        self.world.clock.advance(elapsed - self._sim_elapsed)
        self._sim_elapsed = elapsed
