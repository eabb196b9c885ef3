"""What the calibrator measured at one plan pose (:class:`PoseRecord`), and its JSON form.

The record of a pose: the commanded and reported flange poses, the camera pose, the
expected geometry (with a reference plane), every measurement, the step timings and the
full-frame section. :meth:`PoseRecord.to_dict` is the pose's entry in the result document
and the resume journal; :meth:`PoseRecord.from_dict` reads it back (angles through degrees).
Poses in the base frame, metres, radians.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.measure import ExpectedGeometry, Measurement
from cellcal.devices.errors import CalibrationError
from cellcal.devices.pose import Pose
from cellcal.devices.types import Intrinsics

__all__ = ["PoseRecord"]


@dataclass
class PoseRecord:
    """Everything measured at one plan pose.

    Attributes:
        index: 0-based index in the plan.
        commanded: Commanded flange pose, base frame.
        reported: Flange pose read back from the arm after the move, base frame.
        camera: Camera pose in the base frame (``reported @ mount``).
        expected: Geometry expected from the reference plane, or None without one.
        measurements: One per perimeter x grid method, plus one ``full_frame`` row.
        timings_s: Wall time of the move, settle, capture and compute steps, seconds
            (``compute_full_frame``: the part of ``compute`` spent on the full-frame fit).
        intrinsics: The lens model the frames were taken with.
        full_frame: The ``full_frame`` section (:func:`full_frame_document`), or None when
            the method is not run.
    """

    index: int
    commanded: Pose
    reported: Pose
    camera: Pose
    expected: ExpectedGeometry | None
    measurements: list[Measurement]
    timings_s: dict[str, float] = field(default_factory=dict)
    intrinsics: Intrinsics | None = None
    full_frame: dict[str, Any] | None = None

    def rows(self) -> list[dict[str, Any]]:
        """Flat rows (one per measurement) for the summary and the table."""
        out = []
        for m in self.measurements:
            row = {"pose_index": self.index, **m.to_dict()}
            if self.expected is not None:
                row["expected_angle_deg"] = float(np.degrees(self.expected.angle_rad))
            out.append(row)
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {
            "index": self.index,
            "commanded_flange_pose": self.commanded.to_dict(),
            "reported_flange_pose": self.reported.to_dict(),
            "camera_pose": self.camera.to_dict(),
            "expected": None if self.expected is None else self.expected.to_dict(),
            "measurements": self.rows(),
            "timings_s": dict(self.timings_s),
            "camera_intrinsics": None if self.intrinsics is None else self.intrinsics.to_dict(),
            "full_frame": self.full_frame,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> PoseRecord:
        """Rebuild a record from :meth:`to_dict`'s output (a result document or the resume journal).

        Angles come back through degrees, so values may differ from the original in the
        last bit; keys this version does not know are ignored.

        Raises:
            CalibrationError: If a required field is missing or malformed.
        """
        try:
            exp = data.get("expected")
            expected = None
            if exp is not None:
                pc = exp["plane_cam"]
                expected = ExpectedGeometry(Plane.from_dict(pc),
                                            math.radians(exp["angle_deg"]), math.radians(exp["tilt_x_deg"]),
                                            math.radians(exp["tilt_y_deg"]), float(exp["height_m"]),
                                            float(exp["distance_normal_m"]))
            measurements = []
            for m in data["measurements"]:
                sigma = m.get("angle_sigma_deg")
                pc = m.get("plane_cam")
                measurements.append(Measurement(
                    method=str(m["method"]),
                    perimeter_px=None if m["perimeter_px"] is None else int(m["perimeter_px"]),
                    angle_rad=math.radians(m["angle_deg"]),
                    angle_sigma_rad=None if sigma is None else math.radians(sigma),
                    tilt_x_rad=math.radians(m["tilt_x_deg"]), tilt_y_rad=math.radians(m["tilt_y_deg"]),
                    height_m=float(m["height_m"]), residual_rms_m=m.get("residual_rms_m"),
                    error_pct=m.get("error_pct"),
                    plane=None if pc is None else Plane.from_dict(pc)))
            intr = data.get("camera_intrinsics")
            ff = data.get("full_frame")
            return cls(int(data["index"]), Pose.from_dict(data["commanded_flange_pose"]),
                       Pose.from_dict(data["reported_flange_pose"]), Pose.from_dict(data["camera_pose"]),
                       expected, measurements, {k: float(v) for k, v in dict(data.get("timings_s") or {}).items()},
                       None if intr is None else Intrinsics(**intr), None if ff is None else dict(ff))
        except (KeyError, TypeError, ValueError) as exc:
            raise CalibrationError(f"malformed pose record: {type(exc).__name__}: {exc}") from None
