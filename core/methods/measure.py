"""The per-pose measurement: which methods run on which frames, and their result rows.

The paper's grid methods (``law_of_cosines``, ``plane_fit``, ``plane_fit_nominal``) are
computed in :mod:`cellcal.core.methods.paper`, ``full_frame`` in
:mod:`cellcal.core.methods.fullframe`; this module turns them into :class:`Measurement`
rows, compares them with the :class:`ExpectedGeometry` and builds the full-frame document.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe import FullFrameResult, FullFrameSettings, check_gates, fit_full_frame
from cellcal.core.methods.fullframe.expected import ExpectedPlane
from cellcal.core.methods.paper import GridEstimate, error_pct, grid_estimates, nominal_model
from cellcal.devices.errors import CalibrationError
from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame

#: The whole-frame method (one estimate per pose, no perimeter).
FULL_FRAME = "full_frame"


@dataclass(frozen=True)
class ExpectedGeometry:
    """The plane as it should be seen from the camera, from the arm pose and reference.

    Attributes:
        plane_cam: The reference plane in the camera frame (normal toward the camera).
        angle_rad: Angle between the plane and the optical axis, rad.
        tilt_x_rad: Camera tilt about its x axis (see :meth:`Plane.tilt_about_x_rad`).
        tilt_y_rad: Camera tilt about its y axis.
        height_m: Distance from the optical centre to the plane along the optical axis.
        distance_normal_m: Perpendicular distance from the optical centre to the plane.
    """

    plane_cam: Plane
    angle_rad: float
    tilt_x_rad: float
    tilt_y_rad: float
    height_m: float
    distance_normal_m: float

    def to_dict(self) -> dict[str, Any]:
        """JSON form (degrees and metres, for reports)."""
        return {
            "angle_deg": math.degrees(self.angle_rad),
            "tilt_x_deg": math.degrees(self.tilt_x_rad),
            "tilt_y_deg": math.degrees(self.tilt_y_rad),
            "height_m": self.height_m,
            "distance_normal_m": self.distance_normal_m,
            "plane_cam": self.plane_cam.to_dict(),
        }


def expected_geometry(camera_in_base: Pose, plane_point_m: ArrayLike, plane_normal: ArrayLike) -> ExpectedGeometry:
    """Expected plane geometry in the camera frame.

    Args:
        camera_in_base: Camera pose in the base frame (``T_base_camera``).
        plane_point_m: A point of the reference plane, base frame, metres.
        plane_normal: The reference plane's normal, base frame.
    """
    plane = Plane.from_point_normal(plane_point_m, plane_normal).transformed(camera_in_base.inv())
    plane = plane.oriented_toward_origin()
    return ExpectedGeometry(plane, plane.angle_to_optical_axis_rad(), plane.tilt_about_x_rad(),
                            plane.tilt_about_y_rad(), plane.distance_along_optical_axis_m(),
                            plane.distance_along_normal_m())


@dataclass(frozen=True)
class Measurement:
    """One method's estimate at one perimeter.

    Attributes:
        method: Method name.
        perimeter_px: Half-size of the P1-P9 square, pixels; None for ``full_frame``.
        angle_rad: Estimated angle between plane and optical axis, rad.
        angle_sigma_rad: 1-sigma uncertainty of ``angle_rad`` (None if not available).
        tilt_x_rad: Estimated camera tilt about x, rad.
        tilt_y_rad: Estimated camera tilt about y, rad.
        height_m: Estimated distance to the plane along the optical axis, metres.
        residual_rms_m: RMS residual of the plane fit (None for law of cosines), metres.
        error_pct: ``|angle - expected| / expected * 100`` (None without a reference).
        plane: The fitted plane in the camera frame (plane methods), else None.
    """

    method: str
    perimeter_px: int | None
    angle_rad: float
    angle_sigma_rad: float | None
    tilt_x_rad: float
    tilt_y_rad: float
    height_m: float
    residual_rms_m: float | None
    error_pct: float | None = None
    plane: Plane | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON form (degrees, metres, percent)."""
        return {
            "method": self.method,
            "perimeter_px": self.perimeter_px,
            "angle_deg": math.degrees(self.angle_rad),
            "angle_sigma_deg": None if self.angle_sigma_rad is None else math.degrees(self.angle_sigma_rad),
            "error_pct": self.error_pct,
            "tilt_x_deg": math.degrees(self.tilt_x_rad),
            "tilt_y_deg": math.degrees(self.tilt_y_rad),
            "height_m": self.height_m,
            "residual_rms_m": self.residual_rms_m,
            "plane_cam": None if self.plane is None else self.plane.to_dict(),
        }


def _with_error(m: Measurement, expected: ExpectedGeometry | None) -> Measurement:
    """The row with its ``error_pct`` against the expected angle (unchanged without one)."""
    if expected is None:
        return m
    return dataclasses.replace(m, error_pct=error_pct(m.angle_rad, expected.angle_rad))


def _grid_row(method: str, perimeter_px: int, est: GridEstimate) -> Measurement:
    """A grid method's estimate as a :class:`Measurement` row."""
    return Measurement(method, perimeter_px, est.angle_rad, est.angle_sigma_rad, est.tilt_x_rad, est.tilt_y_rad,
                       est.height_m, est.residual_rms_m, plane=est.plane)


def measure_frames(frames: Sequence[Frame], *, perimeters_px: Sequence[int], methods: Sequence[str],
                   window_px: int = 3, expected: ExpectedGeometry | None = None,
                   nominal_fov_rad: tuple[float, float] | None = None) -> list[Measurement]:
    """Run every method at every perimeter on the frames of one pose.

    Args:
        frames: Frames captured at the pose (their samples are pooled).
        perimeters_px: Grid half-sizes, pixels.
        methods: Method names (:data:`~cellcal.core.methods.grid.GRID_METHODS`, ``full_frame``).
        window_px: Odd sampling window, pixels.
        expected: Expected geometry, to compute each estimate's error.
        nominal_fov_rad: Datasheet field of view (x, y), rad, for ``plane_fit_nominal``.

    ``full_frame`` in ``methods`` is skipped here (see :func:`measure_full_frame`).

    Raises:
        CalibrationError: A perimeter outside the image, too few valid pixels at a grid
            point, or degenerate geometry.
    """
    if not frames:
        raise CalibrationError("no frames captured")
    model = nominal_model(frames[0].intrinsics, nominal_fov_rad) if "plane_fit_nominal" in methods else None
    grid_methods = [m for m in methods if m != FULL_FRAME]
    out: list[Measurement] = []
    for p in perimeters_px if grid_methods else ():
        estimates = grid_estimates(frames, p, grid_methods, window_px=window_px, model=model)
        out += [_with_error(_grid_row(method, p, est), expected) for method, est in estimates]
    return out


def measure_full_frame(frames: Sequence[Frame], settings: FullFrameSettings | None = None, *,
                       expected: ExpectedGeometry | None = None, check: bool = True,
                       region: NDArray[np.bool_] | None = None, expected_plane: ExpectedPlane | None = None,
                       ) -> tuple[Measurement, FullFrameResult]:
    """The ``full_frame`` method on the frames of one pose.

    Args:
        frames: Frames captured at the pose (pooled).
        settings: The ``[full_frame]`` settings; None: defaults.
        expected: Expected geometry, to compute the row's error.
        check: Raise if a quality gate fails.
        region: Region of interest, (H, W) bool mask of the frames' pixels: the fit and its
            gates see only these pixels; None: the whole image.
        expected_plane: The plane to look for (camera frame) and how far the answer may be
            from it (gate ``expected_plane``); None: the whole image decides.

    Returns:
        The summary row (``perimeter_px`` None) and the full result.

    Raises:
        CalibrationQualityError: With ``check``, naming the first failed gate.
        CalibrationError: No frames or no plane defined.
    """
    if not frames:
        raise CalibrationError("no frames captured")
    res = fit_full_frame(list(frames), settings, region=region, expected=expected_plane)
    if check:
        check_gates(res, settings)
    m = Measurement(FULL_FRAME, None, res.angle_rad, res.angle_sigma_rad, res.tilt_x_rad, res.tilt_y_rad,
                    res.height_m, res.residual_rms_m, plane=res.plane)
    return _with_error(m, expected), res


def expected_plane_document(expected_plane: ExpectedPlane | None, plane: Plane) -> dict[str, Any] | None:
    """The ``expected_plane`` the fit searched near and how far the fitted ``plane`` is from it (JSON, rad, m).

    Keys: ``plane_cam`` (camera frame), ``angle_tolerance_rad``, ``offset_tolerance_m``,
    ``departure_angle_rad`` / ``departure_offset_m`` of the fitted plane and ``accepted``
    (within both tolerances); None without an expected plane.
    """
    if expected_plane is None:
        return None
    angle_rad, offset_m = expected_plane.departure(plane)
    return {
        "plane_cam": expected_plane.plane.to_dict(),
        "angle_tolerance_rad": expected_plane.angle_tolerance_rad,
        "offset_tolerance_m": expected_plane.offset_tolerance_m,
        "departure_angle_rad": angle_rad,
        "departure_offset_m": offset_m,
        "accepted": expected_plane.accepts(plane),
    }


def full_frame_document(result: FullFrameResult, camera_in_base: Pose,
                        expected: ExpectedGeometry | None = None, *,
                        expected_plane: ExpectedPlane | None = None) -> dict[str, Any]:
    """The pose record's ``full_frame`` section (JSON form, degrees and metres).

    :meth:`FullFrameResult.to_dict` plus ``plane_base`` (the plane in the base frame via
    ``camera_in_base = T_base_flange @ T_flange_camera``), ``expected_plane``
    (:func:`expected_plane_document`, radians and metres; None without a search) and, with
    an expected geometry, ``error`` (estimate minus expected) and ``expected_in_ci``
    (whether each interval holds the expected value). The expected geometry comes from the arm's *reported* pose:
    its read-back error (e.g. 0.1 mm on an xArm) can exceed the height interval (~0.01 mm
    on the sim), so ``expected_in_ci["height_m"]`` is often False through no fault of the
    camera; the angles are not affected by a translation error.
    """
    out = result.to_dict()
    out["normal_offset_covariance"] = result.normal_offset_covariance.tolist()  # for the hand-eye fit's weights
    out["plane_base"] = result.plane.transformed(camera_in_base).to_dict()
    out["expected_plane"] = expected_plane_document(expected_plane, result.plane)
    if expected is not None:
        pairs = {
            "angle_deg": (result.angle_rad, expected.angle_rad, result.angle_ci_rad, True),
            "tilt_x_deg": (result.tilt_x_rad, expected.tilt_x_rad, result.tilt_x_ci_rad, True),
            "tilt_y_deg": (result.tilt_y_rad, expected.tilt_y_rad, result.tilt_y_ci_rad, True),
            "height_m": (result.height_m, expected.height_m, result.height_ci_m, False),
        }
        out["error"] = {k: (math.degrees(v - e) if deg else v - e) for k, (v, e, _, deg) in pairs.items()}
        out["expected_in_ci"] = {k: bool(ci[0] <= e <= ci[1]) for k, (_, e, ci, _) in pairs.items()}
    return out
