"""The paper's two tilt measurements on the P1–P9 grid (Parpală et al., Appl. Sci. 2024, 14, 8687).

Approach 1: the law of cosines on camera centre C, on-axis point O = P5 and Ay = P8.
Approach 2: the least-squares plane ``Z = a X + b Y + c`` through the nine points.
Both run on a published table (:func:`paper_methods`) or on depth frames
(:func:`grid_estimates`); SI units throughout. The grid itself (its points, what fits an
image, its samples) is :mod:`cellcal.core.methods.grid`. See ``../shared/spec/paper-method.md``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellcal.core.geometry.planes import Plane, PlaneFit, fit_plane_ols
from cellcal.core.geometry.sampling import Sample
from cellcal.core.methods.grid import GRID_NAMES, GridPoint, camera_grid, grid_phi_theta, grid_points, sample_grid
from cellcal.devices.errors import CalibrationError
from cellcal.devices.geometry.camera_model import NominalFovModel
from cellcal.devices.types import Frame, Intrinsics

FloatArray = NDArray[np.float64]

__all__ = [
    "GridEstimate",
    "PaperResult",
    "error_pct",
    "grid_estimates",
    "law_of_cosines_angle",
    "law_of_cosines_estimate",
    "nominal_model",
    "paper_methods",
    "plane_fit",
    "plane_fit_angle",
    "plane_fit_estimate",
    "spherical_to_cartesian",
]


def spherical_to_cartesian(r_m: ArrayLike, theta_rad: ArrayLike, phi_rad: ArrayLike) -> FloatArray:
    """Camera-frame points from spherical coordinates, shape (N, 3), metres.

    ``X = R sin(Phi) cos(Theta)``, ``Y = R sin(Phi) sin(Theta)``, ``Z = R cos(Phi)``
    with Phi from the optical axis and Theta the azimuth from +x toward +y.
    """
    r, th, ph = np.broadcast_arrays(np.asarray(r_m, dtype=np.float64),
                                    np.asarray(theta_rad, dtype=np.float64),
                                    np.asarray(phi_rad, dtype=np.float64))
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(th)) and np.all(np.isfinite(ph))):
        raise CalibrationError("spherical coordinates must be finite")
    s = np.sin(ph)
    return np.stack((r * s * np.cos(th), r * s * np.sin(th), r * np.cos(ph)), axis=-1)


def plane_fit(distances_m: ArrayLike, phi_rad: ArrayLike, theta_rad: ArrayLike) -> PlaneFit:
    """Approach 2's plane: least squares ``Z = a X + b Y + c`` through the measured points.

    Args:
        distances_m: Measured distance R of each point, metres (> 0).
        phi_rad: Angle of each point's ray from the optical axis, radians.
        theta_rad: Azimuth of each point's ray, radians.

    Raises:
        CalibrationError: Fewer than 3 points, non-positive/NaN distances, or a
            degenerate point set.
    """
    r = np.asarray(distances_m, dtype=np.float64)
    if r.ndim != 1:
        raise CalibrationError(f"distances must be a 1-D array, got shape {r.shape}")
    if not np.all(np.isfinite(r)) or np.any(r <= 0):
        raise CalibrationError("distances must be positive and finite")
    pts = spherical_to_cartesian(r, theta_rad, phi_rad)
    return fit_plane_ols(pts)


def plane_fit_angle(distances_m: ArrayLike, phi_rad: ArrayLike, theta_rad: ArrayLike) -> float:
    """Approach 2: angle (rad) between the fitted plane and the optical axis.

    Equals the paper's ``90 deg - arccos(1 / sqrt(a^2 + b^2 + 1))``.
    """
    return float(plane_fit(distances_m, phi_rad, theta_rad).plane.angle_to_optical_axis_rad())


def law_of_cosines_angle(co_m: float, cay_m: float, oay_m: float) -> float:
    """Approach 1: the angle at O between the optical axis and the plane (rad).

    ``arccos((CO^2 + OAy^2 - CAy^2) / (2 CO OAy))`` for the triangle camera centre C,
    on-axis plane point O and an in-plane point Ay.

    Args:
        co_m: Distance from C to O, metres.
        cay_m: Distance from C to Ay, metres.
        oay_m: In-plane distance from O to Ay, metres.

    Raises:
        CalibrationError: If a length is not positive and finite, or the three lengths
            violate the triangle inequality.
    """
    sides = {"CO": co_m, "CAy": cay_m, "OAy": oay_m}
    for name, value in sides.items():
        if not (isinstance(value, (int, float, np.floating, np.integer))
                and math.isfinite(value) and value > 0):
            raise CalibrationError(f"law of cosines: {name} must be a positive length, got {value!r}")
    co, cay, oay = float(co_m), float(cay_m), float(oay_m)
    cos_angle = (co * co + oay * oay - cay * cay) / (2.0 * co * oay)
    if not -1.0 <= cos_angle <= 1.0:
        raise CalibrationError(
            f"law of cosines: CO={co:g}, CAy={cay:g}, OAy={oay:g} do not form a triangle")
    return math.acos(cos_angle)


def error_pct(angle_rad: float, true_angle_rad: float) -> float:
    """The paper's relative error ``|angle - true| / true * 100`` (percent)."""
    if true_angle_rad == 0:
        raise CalibrationError("true angle must be non-zero")
    return abs(angle_rad - true_angle_rad) / abs(true_angle_rad) * 100.0


@dataclass(frozen=True)
class PaperResult:
    """Both approaches on one P1–P9 data set.

    Attributes:
        perimeter_px: The data set's perimeter, pixels.
        law_of_cosines_rad: Approach 1's angle, radians.
        plane_fit_rad: Approach 2's angle, radians.
        fit: The approach-2 plane fit (camera frame, metres).
    """

    perimeter_px: float
    law_of_cosines_rad: float
    plane_fit_rad: float
    fit: PlaneFit


def paper_methods(points_m: Mapping[str, ArrayLike], perimeter_px: float,
                  model: NominalFovModel | Intrinsics | None = None) -> PaperResult:
    """Run both approaches on one data set exactly as the paper did.

    R of every point is its z value, CO and CAy are the z values of P5 and P8, OAy is
    ``|y|`` of P8; Phi comes from ``model`` (default: the paper's nominal 60 x 45 deg
    over 224 x 172 px) and Theta is the grid's nominal Theta.

    Args:
        points_m: Camera-frame ``(x, y, z)`` in metres for each of ``"P1"``..``"P9"``.
        perimeter_px: The perimeter the points were taken at, pixels.
        model: Camera model for Phi.

    Raises:
        CalibrationError: Missing points, a perimeter outside the image, or degenerate
            measurements.
    """
    missing = [n for n in GRID_NAMES if n not in points_m]
    if missing:
        raise CalibrationError(f"data set lacks point(s) {', '.join(missing)}")
    mdl = NominalFovModel.o3r222() if model is None else model
    if isinstance(mdl, NominalFovModel):
        grid = grid_points(perimeter_px, width_px=mdl.width_px, height_px=mdl.height_px)
    else:
        grid = grid_points(perimeter_px, width_px=mdl.width, height_px=mdl.height,
                           cx=mdl.cx, cy=mdl.cy)
    xyz = np.array([np.asarray(points_m[g.name], dtype=np.float64).reshape(3) for g in grid])
    phi, theta = grid_phi_theta(grid, mdl)
    fit = plane_fit(xyz[:, 2], phi, theta)
    p5, p8 = xyz[GRID_NAMES.index("P5")], xyz[GRID_NAMES.index("P8")]
    loc = law_of_cosines_angle(float(p5[2]), float(p8[2]), abs(float(p8[1])))
    return PaperResult(float(perimeter_px), loc, fit.plane.angle_to_optical_axis_rad(), fit)


# ---------------------------------------------------------------------- the paper's methods on depth frames
@dataclass(frozen=True)
class GridEstimate:
    """One grid method's estimate of the plane at one perimeter, camera frame.

    Attributes:
        angle_rad: Angle between the plane and the optical axis, rad.
        angle_sigma_rad: 1-sigma uncertainty of ``angle_rad``, rad (None for the law of cosines).
        tilt_x_rad: Camera tilt about its x axis, rad.
        tilt_y_rad: Camera tilt about its y axis, rad.
        height_m: Distance to the plane along the optical axis, metres (CO for the law of cosines).
        residual_rms_m: RMS residual of the plane fit, metres (None for the law of cosines).
        plane: The fitted plane (None for the law of cosines).
    """

    angle_rad: float
    angle_sigma_rad: float | None
    tilt_x_rad: float
    tilt_y_rad: float
    height_m: float
    residual_rms_m: float | None
    plane: Plane | None = None


def nominal_model(intrinsics: Intrinsics, fov_rad: tuple[float, float] | None = None) -> NominalFovModel:
    """The paper's angle-per-pixel model for a camera.

    Args:
        intrinsics: The camera's intrinsics (image size and, without ``fov_rad``, focal lengths).
        fov_rad: Datasheet field of view (x, y), rad; None: the pinhole field of view of
            the intrinsics (distortion ignored, as in the paper).
    """
    if fov_rad is None:
        # full pinhole field of view: 2 atan(half the image size / focal length), per axis
        fov_rad = (2 * math.atan(intrinsics.width / (2 * intrinsics.fx)),
                   2 * math.atan(intrinsics.height / (2 * intrinsics.fy)))
    return NominalFovModel(intrinsics.width, intrinsics.height, fov_rad[0], fov_rad[1])


def _fold(angle_rad: float) -> float:
    """Fold an angle between two lines into [0, pi/2]."""
    return min(angle_rad, math.pi - angle_rad)


def _axis_angle(o: Sample, a: Sample, along: int, perimeter_px: float) -> tuple[float, float]:
    """Law-of-cosines angle at O toward ``a`` and the sign of the plane's slope along ``along``.

    Args:
        o: The on-axis sample (P5).
        a: The off-axis sample (P8 along y, P4 along x).
        along: Camera axis the two points are separated along (0: x, 1: y).
        perimeter_px: For the error message.

    Returns:
        The angle between the optical axis and the line O-A, folded into [0, pi/2], rad,
        and +1 or -1: the sign of dz / d(along) between O and A.
    """
    co = float(np.linalg.norm(o.xyz_m))  # camera centre to O
    ca = float(np.linalg.norm(a.xyz_m))  # camera centre to A
    oa = float(np.linalg.norm(a.xyz_m - o.xyz_m))  # O to A, in the plane
    if oa <= 0:
        raise CalibrationError(f"grid points coincide at perimeter {perimeter_px} px")
    angle = _fold(law_of_cosines_angle(co, ca, oa))
    slope = (a.xyz_m[2] - o.xyz_m[2]) / (a.xyz_m[along] - o.xyz_m[along])
    return angle, math.copysign(1.0, float(slope))


def law_of_cosines_estimate(samples: Mapping[str, Sample], perimeter_px: float) -> GridEstimate:
    """Approach 1 on real 3D samples: the angle from the triangle C, O = P5, Ay = P8.

    CO and CAy are the measured radial distances, OAy their 3D separation; the same
    construction along x (P4) gives the tilt about y. The reported angle is the y
    construction, as in the paper's Table 3.

    Raises:
        CalibrationError: Coinciding points or lengths that form no triangle.
    """
    o, ay, ax = samples["P5"], samples["P8"], samples["P4"]
    angle_y, slope_y = _axis_angle(o, ay, 1, perimeter_px)
    angle_x, slope_x = _axis_angle(o, ax, 0, perimeter_px)
    # the tilt is the complement of the axis-to-line angle; z falls along +y for a
    # positive tilt about x, and rises along +x for a positive tilt about y
    tilt_x = -slope_y * (math.pi / 2 - angle_y)
    tilt_y = slope_x * (math.pi / 2 - angle_x)
    return GridEstimate(angle_y, None, tilt_x, tilt_y, float(np.linalg.norm(o.xyz_m)), None)


def plane_fit_estimate(fit: PlaneFit) -> GridEstimate:
    """Approach 2's figures from a plane fit: angle with its first-order 1-sigma, tilts, height."""
    plane = fit.plane
    return GridEstimate(plane.angle_to_optical_axis_rad(), fit.angle_to_optical_axis_sigma_rad(),
                        plane.tilt_about_x_rad(), plane.tilt_about_y_rad(), plane.distance_along_optical_axis_m(),
                        fit.rms_m, plane)


def _nominal_plane_fit(samples: Mapping[str, Sample], points: Sequence[GridPoint],
                       model: NominalFovModel) -> PlaneFit:
    """Approach 2 as the paper built its points: measured R at each grid pixel, nominal (Theta, Phi)."""
    phi, theta = grid_phi_theta(points, model)
    r = np.array([samples[g.name].distance_m for g in points])  # measured radial distances, metres
    return plane_fit(r, phi, theta)


def grid_estimates(frames: Sequence[Frame], p_px: float, methods: Sequence[str], *, window_px: int = 3,
                   model: NominalFovModel | None = None) -> list[tuple[str, GridEstimate]]:
    """The paper's methods on the frames of one pose at one perimeter.

    ``law_of_cosines`` is approach 1 on the sampled 3D points (:func:`law_of_cosines_estimate`);
    ``plane_fit`` is approach 2 on the frame's XYZ (the camera's own intrinsics, distortion
    honoured); ``plane_fit_nominal`` is approach 2 exactly as the paper built its points (R at
    each grid pixel, (Theta, Phi) from the nominal model), so its error is the model's bias.

    Args:
        frames: Frames captured at the pose (their samples are pooled).
        p_px: Perimeter, pixels.
        methods: Names from :data:`GRID_METHODS`, in the order wanted.
        window_px: Odd sampling window, pixels.
        model: The nominal model for ``plane_fit_nominal``; None: :func:`nominal_model`
            of the frames' intrinsics.

    Returns:
        ``(method, estimate)`` pairs in the order of ``methods``.

    Raises:
        CalibrationError: The grid leaves the image, too few valid pixels at a point,
            degenerate geometry or an unknown method.
    """
    points = camera_grid(frames[0].intrinsics, p_px)
    samples = sample_grid(frames, points, window_px)
    out: list[tuple[str, GridEstimate]] = []
    for method in methods:
        if method == "law_of_cosines":
            est = law_of_cosines_estimate(samples, p_px)
        elif method == "plane_fit":
            est = plane_fit_estimate(fit_plane_ols(np.array([samples[g.name].xyz_m for g in points])))
        elif method == "plane_fit_nominal":
            mdl = model if model is not None else nominal_model(frames[0].intrinsics)
            est = plane_fit_estimate(_nominal_plane_fit(samples, points, mdl))
        else:
            raise CalibrationError(f"unknown method '{method}'")
        out.append((method, est))
    return out
