"""Bounds on what a UR controller reports: poses within the arm's reach, rotations, modes from the documented sets."""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.errors import ProtocolError

__all__ = ["REACH_MARGIN_M", "UR_REACH_M", "checked_mode", "checked_tcp", "reach_m"]

#: Reach of each UR model (Universal Robots' data sheets: the working radius from the base
#: joint's axis), metres, by the model's number (UR5, UR5e and UR5 CB3 alike).
UR_REACH_M = {3: 0.50, 5: 0.85, 7: 0.85, 8: 1.75, 10: 1.30, 12: 1.30, 15: 1.30, 16: 0.90, 18: 1.75, 20: 1.75,
              30: 1.30}
#: Added to the reach: the flange sits above the base by up to ~0.2 m (shoulder height) on top of
#: the horizontal reach, and the reported TCP may carry a small tool offset.
REACH_MARGIN_M = 0.35
#: A rotation vector's angle is at most pi (UR reports [0, pi]); 2 pi bounds any wrapped form.
MAX_ROTVEC_RAD = 2.0 * math.pi + 1e-9


def reach_m(model: str) -> float:
    """The reach of a model named as the dashboard names it (``"UR5e"``, ``"UR10"``); the largest known if unknown."""
    match = re.search(r"UR\s*(\d+)", model or "", re.IGNORECASE)
    return UR_REACH_M.get(int(match.group(1)), max(UR_REACH_M.values())) if match else max(UR_REACH_M.values())


def checked_tcp(xyz_rotvec: NDArray[np.float64], model: str, what: str) -> NDArray[np.float64]:
    """A finite ``[x, y, z, rx, ry, rz]`` (m, rad) checked to be a pose the arm can have.

    Raises:
        ProtocolError: If the position is beyond the model's reach plus :data:`REACH_MARGIN_M`,
            or the rotation vector's angle beyond 2 pi: a corrupt package, not a pose.
    """
    distance = math.hypot(*map(float, xyz_rotvec[:3]))  # from the base frame's origin, m (scaled: no overflow)
    limit = reach_m(model) + REACH_MARGIN_M
    if distance > limit:
        raise ProtocolError(f"ur: {what} reported a position {distance:.4g} m from the base, beyond the "
                            f"{limit:.3g} m a {model or 'UR arm'} can reach")
    angle = math.hypot(*map(float, xyz_rotvec[3:]))  # rotation angle, rad
    if angle > MAX_ROTVEC_RAD:
        raise ProtocolError(f"ur: {what} reported a rotation vector of {angle:.4g} rad, not a rotation")
    return xyz_rotvec


def checked_mode(value: Any, table: dict[int, str], what: str) -> int:
    """A mode or state code the controller reported, checked against its documented set.

    Raises:
        ProtocolError: If it is not an integer of ``table`` (e.g. a safety mode of 949222551).
    """
    try:
        code = int(value)
    except (TypeError, ValueError, OverflowError):
        raise ProtocolError(f"ur: {what} reported {value!r}, not a code") from None
    if code != value or code not in table:
        raise ProtocolError(f"ur: {what} reported {value!r}, not one of the documented codes "
                            f"{min(table)}..{max(table)}")
    return code
