"""The ``acme-r1`` backend: the ACME R1 arm through ACME's client library, as a cellcal ``RobotArm``.

What an arm backend does, in the order docs/extending.md ("An arm backend") walks through it:

1. A frozen ``Config`` dataclass: the keys of the ``[arm]`` table, ranges in field metadata.
2. The hooks ``_connect``, ``_close``, ``_info`` (every device) and ``_get_pose``,
   ``_move_linear``, ``_stop``, ``_joint_positions``, ``_status``, ``_clear_errors``.
   ``RobotArm``'s public methods check the life cycle, the timeouts, the speed and
   acceleration, and after ``_move_linear`` returns they read the pose back and check the
   arm arrived (stopping it and raising ``MotionError`` if not): the hooks only talk to
   the controller.
3. Units and frames: the R1's library speaks millimetres and degrees (fixed-axis roll,
   pitch, yaw); the backend hands out flange poses in the base frame in metres with
   scipy rotations, joint angles in radians.
4. Errors and timeouts: a move that does not finish within its timeout is stopped and is a
   ``DeviceTimeoutError``; the controller's refusals are ``VendorError`` with its code.
5. The SDK is imported in ``_connect`` only (here :mod:`acme_cellcal.r1_controller`
   stands in for it), so ``cellcal devices`` and configurations that do not use the arm
   never load it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from cellcal.devices import (
    ArmStatus,
    BackendContext,
    DeviceInfo,
    DeviceTimeoutError,
    Pose,
    RobotArm,
    VendorError,
)
from numpy.typing import NDArray


@dataclass(frozen=True)
class AcmeR1Config:
    """``[arm]`` table for ``backend = "acme-r1"``."""

    timeout_s: float = field(default=2.0, metadata={"gt": 0.0, "le": 60.0, "doc": "default I/O timeout, s"})
    poll_interval_s: float = field(default=0.005, metadata={"gt": 0.0, "le": 1.0,
                                                            "doc": "how often a running move is polled, s"})
    time_scale: float = field(default=1.0, metadata={
        "ge": 0.0, "le": 1.0, "doc": "the stand-in controller only: wall seconds per controller second"})


class AcmeR1Arm(RobotArm):
    """ACME R1 six-axis arm over ACME's client library.

    Args:
        config: The validated ``[arm]`` table.
        context: Where the config came from (unused by a real arm).
    """

    backend_name: ClassVar[str] = "acme-r1"
    Config: ClassVar[type[AcmeR1Config]] = AcmeR1Config

    def __init__(self, config: AcmeR1Config, context: BackendContext | None = None):
        super().__init__()
        self.config = config
        self.context = context or BackendContext()
        self.default_timeout_s = config.timeout_s
        self._r1: Any = None
        self._sdk: Any = None

    # ------------------------------------------------------------ life cycle
    def _connect(self, timeout: float) -> None:
        from . import r1_controller  # the vendor SDK: imported only when the arm connects

        self._sdk = r1_controller
        self._r1 = r1_controller.R1Controller(time_scale=self.config.time_scale)

    def _close(self) -> None:
        self._r1 = None

    def _info(self) -> DeviceInfo:
        r1 = self._r1
        return DeviceInfo(backend=self.backend_name, vendor="ACME", model=r1.model, serial=r1.serial,
                          firmware=r1.firmware)

    # ------------------------------------------------------------ reads (mm, degrees -> m, radians)
    def _get_pose(self, timeout: float) -> Pose:
        x, y, z, roll, pitch, yaw = self._r1.get_position()
        return Pose.from_xyz_rpy(np.array([x, y, z]) / 1000.0, np.radians([roll, pitch, yaw]))

    def _joint_positions(self, timeout: float) -> NDArray[np.float64]:
        return np.radians(np.asarray(self._r1.get_joints(), dtype=np.float64))

    def _status(self, timeout: float) -> ArmStatus:
        code = int(self._r1.error_code)
        message = "" if code == 0 else f"R1 error {code}"
        return ArmStatus(error_code=code, message=message, can_move=code == 0)

    # ------------------------------------------------------------ commands
    def _move_linear(self, pose: Pose, speed: float, acceleration: float, timeout: float) -> None:
        xyz_rpy = pose.as_xyz_rpy()
        target = [*(1000.0 * xyz_rpy[:3]).tolist(), *np.degrees(xyz_rpy[3:]).tolist()]
        try:
            self._r1.move_l(target, speed * 1000.0, acceleration * 1000.0)
        except self._sdk.R1Error as exc:
            raise VendorError(self.backend_name, exc.code, str(exc)) from None
        deadline = time.monotonic() + timeout
        while self._r1.moving():
            if time.monotonic() >= deadline:
                self._r1.halt()
                raise DeviceTimeoutError(f"{self.backend_name}: the move did not finish within {timeout:g} s; "
                                         "the arm was told to stop")
            time.sleep(min(self.config.poll_interval_s, max(0.0, deadline - time.monotonic())))

    def _stop(self, timeout: float) -> None:
        self._r1.halt()

    def _clear_errors(self, timeout: float) -> None:
        self._r1.clear_error()
