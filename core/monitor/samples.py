"""What the monitor compares: the plane seen in one frame, and the baseline it should match."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe import FullFrameResult, FullFrameSettings, check_gates, fit_full_frame
from cellcal.devices.errors import CalibrationError, ConfigError
from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame

__all__ = ["Baseline", "PlaneSample", "fit_plane_sample", "plane_sample"]


@dataclass(frozen=True)
class PlaneSample:
    """The measuring plane seen in one frame, camera (optical) frame.

    Attributes:
        timestamp: Frame time, seconds since the epoch.
        tilt_x_rad: Camera tilt about its x axis (:meth:`Plane.tilt_about_x_rad`), rad.
        tilt_y_rad: Camera tilt about its y axis (:meth:`Plane.tilt_about_y_rad`), rad.
        height_m: Distance from the optical centre to the plane along the optical axis, m.
    """

    timestamp: float
    tilt_x_rad: float
    tilt_y_rad: float
    height_m: float

    def __post_init__(self) -> None:
        values = (self.timestamp, self.tilt_x_rad, self.tilt_y_rad, self.height_m)
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
            raise CalibrationError(f"plane sample values must be finite numbers, got {values!r}")

    @classmethod
    def from_plane(cls, plane: Plane, timestamp: float) -> PlaneSample:
        """The sample of a plane given in the camera frame.

        Raises:
            CalibrationError: If the optical axis does not meet the plane in front of the camera.
        """
        return cls(float(timestamp), plane.tilt_about_x_rad(), plane.tilt_about_y_rad(),
                   plane.distance_along_optical_axis_m())


@dataclass(frozen=True)
class Baseline:
    """The plane as it should look from the camera (camera frame), and optionally its noise.

    Attributes:
        tilt_x_rad: Expected tilt about the camera's x axis, rad.
        tilt_y_rad: Expected tilt about the camera's y axis, rad.
        height_m: Expected height along the optical axis, m.
        tilt_noise_rad: Frame-to-frame 1-sigma of a tilt (per axis), rad; None if unknown.
        height_noise_m: Frame-to-frame 1-sigma of the height, m; None if unknown.
    """

    tilt_x_rad: float
    tilt_y_rad: float
    height_m: float
    tilt_noise_rad: float | None = None
    height_noise_m: float | None = None

    def __post_init__(self) -> None:
        for name in ("tilt_x_rad", "tilt_y_rad", "height_m", "tilt_noise_rad", "height_noise_m"):
            v = getattr(self, name)
            optional = "noise" in name
            if v is None and optional:
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise CalibrationError(f"baseline {name} must be a finite number, got {v!r}")
            if (optional or name == "height_m") and v < 0:
                raise CalibrationError(f"baseline {name} must be >= 0, got {v!r}")

    @property
    def has_noise(self) -> bool:
        """Whether both noise figures are known."""
        return self.tilt_noise_rad is not None and self.height_noise_m is not None

    @classmethod
    def from_plane(cls, plane_camera: Plane) -> Baseline:
        """The baseline of a plane given in the camera frame (no noise figures)."""
        s = PlaneSample.from_plane(plane_camera.oriented_toward_origin(), 0.0)
        return cls(s.tilt_x_rad, s.tilt_y_rad, s.height_m)

    @classmethod
    def from_plane_in_base(cls, plane_base: Plane, camera_pose: Pose) -> Baseline:
        """The baseline of a plane known in the robot base frame, seen from ``camera_pose``.

        Args:
            plane_base: The measuring plane, base frame.
            camera_pose: ``T_base_camera`` (e.g. the arm's flange pose @ the mount).
        """
        return cls.from_plane(plane_base.transformed(camera_pose.inv()))

    def to_dict(self) -> dict[str, float | None]:
        """JSON form (SI units)."""
        return {"tilt_x_rad": self.tilt_x_rad, "tilt_y_rad": self.tilt_y_rad, "height_m": self.height_m,
                "tilt_noise_rad": self.tilt_noise_rad, "height_noise_m": self.height_noise_m}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, source: str | None = None) -> Baseline:
        """Inverse of :meth:`to_dict`.

        Raises:
            ConfigError: Naming the missing or malformed key.
        """
        if not isinstance(data, Mapping):
            raise ConfigError(f"baseline must be a table, got {type(data).__name__}", source=source)
        kwargs: dict[str, Any] = {}
        for key in ("tilt_x_rad", "tilt_y_rad", "height_m", "tilt_noise_rad", "height_noise_m"):
            if key not in data:
                if key.endswith(("noise_rad", "noise_m")):
                    continue
                raise ConfigError("missing baseline value", source=source, key=key)
            kwargs[key] = data[key]
        try:
            return cls(**kwargs)
        except CalibrationError as exc:
            raise ConfigError(str(exc), source=source) from None


def plane_sample(frame: Frame, fit_settings: FullFrameSettings | None = None) -> PlaneSample:
    """Fit the measuring plane of one frame (:func:`fit_full_frame`) and return its tilt and height.

    Args:
        frame: A camera frame.
        fit_settings: The ``[full_frame]`` settings (fit and quality gates); None: defaults.

    Raises:
        CalibrationQualityError: If the fit fails a quality gate (too few valid pixels,
            too few inliers, residuals too large, poor coverage).
        CalibrationError: If no plane is found or the optical axis misses it.
    """
    return fit_plane_sample(frame, fit_settings)[0]


def fit_plane_sample(frame: Frame, fit_settings: FullFrameSettings | None = None
                     ) -> tuple[PlaneSample, FullFrameResult]:
    """As :func:`plane_sample`, also returning the fit itself (plane, inlier mask) for a viewer."""
    result = fit_full_frame(frame, fit_settings)
    check_gates(result)
    return PlaneSample(float(frame.timestamp), result.tilt_x_rad, result.tilt_y_rad, result.height_m), result
