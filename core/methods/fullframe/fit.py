"""The full-frame fit as a pipeline over a measurement space: points, space, honesty, flatness, result.

Points are in the camera frame (OpenCV: x right, y down, z along the optical axis), metres,
with the sensor at the origin; the fitted normal points toward the camera (``offset_m > 0``).
The frames' measurement model chooses the space the plane is fitted in (``space.py``): a
stereo or structured-light camera's disparities (``disparity.py``), else ranges along the
rays (``range_space.py``). Method and rationale: docs/adr/0007-full-frame-fit.md; region of
interest, expected plane, quantisation floor: docs/adr/0028-honest-full-frame-fit.md; the
spaces: docs/adr/0050-measurement-spaces.md.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from statistics import NormalDist  # not scipy.special: its 0.2 s import is off calibrate's start-up
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellcal.core.methods.fullframe.disparity import DisparitySpace
from cellcal.core.methods.fullframe.flatness import Flatness, fit_flatness
from cellcal.core.methods.fullframe.gates import gate_table
from cellcal.core.methods.fullframe.honesty import Honest, allow_rounding, honest_intervals
from cellcal.core.methods.fullframe.points import (
    ExpectedPlane,
    cloud_points,
    frame_points,
    image_coverage,
    pixel_inliers,
)
from cellcal.core.methods.fullframe.range_space import RangeSpace
from cellcal.core.methods.fullframe.result import Estimate, FullFrameResult
from cellcal.core.methods.fullframe.settings import FullFrameSettings
from cellcal.core.methods.fullframe.space import EdgeReport, MeasurementSpace, SpaceFit
from cellcal.devices.errors import CalibrationError
from cellcal.devices.measurement import UNKNOWN_MODEL
from cellcal.devices.types import Frame

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = ["fit_full_frame", "fit_plane_points"]

_DEFAULTS = FullFrameSettings()


def fit_full_frame(frames: Frame | Sequence[Frame], settings: FullFrameSettings | None = None, *,
                   region: NDArray[np.bool_] | None = None, expected: ExpectedPlane | None = None
                   ) -> FullFrameResult:
    """Fit the measuring plane to every valid pixel of one or more frames of a static camera.

    Frames are pooled (each pixel of each frame is one observation). The fit does not
    raise on a failed gate: see ``result.gates`` or call :func:`check_gates`. The frames'
    measurement model (``frame.measurement``) sets the space the plane is fitted in
    (stereo: disparity; else range), the noise law and the quantisation floor.

    Args:
        frames: One frame or several of the same camera and pose.
        settings: Fit settings and gates (the ``[full_frame]`` table); None: defaults.
        region: (H, W) bool region of interest: pixels outside it are ignored, and the
            valid fraction and coverage are taken over it. None: the whole image.
        expected: The plane the user means (camera frame): only planes within its
            tolerances start the fit, and a fit outside them fails gate ``expected_plane``.

    Returns:
        The plane (camera frame, normal toward the camera) with intervals and gates.

    Raises:
        CalibrationError: Malformed input (not frames, mixed shapes, a bad region), points
            behind the camera or in millimetres, or no plane defined.
        CalibrationQualityError: Fewer than 16 valid pixels in the region, or fewer left after
            the edge clean-up (gate ``valid_fraction``); no plane near the expected one
            (gate ``expected_plane``).
    """
    cfg = settings or _DEFAULTS
    data = frame_points(frames, region, cfg.min_valid_fraction)        # frames -> pooled points
    space = _space_of(data.frames[0], cfg)
    fit = space.fit(data, expected)                                    # robust start -> refine -> covariance
    fit, honest = honest_intervals(fit, space, data, expected)         # floors, lock-on, widened intervals
    judged = fit_flatness(fit, data, space.noise_shape, cfg)           # in sensor terms (ADR 0060)
    flat, honest = allow_rounding(judged, honest, fit.residual_rms_m)
    if judged.notes:                                                   # the sensor's allowances flatness used
        honest = dataclasses.replace(honest, notes=(*honest.notes, *judged.notes))
    mask = pixel_inliers(fit.inliers, data.masks, data.shape)
    extras = Extras(image_coverage(mask, cfg, data.region), flat, honest)
    return assemble(fit, cfg, sigma_given=False, n_points=data.n, valid_fraction=data.n / data.n_pixels,
                    inlier_mask=mask, n_frames=len(data.frames), extras=extras)


def _space_of(frame: Frame, settings: FullFrameSettings) -> MeasurementSpace:
    """The space a camera measures in: disparity for stereo and structured light, else range along the rays."""
    if frame.measurement.triangulating:
        return DisparitySpace(settings, frame.measurement)
    return RangeSpace(settings, frame.measurement, frame.intrinsics)


def fit_plane_points(points_m: ArrayLike, sigma_m: ArrayLike | None = None,
                     settings: FullFrameSettings | None = None) -> FullFrameResult:
    """Robust full-cloud plane fit of raw camera-frame points (the range space, without image checks).

    The sensor must be at the origin (ranges are measured along the rays through it).

    Args:
        points_m: Shape (N, 3), camera frame, metres; rows with NaN/inf are skipped.
        sigma_m: Optional per-point range-noise sigma, metres, shape (N,): replaces the
            noise model's weights (rows with sigma <= 0 or non-finite are skipped).
        settings: Fit settings and gates; None uses the defaults.

    Returns:
        The result; ``inlier_mask`` has shape (N,), ``coverage`` and ``flatness_m`` are
        NaN (no image) and there are no coverage and flatness gates; ``valid_fraction``
        counts finite rows in front of the camera.

    Raises:
        CalibrationError: Wrong shape or type, points behind the camera or in millimetres,
            or no plane can be defined.
        CalibrationQualityError: Fewer than 16 usable points (gate ``valid_fraction``).
    """
    cfg = settings or _DEFAULTS
    data, sigma, rows = cloud_points(points_m, sigma_m, cfg.min_valid_fraction)
    fit = RangeSpace(cfg, sigma_m=sigma).fit(data, None)
    mask = np.zeros(rows.size, dtype=bool)
    mask[rows] = fit.inliers
    return assemble(fit, cfg, sigma_given=sigma is not None, n_points=data.n, valid_fraction=data.n / data.n_pixels,
                    inlier_mask=mask, n_frames=1, extras=Extras())


# ---------------------------------------------------------------------- the result
@dataclass(frozen=True)
class Extras:
    """What the frame path adds: image coverage, flatness and the honesty checks."""

    coverage: float = math.nan
    flatness: Flatness | None = None
    honest: Honest | None = None


def _geometry(n: FloatArray, d: FloatArray) -> FloatArray:
    """Angle to the optical axis, tilt x, tilt y, height along the axis of planes (K, 4).

    Vectorised copies of :meth:`Plane.angle_to_optical_axis_rad`,
    :meth:`Plane.tilt_about_x_rad`, :meth:`Plane.tilt_about_y_rad` and
    :meth:`Plane.distance_along_optical_axis_m` (NaN where the axis misses the plane)
    for unit normals ``n`` (K, 3) and offsets ``d`` (K,).
    """
    nz = n[:, 2]
    f = np.where((nz > 0)[:, None], -n, n)            # the normal as seen from the camera
    out = np.empty((n.shape[0], 4))
    out[:, 0] = np.arcsin(np.minimum(1.0, np.abs(nz)))
    out[:, 1] = np.arctan2(-f[:, 1], -f[:, 2])
    out[:, 2] = np.arctan2(f[:, 0], -f[:, 2])
    with np.errstate(divide="ignore", invalid="ignore"):
        h = -d / nz
    out[:, 3] = np.where((np.abs(nz) >= 1e-12) & (h > 0), h, np.nan)
    return out


def _derived(fit: SpaceFit) -> tuple[list[float], list[float], FloatArray]:
    """Angle, tilt x, tilt y, height, their 1-sigma, and the (4, 3) Jacobian (central differences)."""
    n0 = fit.plane.normal
    d0 = fit.plane.offset_m
    steps = np.array([1e-6, 1e-6, 1e-6 * max(abs(d0), 1e-3)])
    dp = np.concatenate([np.zeros((1, 3)), np.diag(steps), -np.diag(steps)])   # (7, 3): 0, +steps, -steps
    nn = n0 + dp[:, :1] * fit.e1 + dp[:, 1:2] * fit.e2
    norm = np.linalg.norm(nn, axis=1)
    v = _geometry(nn / norm[:, None], (d0 + dp[:, 2]) / norm)
    jac = ((v[1:4] - v[4:7]) / (2.0 * steps[:, None])).T                      # (4, 3)
    var = np.einsum("ij,jk,ik->i", jac, fit.cov, jac)                          # diag(J C J^T)
    return v[0].tolist(), np.sqrt(np.maximum(var, 0.0)).tolist(), jac


def _noise_and_shifts(hon: Honest, e: FloatArray) -> dict[str, Any]:
    """The noise-only covariances and the allowance's per-term shifts (ADR 0059, "Amended"); {}: noise = total."""
    budget = hon.factors.systematic
    if hon.noise_cov is None or budget is None or not budget.widened:
        return {}
    c = hon.noise_cov
    return {"noise_normal_covariance": e @ c[:2, :2] @ e.T, "noise_offset_sigma_m": math.sqrt(max(c[2, 2], 0.0)),
            "noise_normal_offset_covariance": e @ c[:2, 2],
            "systematic_shifts": {k: (np.asarray(s.normal, dtype=np.float64), float(s.offset_m))
                                  for k, s in budget.allowance_shifts.items()}}


def assemble(fit: SpaceFit, settings: FullFrameSettings, *, sigma_given: bool, n_points: int,
             valid_fraction: float, inlier_mask: BoolArray, n_frames: int, extras: Extras) -> FullFrameResult:
    """The result: estimates with intervals, covariances of normal and offset, gate values.

    Raises:
        CalibrationError: The plane does not cross the optical axis in front of the camera.
    """
    (angle, tx, ty, height), (s_a, s_x, s_y, s_h), jac = _derived(fit)
    if not (math.isfinite(height) and height > 0):
        raise CalibrationError("full-frame fit: the plane does not cross the optical axis in front of the "
                               "camera, so its height is undefined; is the camera looking at the plane?")
    z = NormalDist().inv_cdf(0.5 + settings.confidence / 2.0)   # two-sided normal quantile: value ± z sigma
    e = np.stack([fit.e1, fit.e2], axis=1)
    cov_n = e @ fit.cov[:2, :2] @ e.T                    # tangent steps -> unit normal (3x3)
    cov_nd = e @ fit.cov[:2, 2]
    edge = fit.edge or EdgeReport()
    hon = extras.honest or Honest(expected_m=fit.unit_rms_m * (1.0 if sigma_given else math.nan),
                                  sigma_stated=sigma_given, region_pixels=n_points)
    n_in = int(np.count_nonzero(fit.inliers))
    inlier_fraction = (n_in + edge.n_dropped) / n_points   # on the plane: inliers and mixed pixels
    flat = extras.flatness
    beta, beta_sigma, dstep = fit.multipath
    shift = jac @ dstep                                  # change of each value with the radial bias fitted
    exp = hon.expected
    res = FullFrameResult(
        plane=fit.plane, angle=Estimate.from_sigma(angle, s_a, z, 0.0, math.pi / 2),
        tilt_x=Estimate.from_sigma(tx, s_x, z), tilt_y=Estimate.from_sigma(ty, s_y, z),
        height=Estimate.from_sigma(height, s_h, z), confidence=settings.confidence,
        normal_covariance=cov_n, offset_variance_m2=float(fit.cov[2, 2]), normal_offset_covariance=cov_nd,
        valid_fraction=valid_fraction, inlier_fraction=inlier_fraction, residual_rms_m=fit.residual_rms_m,
        coverage=extras.coverage, noise_scale_m=fit.noise_scale_m, n_points=n_points, n_inliers=n_in,
        n_frames=n_frames, inlier_mask=inlier_mask, gates={},
        residual_unit_rms_m=fit.unit_rms_m, sigma_given=sigma_given,
        flatness_m=math.nan if flat is None else flat.excess_m, flatness_where="" if flat is None else flat.where,
        multipath=Estimate.from_sigma(beta, beta_sigma, z),
        multipath_shift={"angle_rad": float(shift[0]), "tilt_x_rad": float(shift[1]),
                         "tilt_y_rad": float(shift[2]), "height_m": float(shift[3])},
        mixed_margin_px=edge.margin_px, n_mixed=edge.n_dropped, settings=settings,
        measurement=hon.measurement, native_space=hon.native_space, residual_expected_m=hon.expected_m,
        residual_floor_m=hon.floor_m, sigma_stated=hon.sigma_stated, multipath_allowance_m=hon.multipath_m,
        lock_on=hon.lock_on, expected_departure=None if exp is None else exp.departure(fit.plane),
        expected_tolerance=None if exp is None else (exp.angle_tolerance_rad, exp.offset_tolerance_m),
        region_pixels=hon.region_pixels, interval_factors=hon.factors, interval_notes=hon.notes,
        **_noise_and_shifts(hon, e))
    if extras.honest is None:                            # raw clouds: the expected RMS from the default noise
        expected = res.residual_unit_rms_m * (1.0 if sigma_given else settings.noise_at_1m_m(UNKNOWN_MODEL))
        res = dataclasses.replace(res, residual_expected_m=expected)
    return dataclasses.replace(res, gates=gate_table(settings, res))
