"""The per-pose measurement: P1-P9 grids sampled from frames, each method applied.

Three methods, named as in the configuration:

``law_of_cosines``
    The paper's approach 1 on real 3D samples: triangle camera centre C, the on-axis
    point O (P5) and the point Ay (P8) on the plane; CO and CAy are measured radial
    distances, OAy their 3D separation. The same construction along x (P4) gives the
    tilt about y. Reported angle: the y construction, as in the paper's Table 3.
``plane_fit``
    The paper's approach 2 (least squares ``z = a x + b y + c`` over the nine points)
    on points placed with the camera's *own* intrinsics (distortion honoured: the
    frame's XYZ), with a first-order 1-sigma uncertainty on the angle.
``plane_fit_nominal``
    Approach 2 exactly as the paper built its points: measured radial distance R at
    each grid pixel, with (Theta, Phi) from the nominal constant angle-per-pixel model.
    Its error against the truth is the model's bias, reported rather than hidden.
``full_frame``
    Every valid pixel of the pose's frames, robust plane fit with 95 % intervals and
    quality gates (:mod:`cellcal.core.methods.fullframe`). Not tied to a perimeter: its row has
    ``perimeter_px = None``; :func:`measure_full_frame` also returns the full result.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from cellcal.core.geometry.planes import Plane, PlaneFit, fit_plane_ols
from cellcal.core.geometry.sampling import Sample, sample_points
from cellcal.core.methods.fullframe import FullFrameResult, FullFrameSettings, check_gates, fit_full_frame
from cellcal.core.methods.paper import error_pct, grid_phi_theta, grid_points, law_of_cosines_angle, plane_fit
from cellcal.devices.errors import CalibrationError
from cellcal.devices.geometry.camera_model import NominalFovModel
from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame, Intrinsics

#: The methods evaluated on the P1-P9 grid at every perimeter.
GRID_METHODS = ("law_of_cosines", "plane_fit", "plane_fit_nominal")
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


def _fold(angle: float) -> float:
    """Fold an angle between two lines into [0, pi/2]."""
    return min(angle, math.pi - angle)


def _law_of_cosines(samples: dict[str, Sample], perimeter: int) -> Measurement:
    o, ay, ax = samples["P5"], samples["P8"], samples["P4"]
    co = float(np.linalg.norm(o.xyz_m))

    def axis_angle(a: Sample, along: int) -> tuple[float, float]:
        ca = float(np.linalg.norm(a.xyz_m))
        oa = float(np.linalg.norm(a.xyz_m - o.xyz_m))
        if oa <= 0:
            raise CalibrationError(f"grid points coincide at perimeter {perimeter} px")
        angle = _fold(law_of_cosines_angle(co, ca, oa))
        slope = (a.xyz_m[2] - o.xyz_m[2]) / (a.xyz_m[along] - o.xyz_m[along])
        return angle, math.copysign(1.0, float(slope))

    angle_y, slope_y = axis_angle(ay, 1)
    angle_x, slope_x = axis_angle(ax, 0)
    # z falls along +y for a positive tilt about x, and rises along +x for a positive tilt about y
    tilt_x = -slope_y * (math.pi / 2 - angle_y)
    tilt_y = slope_x * (math.pi / 2 - angle_x)
    return Measurement("law_of_cosines", perimeter, angle_y, None, tilt_x, tilt_y, co, None)


def _plane_measurement(method: str, perimeter: int, fit: PlaneFit) -> Measurement:
    plane = fit.plane
    return Measurement(method, perimeter, plane.angle_to_optical_axis_rad(), fit.angle_to_optical_axis_sigma_rad(),
                       plane.tilt_about_x_rad(), plane.tilt_about_y_rad(), plane.distance_along_optical_axis_m(),
                       fit.rms_m, plane=plane)


def nominal_model(intrinsics: Intrinsics, fov_rad: tuple[float, float] | None = None) -> NominalFovModel:
    """The paper's angle-per-pixel model for a camera: the datasheet field of view if given,
    else the pinhole field of view of its intrinsics (distortion ignored, as in the paper)."""
    if fov_rad is None:
        fov_rad = (2 * math.atan(intrinsics.width / (2 * intrinsics.fx)),
                   2 * math.atan(intrinsics.height / (2 * intrinsics.fy)))
    return NominalFovModel(intrinsics.width, intrinsics.height, fov_rad[0], fov_rad[1])


def measure_frames(frames: Sequence[Frame], *, perimeters_px: Sequence[int], methods: Sequence[str],
                   window_px: int = 3, expected: ExpectedGeometry | None = None,
                   nominal_fov_rad: tuple[float, float] | None = None) -> list[Measurement]:
    """Run every method at every perimeter on the frames of one pose.

    Args:
        frames: Frames captured at the pose (their samples are pooled).
        perimeters_px: Grid half-sizes, pixels.
        methods: Method names (see module docstring).
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
    intr = frames[0].intrinsics
    model = nominal_model(intr, nominal_fov_rad) if "plane_fit_nominal" in methods else None
    methods = [m for m in methods if m != FULL_FRAME]
    out: list[Measurement] = []
    for p in perimeters_px if methods else ():
        grid = grid_points(p, width_px=intr.width, height_px=intr.height, cx=intr.cx, cy=intr.cy)
        uv = np.array([[intr.cx + g.dx_px, intr.cy + g.dy_px] for g in grid])
        samples = dict(zip((g.name for g in grid), sample_points(frames, uv, window_px), strict=True))
        for method in methods:
            if method == "law_of_cosines":
                m = _law_of_cosines(samples, p)
            elif method == "plane_fit":
                m = _plane_measurement(method, p, fit_plane_ols(np.array([samples[g.name].xyz_m for g in grid])))
            elif method == "plane_fit_nominal":
                assert model is not None
                phi, theta = grid_phi_theta(grid, model)
                r = np.array([samples[g.name].distance_m for g in grid])
                m = _plane_measurement(method, p, plane_fit(r, phi, theta))
            else:
                raise CalibrationError(f"unknown method '{method}'")
            if expected is not None:
                m = dataclasses.replace(m, error_pct=error_pct(m.angle_rad, expected.angle_rad))
            out.append(m)
    return out


def measure_full_frame(frames: Sequence[Frame], settings: FullFrameSettings | None = None, *,
                       expected: ExpectedGeometry | None = None, check: bool = True
                       ) -> tuple[Measurement, FullFrameResult]:
    """The ``full_frame`` method on the frames of one pose.

    Args:
        frames: Frames captured at the pose (pooled).
        settings: The ``[full_frame]`` settings; None: defaults.
        expected: Expected geometry, to compute the row's error.
        check: Raise if a quality gate fails.

    Returns:
        The summary row (``perimeter_px`` None) and the full result.

    Raises:
        CalibrationQualityError: With ``check``, naming the first failed gate.
        CalibrationError: No frames or no plane defined.
    """
    if not frames:
        raise CalibrationError("no frames captured")
    res = fit_full_frame(list(frames), settings)
    if check:
        check_gates(res, settings)
    m = Measurement(FULL_FRAME, None, res.angle_rad, res.angle_sigma_rad, res.tilt_x_rad, res.tilt_y_rad,
                    res.height_m, res.residual_rms_m, plane=res.plane)
    if expected is not None:
        m = dataclasses.replace(m, error_pct=error_pct(m.angle_rad, expected.angle_rad))
    return m, res


def full_frame_document(result: FullFrameResult, camera_in_base: Pose,
                        expected: ExpectedGeometry | None = None) -> dict[str, Any]:
    """The pose record's ``full_frame`` section (JSON form, degrees and metres).

    :meth:`FullFrameResult.to_dict` plus ``plane_base`` (the plane in the base frame via
    ``camera_in_base = T_base_flange @ T_flange_camera``) and, with an expected geometry,
    ``error`` (estimate minus expected) and ``expected_in_ci`` (whether each interval
    holds the expected value). The expected geometry comes from the arm's *reported* pose:
    its read-back error (e.g. 0.1 mm on an xArm) can exceed the height interval (~0.01 mm
    on the sim), so ``expected_in_ci["height_m"]`` is often False through no fault of the
    camera; the angles are not affected by a translation error.
    """
    out = result.to_dict()
    out["plane_base"] = result.plane.transformed(camera_in_base).to_dict()
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
