"""What an arm's reported pose is worth: :class:`ArmModel` (repeatability and absolute accuracy; issue #39).

Arms are specified by repeatability (ISO 9283 RP, hundredths of a millimetre) but an uncalibrated
arm's *absolute* accuracy (ISO 9283 AP/AO) is 0.2–2 mm and up to a few mrad: the pose it reports
errs smoothly with the pose (joint zero offsets, link lengths), the same way every time it returns.
Each backend states its vendor's figures (:meth:`cellcal.devices.arm.RobotArm.arm_model`);
``[arm.model]`` overrides them. Every interval that takes the arm's poses as known carries them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from .config import parse_section

__all__ = ["UNSTATED_ARM_MODEL", "ArmModel"]


@dataclass(frozen=True)
class ArmModel:
    """An arm's stated pose errors (the ``[arm.model]`` table), SI units.

    Attributes:
        repeatability_m: Position repeatability (ISO 9283 RP), m: the random scatter of returns to one pose.
        accuracy_m: Absolute position accuracy (ISO 9283 AP), m: how far a reported position may lie
            from the true one, smoothly varying over the workspace.
        accuracy_rad: Absolute orientation accuracy (ISO 9283 AO), rad.
        source: Who stated it (``backend``, ``config``, ``sim``, ``unstated``), for reports.
    """

    repeatability_m: float = field(default=25e-6, metadata={"ge": 0.0, "le": 0.1})
    accuracy_m: float = field(default=1e-3, metadata={"ge": 0.0, "le": 0.1})
    accuracy_rad: float = field(default=2e-3, metadata={"ge": 0.0, "le": 0.2})
    source: str = "unstated"

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None, *, where: str = "arm.model",
                  source: str | None = None, base: ArmModel | None = None) -> ArmModel:
        """Parse an ``[arm.model]`` table over ``base`` (keys not given keep ``base``'s values).

        Raises:
            ConfigError: Naming the key and what was wrong (one line).
        """
        merged: dict[str, Any] = {} if base is None else {
            "repeatability_m": base.repeatability_m, "accuracy_m": base.accuracy_m,
            "accuracy_rad": base.accuracy_rad, "source": base.source}
        merged.update(dict(data or {}))
        if data:
            merged["source"] = "config"
        return parse_section(cls, merged, where=where, source=source)

    def to_dict(self) -> dict[str, Any]:
        """JSON form (SI units)."""
        return {"repeatability_m": self.repeatability_m, "accuracy_m": self.accuracy_m,
                "accuracy_rad": self.accuracy_rad, "source": self.source}

    def describe(self) -> str:
        """One line for humans (mm, degrees)."""
        import math

        return (f"repeatability {self.repeatability_m * 1000:.3g} mm, accuracy {self.accuracy_m * 1000:.3g} mm "
                f"and {math.degrees(self.accuracy_rad):.3g} deg ({self.source})")


#: What an arm that states nothing is taken to be: an uncalibrated industrial arm (1 mm, 2 mrad).
UNSTATED_ARM_MODEL = ArmModel()
