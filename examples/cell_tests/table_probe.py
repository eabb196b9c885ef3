"""A user's cell code, the code the example tests test: how far the table is below the camera.

It knows only cellcal's device interfaces (``Camera3D``, ``RobotArm``), so the same function
runs on the real O3R + xArm and, in the tests, on the simulated cell.
"""

from __future__ import annotations

import numpy as np

from cellcal.devices import Camera3D, Pose, RobotArm
from cellcal.devices.errors import CellcalError, DeviceTimeoutError


class TableNotSeenError(CellcalError):
    """The camera delivered a frame with too few valid pixels in its centre."""


def table_distance_m(camera: Camera3D, *, attempts: int = 2, timeout_s: float = 1.0, window_px: int = 5,
                     min_valid: float = 0.5) -> float:
    """Median radial distance of the central ``window_px`` x ``window_px`` pixels, metres.

    A capture that times out is tried again, ``attempts`` times in all.

    Raises:
        DeviceTimeoutError: If every attempt timed out.
        TableNotSeenError: If fewer than ``min_valid`` of the window's pixels are valid.
    """
    for attempt in range(1, attempts + 1):
        try:
            frame = camera.capture(timeout_s)
            break
        except DeviceTimeoutError:
            if attempt == attempts:
                raise
    h, w = frame.distance.shape
    r0, c0 = h // 2 - window_px // 2, w // 2 - window_px // 2
    window = frame.distance[r0:r0 + window_px, c0:c0 + window_px]
    valid = frame.valid[r0:r0 + window_px, c0:c0 + window_px]
    if valid.mean() < min_valid:
        raise TableNotSeenError(f"only {valid.mean():.0%} of the central {window_px}x{window_px} pixels are valid")
    return float(np.median(window[valid]))


def lower_by(arm: RobotArm, drop_m: float, *, speed_m_s: float = 0.1, acceleration_m_s2: float = 1.0,
             timeout_s: float = 5.0) -> Pose:
    """Move the flange ``drop_m`` straight down (base frame) and return the pose read back after the move."""
    start = arm.get_pose()
    target = start.with_translation(start.translation - np.array([0.0, 0.0, drop_m]))
    arm.move_linear(target, speed=speed_m_s, acceleration=acceleration_m_s2, timeout=timeout_s)
    return arm.get_pose()
