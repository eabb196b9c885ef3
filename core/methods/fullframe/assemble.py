"""The result of a full-frame fit from a space's plane: estimates with intervals, covariances, gate values.

Angle to the optical axis, tilt x, tilt y and height along the axis are propagated from the
plane's covariance by central-difference Jacobians of vectorised copies of the
:class:`~cellcal.core.geometry.planes.Plane` methods (ADR 0007, "Uncertainty").
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from statistics import NormalDist  # not scipy.special: its 0.2 s import is off calibrate's start-up

import numpy as np
from numpy.typing import NDArray

from cellcal.core.methods.fullframe.flatness import Flatness
from cellcal.core.methods.fullframe.gates import gate_table
from cellcal.core.methods.fullframe.honesty import Honest
from cellcal.core.methods.fullframe.mixed import EdgeReport
from cellcal.core.methods.fullframe.result import Estimate, FullFrameResult
from cellcal.core.methods.fullframe.settings import FullFrameSettings
from cellcal.core.methods.fullframe.space import SpaceFit
from cellcal.devices.errors import CalibrationError
from cellcal.devices.measurement import UNKNOWN_MODEL

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = ["Extras", "assemble"]


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
        region_pixels=hon.region_pixels, interval_factors=hon.factors, interval_notes=hon.notes)
    if extras.honest is None:                            # raw clouds: the expected RMS from the default noise
        expected = res.residual_unit_rms_m * (1.0 if sigma_given else settings.noise_at_1m_m(UNKNOWN_MODEL))
        res = dataclasses.replace(res, residual_expected_m=expected)
    return dataclasses.replace(res, gates=gate_table(settings, res))
