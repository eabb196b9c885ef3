"""The range space: a ToF camera's ranges along fixed rays (and raw clouds seen from the origin).

The plane ``n·p + offset = 0`` predicts the range ``t = -offset / (r·n)`` along each ray
``r``; residuals ``|p| - t`` are whitened by the noise law ``sigma ∝ t^e / sqrt|cos|`` (or
given sigmas), cut at a band of robust sigmas, started from the best triplet plane
(``start.py``) and refined by Gauss-Newton passes (``passes.py``), the last two over every
point with the mixed-pixel clean-up (``mixed.py``). Its floors: the range step projected
across the plane, and the camera's stated noise. Rationale: docs/adr/0007-full-frame-fit.md,
docs/adr/0028-honest-full-frame-fit.md, docs/adr/0047-measurement-spaces.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe.expected import ExpectedPlane
from cellcal.core.methods.fullframe.mixed import EdgeClean
from cellcal.core.methods.fullframe.passes import (
    Cutoff,
    FinalPass,
    KeepMask,
    Model,
    NothingLeftError,
    Scratch,
    basis,
    final_pass,
    step_plane,
)
from cellcal.core.methods.fullframe.points import Points, Sample
from cellcal.core.methods.fullframe.settings import MIN_POINTS, FullFrameSettings
from cellcal.core.methods.fullframe.space import Floors, SpaceFit
from cellcal.core.methods.fullframe.start import initial_scale, refine, robust_start
from cellcal.devices.errors import CalibrationError, CalibrationQualityError
from cellcal.devices.measurement import UNKNOWN_MODEL, MeasurementModel
from cellcal.devices.types import Intrinsics

F32 = NDArray[np.float32]

__all__ = ["RangeSpace"]

#: Passes over every point (the second from the first one's plane).
FINAL_PASSES = 2
#: Rings around outlier patches examined for mixed pixels, as a multiple of the floor (+ this many pixels).
RING_REACH = 16
#: Frames with at most this many valid pixels are checked for what the edge margin leaves.
SMALL_FRAME_POINTS = 4096


@dataclass(frozen=True)
class RangeSpace:
    """Residuals along the rays, whitened by the range-noise law (see the module docstring).

    Attributes:
        settings: The ``[full_frame]`` table.
        model: The noise law's exponent, or given per-point sigmas.
        measurement: The camera's measurement model (its quantisation and stated noise).
        edge_floor_px: Rings always dropped around solid patches of outliers and invalid pixels
            (``edge_margin_deg`` in pixels; 0: no mixed-pixel clean-up, as for raw clouds).
    """

    settings: FullFrameSettings
    model: Model
    measurement: MeasurementModel = UNKNOWN_MODEL
    edge_floor_px: int = 0
    name: ClassVar[str] = "range"

    @classmethod
    def of_camera(cls, measurement: MeasurementModel, intrinsics: Intrinsics, settings: FullFrameSettings
                  ) -> RangeSpace:
        """The space of a camera's frames: its noise law, and the edge margin at its focal length."""
        floor_px = math.ceil(math.radians(settings.edge_margin_deg) * max(intrinsics.fx, intrinsics.fy) - 1e-9)
        return cls(settings, Model(settings.weighted, settings.noise_exponent(measurement)), measurement, floor_px)

    @property
    def noise_shape(self) -> Model:
        """The range-noise shape of the flatness gate's weights: the fit's own."""
        return self.model

    def fit(self, points: Points, expected: ExpectedPlane | None) -> SpaceFit:
        """Robust start, passes on a subsample, then two passes over every point (with the edge clean-up)."""
        edge = None
        if self.edge_floor_px > 0 and points.masks:
            edge = EdgeClean(points.masks, points.shape, self.edge_floor_px, RING_REACH * (self.edge_floor_px + 1),
                             self.settings.mixed_ring_sigma,
                             region=None if points.region is None else points.region.reshape(-1))
            _check_margin(edge, points, self.settings.min_valid_fraction)
        try:
            fit = _robust_fit(points.p, points.dm, self.model, self.settings, keep=edge, edge=edge, expected=expected)
        except NothingLeftError as exc:
            raise _nothing_left(exc.n_points, exc.n_left, points, self.settings.min_valid_fraction,
                                0 if edge is None else edge.floor_px) from None
        fit.edge = None if edge is None else edge.report
        return fit

    def floors(self, fit: SpaceFit, points: Points, sample: Sample) -> Floors:
        """The range step across the plane, the stated noise law's RMS, and the whitened residuals."""
        meas, tof = self.measurement, self.measurement.kind == "tof"
        cos = np.abs(fit.plane.normal @ sample.p) / np.maximum(points.dm[sample.index].astype(np.float64), 1e-12)
        q = meas.range_step_m if tof else 0.0
        floor = q / math.sqrt(12.0) * math.sqrt(float(np.mean(cos * cos))) if cos.size else 0.0
        expected_m = math.hypot(fit.unit_rms_m * self.settings.noise_at_1m_m(meas), floor)
        stated = tof and meas.sigma_at_1m_m is not None
        ratio = fit.residual_rms_m / expected_m if expected_m > 0 else math.nan
        notes: tuple[str, ...] = ()
        if stated and ratio > 1.0:
            notes = (f"residuals {ratio:.3g} x what the sensor model expects: the intervals follow the observed "
                     "scatter (sandwich covariance)",)
        resid = fit.resid if fit.resid is not None else np.zeros(fit.inliers.size, np.float32)
        return Floors(floor, expected_m, stated, meas.multipath_m if tof else 0.0,
                      points.dm if tof else points.p[2], resid, notes)   # a ToF camera quantises the range


# ---------------------------------------------------------------------- the stages
def _subsample(limit: int, *arrays: F32) -> list[F32]:
    """Every k-th point (last axis; contiguous copies) so that at most ``limit`` remain."""
    step = -(-arrays[0].shape[-1] // limit)
    if step <= 1:
        return list(arrays)
    return [np.ascontiguousarray(a[..., ::step]) for a in arrays]


def _robust_fit(p: F32, dm: F32, model: Model, settings: FullFrameSettings, keep: KeepMask | None = None,
                edge: EdgeClean | None = None, expected: ExpectedPlane | None = None) -> SpaceFit:
    """The stages on finite camera-frame points ``p`` (3, N) with ranges ``dm``.

    ``keep`` maps the inlier mask (N,) and the residuals of the converged plane to the
    points allowed in the last pass (image-space clean-up, see ``edge_margin_deg``).
    ``expected`` restricts the robust start to planes within its tolerances.
    """
    n, offset = robust_start(p, dm, model, settings, expected)
    if model.sigma is None:                                    # strided subsample for the passes
        ps, ds = _subsample(settings.refine_points, p, dm)
        sub = model
    else:
        ps, ds, ss = _subsample(settings.refine_points, p, dm, model.sigma)
        sub = model.subset(ss)
    s, cutoff = initial_scale(ps, ds, sub, n, offset, settings)
    n, offset, s = refine(ps, ds, sub, n, offset, s, cutoff, settings)
    return _final(p, dm, model, n, offset, s, cutoff, keep, edge)


def _final(p: F32, dm: F32, model: Model, n: NDArray[np.float64], offset: float, s: float, cutoff: Cutoff,
           keep: KeepMask | None, edge: EdgeClean | None) -> SpaceFit:
    """Passes over every point: plane, sandwich covariance, inliers, RMS, scale, multipath.

    The second pass starts from the first one's full-data plane and scale, so that the
    inliers and the edge clean-up of the answer do not depend on where the start was.
    """
    scratch = Scratch(dm.size)                                 # point-sized rows reused by both passes
    for k in range(FINAL_PASSES):
        e1, e2 = basis(n)
        if edge is not None:
            edge.scale = s
        fin: FinalPass = final_pass(p, dm, n, e1, e2, offset, cutoff.at(s), model, keep,
                                    answer=k == FINAL_PASSES - 1, scratch=scratch)
        n_fin, offset_fin = step_plane(n, e1, e2, offset, fin.step)
        s = math.sqrt(fin.z2_sum / fin.n_inliers / cutoff.kept_var)   # truncation-corrected scale
        if k < FINAL_PASSES - 1:
            n, offset = n_fin, offset_fin
    try:
        h_inv = np.linalg.inv(fin.hessian)
        h4_inv = np.linalg.inv(fin.radial[0])
    except np.linalg.LinAlgError:
        raise CalibrationError("full-frame fit is degenerate: the inliers do not span a plane") from None
    dof = max(fin.n_inliers - 3, 1)
    # sandwich H^-1 M H^-1, small-sample factor n / (n - 3), hard-rejection correction
    cov = h_inv @ fin.meat @ h_inv * (fin.n_inliers / dof) * cutoff.cov_factor
    rms = math.sqrt(fin.ortho2_sum / fin.n_inliers)
    unit = math.sqrt(cutoff.kept_var * fin.model_ortho2_sum / fin.n_inliers)
    step4 = -h4_inv @ fin.radial[1]                             # plane and radial range bias together
    beta_sigma = s * math.sqrt(max(float(h4_inv[3, 3]), 0.0) * cutoff.cov_factor)
    return SpaceFit(Plane(n_fin, offset_fin), cov, e1, e2, fin.inliers, rms, s, unit,
                    (-float(step4[3]), beta_sigma, step4[:3] - fin.step), fin.z)


# ---------------------------------------------------------------------- too few pixels left
def _nothing_left(n_ok: int, left: int, points: Points, min_valid: float, floor_px: int) -> CalibrationQualityError:
    """Gate ``valid_fraction``: too few pixels left after the edge clean-up (small and large frames alike)."""
    return CalibrationQualityError(
        "valid_fraction", left / max(points.n_pixels, 1), min_valid,
        f"{n_ok} {points.what}s, {left} left after the edge clean-up ({floor_px} px around invalid and off-plane "
        f"patches, edge_margin_deg, and mixed pixels at depth edges); a full-frame fit needs {MIN_POINTS}")


def _check_margin(edge: EdgeClean, points: Points, min_valid: float) -> None:
    """Few valid pixels: enough of them must lie farther than the edge margin from invalid patches."""
    if points.n > SMALL_FRAME_POINTS:
        return
    left = edge.margin_keep()
    if left < MIN_POINTS:
        raise _nothing_left(points.n, left, points, min_valid, edge.floor_px)
