"""Full-frame plane calibration: every valid pixel, robust, weighted, with honest intervals.

The paper fits a plane through 9 of ~38,500 depth pixels. This module fits the
measuring plane to *all* valid pixels of one or more frames of a static camera:

1. **Hypotheses** (robust start, threshold-free): ``hypotheses`` planes through random
   point triplets of a random subset of ``sample_points`` points are scored by a low
   quantile (``hypothesis_quantile``) of their noise-normalised orthogonal residuals
   (least-quantile-of-squares, a generalised LMedS). Boxes on the plane, flying pixels
   and multipath points are a minority of any quantile this low, so the plane wins.
2. **Refinement** (maximum likelihood along the rays): a ToF camera measures the range
   ``d`` along each pixel's known ray ``r`` (``p = d r``), so the plane ``n·p + offset = 0``
   predicts the range ``t = -offset / (r·n)``. Iteratively reweighted Gauss-Newton
   minimises ``sum w_i (d_i - t_i)^2`` over the points within ``inlier_threshold_sigma``
   robust standard deviations (scale re-estimated each pass from the inliers, corrected
   for the truncation). With ``weighted`` the weights follow the noise model
   ``sigma_i ∝ t_i^e / sqrt(|cos theta_i|)`` (``e = noise_distance_exponent``), with
   ``t_i`` and ``cos theta_i = r_i·n`` from the current plane (not the noisy data, which
   would bias the fit). Regressing the range on the exact rays is consistent; an
   orthogonal (TLS) fit with noise along the rays is not (its bias does not shrink
   with the number of points). The passes run on a strided subsample
   (``refine_points``); one last Gauss-Newton pass uses every point. Before it, for
   frames, inliers within ``edge_margin_deg`` of solid patches of outliers (box walls'
   feet, depth-edge mixed pixels) are dropped.
3. **Uncertainty**: the sandwich (heteroscedasticity-robust) covariance of the three
   plane parameters from the last pass, corrected for the hard inlier cut-off, is
   propagated by Jacobians (central differences of vectorised copies of the
   :class:`Plane` methods) to the angle to the optical axis, the tilts about x and y and the height
   along the optical axis; the intervals are ``value ± z sigma`` with ``z`` the normal
   quantile of ``confidence``.
4. **Gates**: valid-pixel fraction, inlier fraction, inlier residual RMS and the
   coverage of the image by inliers (fraction of the ``coverage_grid`` cells holding at
   least ``min_cell_inlier_fraction`` inliers). :func:`check_gates` raises
   :class:`~cellcal.devices.errors.CalibrationQualityError` for the first failed gate.

Camera frame: OpenCV (x right, y down, z along the optical axis), metres, the sensor at
the origin. The plane's normal points toward the camera (``offset_m > 0``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import ndtr, ndtri

from cellcal.core.geometry.planes import Plane
from cellcal.devices.errors import CalibrationError, CalibrationQualityError
from cellcal.devices.types import Frame

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
F32 = NDArray[np.float32]

__all__ = [
    "GATE_NAMES",
    "FullFrameResult",
    "FullFrameSettings",
    "check_gates",
    "fit_full_frame",
    "fit_plane_points",
]

#: Gate names in the order they are checked.
GATE_NAMES = ("valid_fraction", "inlier_fraction", "residual_rms_m", "coverage")
#: A fit needs at least this many valid points.
MIN_POINTS = 16
_SQRT_2PI = math.sqrt(2.0 * math.pi)


@dataclass(frozen=True)
class FullFrameSettings:
    """The ``[full_frame]`` configuration table: the fit's knobs and its quality gates.

    Attributes:
        weighted: Weight points by the range-noise model (see the module docstring).
        noise_distance_exponent: Exponent ``e`` of the range in the noise model.
        inlier_threshold_sigma: Inlier cut-off, in robust standard deviations of the
            (noise-normalised) range residual.
        min_inlier_threshold_m: Lower bound of the cut-off at the median pixel's noise,
            metres (keeps noise-free data fittable).
        max_inlier_threshold_m: Upper bound of the cut-off at the median pixel, metres.
        confidence: Confidence level of the reported intervals.
        min_valid_fraction: Gate: valid pixels / all pixels.
        min_inlier_fraction: Gate: inliers / valid pixels.
        max_residual_rms_m: Gate: RMS orthogonal residual of the inliers, metres.
        min_coverage: Gate: fraction of the ``coverage_grid`` cells holding inliers.
        coverage_grid: Cells across and down the image, ``(columns, rows)``.
        min_cell_inlier_fraction: A cell counts as covered when at least this fraction
            of its pixels are inliers.
        edge_margin_deg: Before the last pass, inliers within this angle (degrees of
            view; ``ceil(radians * focal length)`` pixels, 1 px at 224x172, 4 px at
            1280x800) of a solid (at least 3x3 px) patch of outliers or invalid pixels are
            dropped: the feet of box walls and the mixed pixels along depth edges, which
            sit within the noise of the plane but are not on it (with 1 M points their
            bias would exceed the interval). 0 disables; raw point clouds never use it.
        hypotheses: Number of random triplet planes of the robust start.
        sample_points: Points scoring the hypotheses.
        hypothesis_quantile: Quantile of the residuals that scores a hypothesis.
        refine_points: Points (strided subsample) of the reweighting passes.
        max_iterations: Maximum reweighting passes on the subsample.
        seed: Seed of the random sampling (same data and seed, same result).
    """

    weighted: bool = True
    noise_distance_exponent: float = field(default=1.5, metadata={"ge": 0.0, "le": 4.0})
    inlier_threshold_sigma: float = field(default=3.0, metadata={"ge": 1.5, "le": 20.0})
    min_inlier_threshold_m: float = field(default=0.0005, metadata={"ge": 0.0, "le": 0.1})
    max_inlier_threshold_m: float = field(default=0.1, metadata={"gt": 0.0, "le": 10.0})
    confidence: float = field(default=0.95, metadata={"gt": 0.0, "lt": 1.0})
    min_valid_fraction: float = field(default=0.5, metadata={"ge": 0.0, "le": 1.0})
    min_inlier_fraction: float = field(default=0.5, metadata={"ge": 0.0, "le": 1.0})
    max_residual_rms_m: float = field(default=0.01, metadata={"gt": 0.0})
    min_coverage: float = field(default=0.5, metadata={"ge": 0.0, "le": 1.0})
    coverage_grid: tuple[int, int] = field(default=(6, 6), metadata={"ge": 1, "le": 64})
    min_cell_inlier_fraction: float = field(default=0.2, metadata={"ge": 0.0, "le": 1.0})
    edge_margin_deg: float = field(default=0.2, metadata={"ge": 0.0, "le": 10.0})
    hypotheses: int = field(default=96, metadata={"ge": 8, "le": 10000})
    sample_points: int = field(default=160, metadata={"ge": 32, "le": 100000})
    hypothesis_quantile: float = field(default=0.25, metadata={"gt": 0.0, "lt": 1.0})
    refine_points: int = field(default=4096, metadata={"ge": 256})
    max_iterations: int = field(default=6, metadata={"ge": 1, "le": 100})
    seed: int = field(default=0, metadata={"ge": 0})

    def __post_init__(self) -> None:
        if self.max_inlier_threshold_m < self.min_inlier_threshold_m:
            raise ValueError(f"full_frame.max_inlier_threshold_m ({self.max_inlier_threshold_m}) must be "
                             f">= min_inlier_threshold_m ({self.min_inlier_threshold_m})")


@dataclass(frozen=True, eq=False)
class FullFrameResult:
    """A full-frame plane fit with uncertainty and quality-gate values.

    Angles in radians, lengths in metres; intervals are ``(lo, hi)`` at ``confidence``.

    Attributes:
        plane: The plane in the camera frame, normal toward the camera.
        angle_rad: Angle between the plane and the optical axis (pi/2 looking straight).
        angle_sigma_rad: Its 1-sigma.
        angle_ci_rad: Its interval (clipped to [0, pi/2]).
        tilt_x_rad, tilt_x_sigma_rad, tilt_x_ci_rad: Camera tilt about its x axis
            (:meth:`Plane.tilt_about_x_rad`), 1-sigma, interval.
        tilt_y_rad, tilt_y_sigma_rad, tilt_y_ci_rad: Same about y.
        height_m, height_sigma_m, height_ci_m: Distance from the optical centre along the
            optical axis to the plane (NaN when the axis misses the plane).
        confidence: Confidence level of the intervals.
        normal_covariance: 3x3 covariance of the unit normal (tangent to the sphere).
        offset_variance_m2: Variance of ``plane.offset_m``, m^2.
        normal_offset_covariance: Cross-covariance of normal and offset, shape (3,), m.
        valid_fraction: Valid pixels / all pixels (1.0 for raw point clouds).
        inlier_fraction: Inliers / valid points.
        residual_rms_m: RMS orthogonal distance of the inliers to the plane.
        coverage: Fraction of the image cells holding inliers (NaN for raw clouds).
        noise_scale_m: Robust scale of the range residuals: with ``weighted``, the
            range-noise sigma at 1 m and normal incidence implied by the data; otherwise
            the range-noise sigma itself, metres.
        n_points: Valid points used (all frames).
        n_inliers: Inlier points (all frames).
        n_frames: Number of frames pooled (1 for raw clouds).
        inlier_mask: (H, W) bool, pixels that are inliers in at least half of the frames
            where they are valid; shape (N,) for raw point clouds.
        gates: ``name -> (value, threshold, passed)``.
    """

    plane: Plane
    angle_rad: float
    angle_sigma_rad: float
    angle_ci_rad: tuple[float, float]
    tilt_x_rad: float
    tilt_x_sigma_rad: float
    tilt_x_ci_rad: tuple[float, float]
    tilt_y_rad: float
    tilt_y_sigma_rad: float
    tilt_y_ci_rad: tuple[float, float]
    height_m: float
    height_sigma_m: float
    height_ci_m: tuple[float, float]
    confidence: float
    normal_covariance: FloatArray
    offset_variance_m2: float
    normal_offset_covariance: FloatArray
    valid_fraction: float
    inlier_fraction: float
    residual_rms_m: float
    coverage: float
    noise_scale_m: float
    n_points: int
    n_inliers: int
    n_frames: int
    inlier_mask: BoolArray
    gates: dict[str, tuple[float, float, bool]]

    @property
    def passed(self) -> bool:
        """Whether every gate passed."""
        return all(ok for _, _, ok in self.gates.values())

    @property
    def offset_sigma_m(self) -> float:
        """1-sigma of ``plane.offset_m``, metres."""
        return math.sqrt(max(self.offset_variance_m2, 0.0))

    def to_dict(self) -> dict[str, Any]:
        """JSON form: degrees and metres for humans."""
        def deg(v: float) -> float:
            return math.degrees(v)

        def ci_deg(ci: tuple[float, float]) -> list[float]:
            return [deg(ci[0]), deg(ci[1])]

        def num(v: float) -> float | None:
            return v if math.isfinite(v) else None

        return {
            "method": "full_frame",
            "angle_deg": deg(self.angle_rad),
            "angle_sigma_deg": deg(self.angle_sigma_rad),
            "angle_ci_deg": ci_deg(self.angle_ci_rad),
            "tilt_x_deg": deg(self.tilt_x_rad),
            "tilt_x_sigma_deg": deg(self.tilt_x_sigma_rad),
            "tilt_x_ci_deg": ci_deg(self.tilt_x_ci_rad),
            "tilt_y_deg": deg(self.tilt_y_rad),
            "tilt_y_sigma_deg": deg(self.tilt_y_sigma_rad),
            "tilt_y_ci_deg": ci_deg(self.tilt_y_ci_rad),
            "height_m": num(self.height_m),
            "height_sigma_m": num(self.height_sigma_m),
            "height_ci_m": [num(self.height_ci_m[0]), num(self.height_ci_m[1])],
            "confidence": self.confidence,
            "plane_cam": {**self.plane.to_dict(), "offset_sigma_m": self.offset_sigma_m},
            "normal_covariance": self.normal_covariance.tolist(),
            "valid_fraction": self.valid_fraction,
            "inlier_fraction": self.inlier_fraction,
            "residual_rms_m": self.residual_rms_m,
            "coverage": num(self.coverage),
            "noise_scale_m": self.noise_scale_m,
            "n_points": self.n_points,
            "n_inliers": self.n_inliers,
            "n_frames": self.n_frames,
            "gates": {name: {"value": num(v), "threshold": t, "passed": ok}
                      for name, (v, t, ok) in self.gates.items()},
            "passed": self.passed,
        }


# ---------------------------------------------------------------------- gates
def _gate_table(settings: FullFrameSettings, valid_fraction: float, inlier_fraction: float,
                residual_rms_m: float, coverage: float) -> dict[str, tuple[float, float, bool]]:
    """Gate name -> (value, threshold, passed); coverage is skipped when NaN (no image)."""
    gates = {
        "valid_fraction": (valid_fraction, settings.min_valid_fraction,
                           valid_fraction >= settings.min_valid_fraction),
        "inlier_fraction": (inlier_fraction, settings.min_inlier_fraction,
                            inlier_fraction >= settings.min_inlier_fraction),
        "residual_rms_m": (residual_rms_m, settings.max_residual_rms_m,
                           residual_rms_m <= settings.max_residual_rms_m),
    }
    if math.isfinite(coverage):
        gates["coverage"] = (coverage, settings.min_coverage, coverage >= settings.min_coverage)
    return gates


_GATE_TEXT = {
    "valid_fraction": ("valid pixels", "below the minimum", "%"),
    "inlier_fraction": ("plane inliers among the valid pixels", "below the minimum", "%"),
    "residual_rms_m": ("inlier residual RMS", "above the maximum", "mm"),
    "coverage": ("image cells holding plane inliers", "below the minimum", "%"),
}


def check_gates(result: FullFrameResult, settings: FullFrameSettings | None = None) -> None:
    """Raise for the first quality gate the result fails.

    Args:
        result: A fit from :func:`fit_full_frame` or :func:`fit_plane_points`.
        settings: Thresholds to apply; None re-applies the ones the fit was made with.

    Raises:
        CalibrationQualityError: Naming the gate, the value, the threshold and by how
            much it was missed.
    """
    gates = result.gates if settings is None else _gate_table(
        settings, result.valid_fraction, result.inlier_fraction, result.residual_rms_m, result.coverage)
    for name in GATE_NAMES:
        if name not in gates:
            continue
        value, threshold, ok = gates[name]
        if ok:
            continue
        what, side, unit = _GATE_TEXT[name]
        k = 1000.0 if unit == "mm" else 100.0
        unit_s = " mm" if unit == "mm" else " %"
        raise CalibrationQualityError(
            name, value, threshold,
            f"{what} {value * k:.3g}{unit_s}, {abs(value - threshold) * k:.3g}{unit_s} {side} of "
            f"{threshold * k:.3g}{unit_s}")


# ---------------------------------------------------------------------- numerics
def _basis(n: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors completing the unit vector ``n`` to a right-handed orthonormal basis."""
    x, y, z = float(n[0]), float(n[1]), float(n[2])
    # e1 = normalise(ex - x n), or normalise(ey - y n) when n is close to ex
    e1 = np.array([1.0 - x * x, -x * y, -x * z]) if abs(x) < 0.8 else np.array([-y * x, 1.0 - y * y, -y * z])
    e1 /= math.sqrt(float(e1 @ e1))
    a, b, c = float(e1[0]), float(e1[1]), float(e1[2])
    return e1, np.array([y * c - z * b, z * a - x * c, x * b - y * a])


def _truncation(c: float) -> tuple[float, float]:
    """For a Gaussian cut at ``±c`` sigma: (variance factor of the kept part, covariance factor).

    The first divides the inlier mean square to estimate sigma^2; the second multiplies
    the sandwich covariance of the hard-rejection estimator (its derivative loses the
    ``2 c phi(c)`` of the points crossing the cut).
    """
    p = 2.0 * float(ndtr(c)) - 1.0
    jump = 2.0 * c * math.exp(-0.5 * c * c) / _SQRT_2PI
    kept_var = (p - jump) / p
    bread = p - jump
    return kept_var, (p / bread) ** 2 if bread > 0 else 1.0


@dataclass
class _Pass:
    """Sums of one Gauss-Newton pass over a point set."""

    step: FloatArray          # (d_e1, d_e2, d_offset)
    hessian: FloatArray       # J^T W J
    n_inliers: int
    z2_sum: float             # sum of squared normalised residuals of the inliers
    meat: FloatArray | None = None      # sum (w rho)^2 J J^T (final pass only)
    ortho2_sum: float = math.nan        # sum of squared orthogonal residuals (final pass only)
    inliers: BoolArray | None = None    # (final pass only)


def _residuals(b0: F32, dm: F32, offset: float, thr: float, weighted: bool, exponent: float,
               sigma: F32 | None) -> tuple[F32, F32, F32, F32 | None, BoolArray]:
    """Whitened range residuals of points with ``b0 = p·n`` (N,) and ranges ``dm``.

    Returns ``1/cos``, the predicted range ``t``, the whitened residual ``z``, the
    inverse sigma (None when unweighted) and the inlier mask ``|z| < thr`` (in front).
    """
    f32 = np.float32
    inv_c = np.divide(dm, b0)                  # 1 / cos(ray, normal), negative in front
    t = inv_c * f32(-offset)                   # predicted range along the ray
    z = np.subtract(dm, t)                     # range residual rho ...
    if sigma is not None:
        isig: F32 | None = np.divide(f32(1.0), sigma)
    elif weighted:                             # 1 / (t^e / sqrt|cos|)
        isig = np.multiply(t, inv_c)
        np.abs(isig, out=isig)
        if exponent == 1.5:
            np.sqrt(isig, out=isig)
            isig *= t
        else:
            np.power(isig, f32(0.5), out=isig)
            isig *= np.abs(t) ** f32(exponent - 1.0) * t
        np.divide(f32(1.0), isig, out=isig)
    else:
        isig = None
    if isig is not None:
        z *= isig                              # ... whitened
    inl = np.abs(z) < f32(thr)
    inl &= t > 0
    return inv_c, t, z, isig, inl


def _gn_pass(p: F32, dm: F32, n: FloatArray, e1: FloatArray, e2: FloatArray, offset: float,
             thr: float, weighted: bool, exponent: float, sigma: F32 | None = None,
             final: bool = False, refine: Callable[[BoolArray], BoolArray] | None = None) -> _Pass:
    """One reweighted Gauss-Newton pass of the range model over points ``p`` (3, N).

    The range along the ray ``r = p / |p|`` predicted by the plane is
    ``t = -offset / (r·n)``; the residual ``rho = |p| - t`` has the Jacobian
    ``(t (r·e1) / (r·n), t (r·e2) / (r·n), 1 / (r·n))`` with respect to the normal's
    tangent steps along ``e1``, ``e2`` and the offset. Everything is whitened by the
    point's noise sigma and masked to the inliers, in place on a few float32 buffers.

    Args:
        thr: Cut-off on the noise-normalised range residual.
        sigma: Per-point range-noise sigma (N,), replacing the noise model if given.
        final: Also return the sandwich "meat", the orthogonal residual sum and the
            inlier mask.
        refine: Maps the inlier mask (N,) to the points allowed to stay inliers.
    """
    f32 = np.float32
    basis = np.stack([n, e1, e2]).astype(f32)
    b = basis @ p                              # (3, N): p·n, p·e1, p·e2
    inv_c, t, z, isig, inl = _residuals(b[0], dm, offset, thr, weighted, exponent, sigma)
    if refine is not None:
        inl &= refine(inl)
    n_in = int(np.count_nonzero(inl))
    if n_in < MIN_POINTS:
        raise CalibrationError(f"full-frame fit found only {n_in} inlier(s); no plane is defined")
    z *= inl                                   # r: whitened, masked residual
    if isig is None:
        isig = inl.astype(f32)
    else:
        isig *= inl                            # masked 1 / sigma
    t *= inv_c
    t /= dm
    t *= isig                                  # q = t / (|p| cos) / sigma
    a1 = np.multiply(t, b[1])                  # whitened Jacobian columns
    a2 = np.multiply(t, b[2], out=t)
    a3 = np.multiply(inv_c, isig, out=inv_c)
    cols = (a1, a2, a3)
    h = np.empty((3, 3))
    g = np.empty(3)
    for i in range(3):
        g[i] = float(np.dot(cols[i], z))
        for k in range(i, 3):
            h[i, k] = h[k, i] = float(np.dot(cols[i], cols[k]))
    try:
        step = np.asarray(-np.linalg.solve(h, g), dtype=np.float64)
    except np.linalg.LinAlgError:
        raise CalibrationError("full-frame fit is degenerate: the inliers do not span a plane") from None
    z2 = float(np.dot(z, z))
    if not final:
        return _Pass(step, h, n_in, z2)
    rz = [np.multiply(c, z, out=c if c is not a1 else None) for c in cols]
    meat = np.empty((3, 3))
    for i in range(3):
        for k in range(i, 3):
            meat[i, k] = meat[k, i] = float(np.dot(rz[i], rz[k]))
    ortho = np.add(b[0], f32(offset), out=isig)
    ortho *= inl
    return _Pass(step, h, n_in, z2, meat, float(np.dot(ortho, ortho)), inl)


def _hypothesis(p: F32, settings: FullFrameSettings, rng: np.random.Generator) -> tuple[FloatArray, float]:
    """Best triplet plane by the quantile of normalised orthogonal residuals (unit n, offset)."""
    n_pts = p.shape[1]
    m = min(n_pts, settings.sample_points)
    sub = np.take(p, rng.integers(0, n_pts, m), axis=1).T.astype(np.float64)
    idx = rng.integers(0, m, size=(3, settings.hypotheses))
    a = sub[idx[0]]
    u = sub[idx[1]] - a
    v = sub[idx[2]] - a
    nrm = np.empty_like(u)
    nrm[:, 0] = u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1]
    nrm[:, 1] = u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2]
    nrm[:, 2] = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
    length = np.sqrt(np.einsum("ij,ij->i", nrm, nrm))
    ok = length > 1e-9 * np.einsum("ij,ij->i", u, u)
    if not ok.any():
        raise CalibrationError("full-frame fit: the points are collinear or coincident; no plane is defined")
    nrm = nrm[ok] / length[ok, None]
    off = -np.einsum("ij,ij->i", nrm, a[ok])
    sub32 = sub.astype(np.float32)
    res = nrm.astype(np.float32) @ sub32.T                # (K, m) orthogonal distances
    res += off.astype(np.float32)[:, None]
    np.abs(res, out=res)
    if settings.weighted:                                  # noise grows with the range
        rng_m = np.sqrt(np.einsum("ij,ij->i", sub32, sub32))
        res /= rng_m ** np.float32(settings.noise_distance_exponent)
    k = min(int(settings.hypothesis_quantile * m), m - 1)
    score = np.partition(res, k, axis=1)[:, k]
    j = int(np.argmin(score))
    n = nrm[j]
    d = float(off[j])
    if d < 0:
        n, d = -n, -d
    return n, d


def _subsample(limit: int, *arrays: F32) -> list[F32]:
    """Every k-th point (last axis; contiguous copies) so that at most ``limit`` remain."""
    step = -(-arrays[0].shape[-1] // limit)
    if step <= 1:
        return list(arrays)
    return [np.ascontiguousarray(a[..., ::step]) for a in arrays]


@dataclass
class _Fit:
    plane: Plane
    cov: FloatArray           # covariance of (d_e1, d_e2, d_offset)
    e1: FloatArray
    e2: FloatArray
    inliers: BoolArray
    residual_rms_m: float
    noise_scale_m: float


def _robust_fit(p: F32, dm: F32, settings: FullFrameSettings, sigma: F32 | None = None,
                refine_mask: Callable[[BoolArray], BoolArray] | None = None) -> _Fit:
    """The three stages on finite camera-frame points ``p`` (3, N) with ranges ``dm``.

    ``sigma`` (N,), if given, is each point's range-noise sigma (replaces the model).
    ``refine_mask`` maps the inlier mask (N,) of the converged plane to the points
    allowed in the last pass (image-space clean-up, see ``edge_margin_deg``).
    """
    rng = np.random.default_rng(settings.seed)
    n, offset = _hypothesis(p, settings, rng)
    k_sig = settings.inlier_threshold_sigma
    kept_var, cov_factor = _truncation(k_sig)
    if sigma is None:
        ps, ds = _subsample(settings.refine_points, p, dm)
        ss = None
    else:
        ps, ds, ss = _subsample(settings.refine_points, p, dm, sigma)
    weighted = settings.weighted
    expo = settings.noise_distance_exponent

    # initial robust scale of the normalised range residuals on <= 1024 of the points
    e1, e2 = _basis(n)
    k0 = max(1, ps.shape[1] // 1024)
    p0, d0 = ps[:, ::k0], ds[::k0]
    inv_c = d0 / (n.astype(np.float32) @ p0)
    t = inv_c * np.float32(-offset)
    z = d0 - t
    sig_med = 1.0
    if ss is not None:
        sig = ss[::k0]
        z /= sig
    elif weighted:
        sig = (np.abs(t) ** np.float32(expo) / np.sqrt(np.abs(inv_c))).astype(np.float32)
        z /= sig
    if ss is not None or weighted:
        mid = sig.size // 2
        sig_med = max(float(np.partition(sig, mid)[mid]), 1e-12)
    q = settings.hypothesis_quantile
    az = np.abs(z)
    kq = min(int(q * az.size), az.size - 1)
    s = float(np.partition(az, kq)[kq]) / float(ndtri(0.5 + q / 2.0))
    lo = settings.min_inlier_threshold_m / sig_med
    hi = settings.max_inlier_threshold_m / sig_med

    def threshold(scale: float) -> float:
        return min(max(k_sig * scale, lo), hi)

    for _ in range(settings.max_iterations):
        it = _gn_pass(ps, ds, n, e1, e2, offset, threshold(s), weighted, expo, ss)
        n_new = n + it.step[0] * e1 + it.step[1] * e2
        n = n_new / np.linalg.norm(n_new)
        offset += float(it.step[2])
        e1, e2 = _basis(n)
        s_new = math.sqrt(it.z2_sum / it.n_inliers / kept_var)
        # converged: the step is a small fraction of the parameters' (subsample) sigma
        # and the scale has settled (noise-free data: the cut-off sits at its floor);
        # the full-data pass below finishes the job
        floor_scale = lo / k_sig
        try:
            sd = np.sqrt(np.abs(np.diag(np.linalg.inv(it.hessian)))) * max(s_new, floor_scale)
        except np.linalg.LinAlgError:
            sd = np.full(3, np.inf)
        settled = abs(s_new - s) <= 0.15 * s or max(s, s_new) <= floor_scale
        converged = bool(np.all(np.abs(it.step) <= 0.5 * sd)) and settled
        s = s_new
        if converged:
            break
    # the last pass over every point
    fin = _gn_pass(p, dm, n, e1, e2, offset, threshold(s), weighted, expo, sigma, final=True, refine=refine_mask)
    assert fin.meat is not None and fin.inliers is not None
    n_fin = n + fin.step[0] * e1 + fin.step[1] * e2
    n_fin = n_fin / np.linalg.norm(n_fin)
    offset_fin = offset + float(fin.step[2])
    try:
        h_inv = np.linalg.inv(fin.hessian)
    except np.linalg.LinAlgError:
        raise CalibrationError("full-frame fit is degenerate: the inliers do not span a plane") from None
    dof = max(fin.n_inliers - 3, 1)
    cov = h_inv @ fin.meat @ h_inv * (fin.n_inliers / dof) * cov_factor
    plane = Plane(n_fin, offset_fin)
    rms = math.sqrt(fin.ortho2_sum / fin.n_inliers)
    noise = math.sqrt(fin.z2_sum / fin.n_inliers / kept_var)
    return _Fit(plane, cov, e1, e2, fin.inliers, rms, noise)


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


def _derived(fit: _Fit) -> tuple[list[float], list[float]]:
    """Angle, tilt x, tilt y, height and their 1-sigma (central-difference Jacobians)."""
    n0 = fit.plane.normal
    d0 = fit.plane.offset_m
    steps = np.array([1e-6, 1e-6, 1e-6 * max(abs(d0), 1e-3)])
    dp = np.concatenate([np.zeros((1, 3)), np.diag(steps), -np.diag(steps)])   # (7, 3)
    nn = n0 + dp[:, :1] * fit.e1 + dp[:, 1:2] * fit.e2
    norm = np.linalg.norm(nn, axis=1)
    v = _geometry(nn / norm[:, None], (d0 + dp[:, 2]) / norm)
    jac = ((v[1:4] - v[4:7]) / (2.0 * steps[:, None])).T                      # (4, 3)
    var = np.einsum("ij,jk,ik->i", jac, fit.cov, jac)
    return v[0].tolist(), np.sqrt(np.maximum(var, 0.0)).tolist()


def _interval(value: float, sigma: float, z: float, lo: float = -math.inf, hi: float = math.inf
              ) -> tuple[float, float]:
    return (max(value - z * sigma, lo), min(value + z * sigma, hi))


def _coverage(mask: BoolArray, settings: FullFrameSettings) -> float:
    """Fraction of grid cells with at least ``min_cell_inlier_fraction`` inliers."""
    h, w = mask.shape
    cols, rows = settings.coverage_grid
    rows, cols = min(rows, h), min(cols, w)
    r_edges = (np.arange(rows) * h) // rows
    c_edges = (np.arange(cols) * w) // cols
    per_row = np.add.reduceat(mask.view(np.uint8), r_edges, axis=0, dtype=np.int32)
    counts = np.add.reduceat(per_row, c_edges, axis=1)
    r_size = np.diff(np.append(r_edges, h))
    c_size = np.diff(np.append(c_edges, w))
    area = np.outer(r_size, c_size)
    return float(np.mean(counts >= settings.min_cell_inlier_fraction * area))


def _assemble(fit: _Fit, settings: FullFrameSettings, *, n_points: int, valid_fraction: float,
              inlier_mask: BoolArray, coverage: float, n_frames: int) -> FullFrameResult:
    (angle, tx, ty, height), (s_a, s_x, s_y, s_h) = _derived(fit)
    z = float(ndtri(0.5 + settings.confidence / 2.0))
    e = np.stack([fit.e1, fit.e2], axis=1)
    cov_n = e @ fit.cov[:2, :2] @ e.T
    cov_nd = e @ fit.cov[:2, 2]
    n_in = int(np.count_nonzero(fit.inliers))
    inlier_fraction = n_in / n_points
    gates = _gate_table(settings, valid_fraction, inlier_fraction, fit.residual_rms_m, coverage)
    return FullFrameResult(
        plane=fit.plane,
        angle_rad=angle, angle_sigma_rad=s_a, angle_ci_rad=_interval(angle, s_a, z, 0.0, math.pi / 2),
        tilt_x_rad=tx, tilt_x_sigma_rad=s_x, tilt_x_ci_rad=_interval(tx, s_x, z),
        tilt_y_rad=ty, tilt_y_sigma_rad=s_y, tilt_y_ci_rad=_interval(ty, s_y, z),
        height_m=height, height_sigma_m=s_h, height_ci_m=_interval(height, s_h, z),
        confidence=settings.confidence,
        normal_covariance=cov_n, offset_variance_m2=float(fit.cov[2, 2]), normal_offset_covariance=cov_nd,
        valid_fraction=valid_fraction, inlier_fraction=inlier_fraction, residual_rms_m=fit.residual_rms_m,
        coverage=coverage, noise_scale_m=fit.noise_scale_m, n_points=n_points, n_inliers=n_in,
        n_frames=n_frames, inlier_mask=inlier_mask, gates=gates)


# ---------------------------------------------------------------------- public API
def fit_plane_points(points_m: ArrayLike, sigma_m: ArrayLike | None = None,
                     settings: FullFrameSettings | None = None) -> FullFrameResult:
    """Robust full-cloud plane fit of raw camera-frame points.

    The sensor must be at the origin (ranges are measured along the rays through it).

    Args:
        points_m: Shape (N, 3), camera frame, metres; rows with NaN/inf are skipped.
        sigma_m: Optional per-point range-noise sigma, metres, shape (N,): replaces the
            noise model's weights (rows with sigma <= 0 or non-finite are skipped).
        settings: Fit settings and gates; None uses the defaults.

    Returns:
        The result; ``inlier_mask`` has shape (N,), ``coverage`` is NaN (no image) and
        there is no coverage gate; ``valid_fraction`` counts finite rows.

    Raises:
        CalibrationError: Wrong shape or type, or no plane can be defined.
        CalibrationQualityError: Fewer than 16 usable points (gate ``valid_fraction``).
    """
    cfg = settings or FullFrameSettings()
    try:
        pts = np.asarray(points_m, dtype=np.float32)
    except (TypeError, ValueError):
        raise CalibrationError("points_m must be a numeric (N, 3) array") from None
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise CalibrationError(f"points_m must have shape (N, 3), got {pts.shape}")
    n_all = pts.shape[0]
    with np.errstate(invalid="ignore", over="ignore"):
        dm = np.sqrt(np.einsum("ij,ij->i", pts, pts))
    ok = np.isfinite(dm) & (dm > 0)
    sig: F32 | None = None
    if sigma_m is not None:
        try:
            sig = np.asarray(sigma_m, dtype=np.float32).reshape(-1)
        except (TypeError, ValueError):
            raise CalibrationError("sigma_m must be a numeric (N,) array") from None
        if sig.shape != (n_all,):
            raise CalibrationError(f"sigma_m must have shape ({n_all},), got {np.shape(sigma_m)}")
        ok &= np.isfinite(sig) & (sig > 0)
    n_ok = int(np.count_nonzero(ok))
    valid_fraction = n_ok / n_all if n_all else 0.0
    if n_ok < MIN_POINTS:
        raise CalibrationQualityError("valid_fraction", valid_fraction, cfg.min_valid_fraction,
                                      f"only {n_ok} usable point(s); a full-frame fit needs {MIN_POINTS}")
    p = np.ascontiguousarray(pts[ok].T)
    d = np.ascontiguousarray(dm[ok])
    fit = _robust_fit(p, d, cfg, None if sig is None else np.ascontiguousarray(sig[ok]))
    mask = np.zeros(n_all, dtype=bool)
    mask[ok] = fit.inliers
    return _assemble(fit, cfg, n_points=n_ok, valid_fraction=valid_fraction, inlier_mask=mask,
                     coverage=math.nan, n_frames=1)


def _frames_points(frames: Frame | Sequence[Frame]) -> tuple[list[Frame], F32, F32, list[BoolArray]]:
    """Validate frames; pooled valid points (3, N), ranges (N,) and each frame's flat mask."""
    if isinstance(frames, Frame):
        seq = [frames]
    else:
        try:
            seq = list(frames)
        except TypeError:
            raise CalibrationError(f"expected a Frame or a sequence of frames, got {type(frames).__name__}") from None
    if not seq:
        raise CalibrationError("fit_full_frame needs at least one frame")
    for i, f in enumerate(seq):
        if not isinstance(f, Frame):
            raise CalibrationError(f"frame {i} is a {type(f).__name__}, not a Frame")
        if f.shape != seq[0].shape:
            raise CalibrationError(f"frame {i} has shape {f.shape}, frame 0 has {seq[0].shape}")
    pts, dms, masks = [], [], []
    for f in seq:
        dist = f.distance.reshape(-1)
        with np.errstate(invalid="ignore"):
            m = f.valid.reshape(-1) & (dist > 0)   # NaN compares False
        idx = np.flatnonzero(m)
        p = np.take(f.xyz.reshape(-1, 3).T, idx, axis=1)    # (3, n) structure of arrays
        d = np.take(dist, idx)
        if not (math.isfinite(float(p.sum())) and math.isfinite(float(d.sum()))):
            fin = np.isfinite(p).all(axis=0) & np.isfinite(d)
            m[idx[~fin]] = False
            p, d = np.ascontiguousarray(p[:, fin]), d[fin]
        pts.append(p)
        dms.append(d)
        masks.append(m)
    if len(seq) == 1:
        return seq, pts[0], dms[0], masks
    return seq, np.concatenate(pts, axis=1), np.concatenate(dms), masks


def _edge_keep(inliers: BoolArray, masks: list[BoolArray], shape: tuple[int, int], margin_px: int) -> BoolArray:
    """Points (pooled order) farther than ``margin_px`` from solid patches of non-plane pixels.

    Per frame: non-plane = outlier or invalid; a morphological opening (3x3) keeps
    patches, dropping isolated outliers (noise tails, random flying pixels); the
    patches grown by ``margin_px`` are excluded.
    """
    h, w = shape
    keep = np.ones(inliers.size, dtype=bool)
    k_open = np.ones((3, 3), np.uint8)
    k_grow = np.ones((2 * margin_px + 1, 2 * margin_px + 1), np.uint8)
    start = 0
    for m in masks:
        k = int(np.count_nonzero(m))
        off_plane = np.ones(h * w, dtype=np.uint8)
        off_plane[m] = ~inliers[start:start + k]
        patches = cv2.morphologyEx(off_plane.reshape(h, w), cv2.MORPH_OPEN, k_open)
        near = cv2.dilate(patches, k_grow).reshape(-1)
        keep[start:start + k] = near[m] == 0
        start += k
    return keep


def fit_full_frame(frames: Frame | Sequence[Frame], settings: FullFrameSettings | None = None) -> FullFrameResult:
    """Fit the measuring plane to every valid pixel of one or more frames of a static camera.

    Frames are pooled (each pixel of each frame is one observation). The fit does not
    raise on a failed gate: see ``result.gates`` or call :func:`check_gates`.

    Args:
        frames: One frame or several of the same camera and pose.
        settings: Fit settings and gates (the ``[full_frame]`` table); None: defaults.

    Returns:
        The plane (camera frame, normal toward the camera) with intervals and gates.

    Raises:
        CalibrationError: Malformed input (not frames, mixed shapes) or no plane defined.
        CalibrationQualityError: Fewer than 16 valid pixels (gate ``valid_fraction``).
    """
    cfg = settings or FullFrameSettings()
    seq, p, dm, masks = _frames_points(frames)
    h, w = seq[0].shape
    n_pixels = h * w * len(seq)
    n_ok = p.shape[1]
    valid_fraction = n_ok / n_pixels
    if n_ok < MIN_POINTS:
        raise CalibrationQualityError("valid_fraction", valid_fraction, cfg.min_valid_fraction,
                                      f"only {n_ok} valid pixel(s); a full-frame fit needs {MIN_POINTS}")
    refine = None
    intr = seq[0].intrinsics
    margin_px = math.ceil(math.radians(cfg.edge_margin_deg) * max(intr.fx, intr.fy) - 1e-9)
    if margin_px > 0:
        def refine(inliers: BoolArray) -> BoolArray:
            return _edge_keep(inliers, masks, (h, w), margin_px)
    fit = _robust_fit(p, dm, cfg, refine_mask=refine)
    if len(seq) == 1:
        flat = np.zeros(h * w, dtype=bool)
        flat[masks[0]] = fit.inliers
        mask = flat.reshape(h, w)
    else:
        inl_count = np.zeros(h * w, dtype=np.int32)
        val_count = np.zeros(h * w, dtype=np.int32)
        start = 0
        for m in masks:
            k = int(np.count_nonzero(m))
            inl_count[m] += fit.inliers[start:start + k]
            val_count += m
            start += k
        mask = ((val_count > 0) & (2 * inl_count >= val_count)).reshape(h, w)
    coverage = _coverage(mask, cfg)
    return _assemble(fit, cfg, n_points=n_ok, valid_fraction=valid_fraction, inlier_mask=mask,
                     coverage=coverage, n_frames=len(seq))
