"""What a full-frame fit returns: :class:`FullFrameResult` and its :class:`Estimate` values."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe.settings import FullFrameSettings
from cellcal.core.methods.fullframe.systematic import ErrorBudget
from cellcal.devices.measurement import UNKNOWN_MODEL, MeasurementModel

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = ["Estimate", "FullFrameResult", "IntervalFactors"]


@dataclass(frozen=True)
class Estimate:
    """A derived quantity with its 1-sigma and its confidence interval.

    Attributes:
        value: The estimate, SI units (radians or metres).
        sigma: Its 1-sigma, same unit.
        interval: ``(lo, hi)`` at the result's confidence, same unit.
    """

    value: float
    sigma: float
    interval: tuple[float, float]

    @classmethod
    def from_sigma(cls, value: float, sigma: float, z: float, lo: float = -math.inf,
                   hi: float = math.inf) -> Estimate:
        """``value ± z sigma`` clipped to ``[lo, hi]`` (``z``: normal quantile of the confidence)."""
        return cls(value, sigma, (max(value - z * sigma, lo), min(value + z * sigma, hi)))

    def to_dict(self, name: str, unit: str, convert: Callable[[float], Any]) -> dict[str, Any]:
        """``{name_unit, name_sigma_unit, name_ci_unit}`` with every number passed through ``convert``."""
        lo, hi = self.interval
        return {f"{name}_{unit}": convert(self.value), f"{name}_sigma_{unit}": convert(self.sigma),
                f"{name}_ci_{unit}": [convert(lo), convert(hi)]}


def _finite_or_none(v: float) -> float | None:
    return v if math.isfinite(v) else None


@dataclass(frozen=True)
class IntervalFactors:
    """What widened the intervals beyond the fit's own covariance (1.0 / False: nothing).

    Attributes:
        observed_scale: The inliers' RMS residual over the RMS the sensor model expects
            (NaN when it states none). On the range path the sandwich covariance is built from
            the observed residuals, so it already carries this scale when it exceeds 1.
        spatial: Variance factor (>= 1) for residuals correlated across neighbouring pixels:
            the design effect of blocks of pixels (block sums' mean square over the sum of
            the squares), applied when significant.
        quantisation: Whether the quantisation floor (``residual_floor_m`` spread over the
            inliers' extent) widened the covariance.
        systematic: What systematic depth errors do to the plane (a 1 % depth scale, a 1 mm depth
            offset) and what the camera's systematic allowance added to the covariance
            (:class:`~cellcal.core.methods.fullframe.systematic.ErrorBudget`; None: not computed).
    """

    observed_scale: float = math.nan
    spatial: float = 1.0
    quantisation: bool = False
    systematic: ErrorBudget | None = field(default=None, compare=False)

    @property
    def allowance(self) -> bool:
        """Whether the camera's systematic allowance widened the covariance."""
        return self.systematic is not None and self.systematic.widened

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {"observed_scale": _finite_or_none(self.observed_scale), "spatial": self.spatial,
                "quantisation": self.quantisation, "systematic_allowance": self.allowance}


@dataclass(frozen=True, eq=False)
class FullFrameResult:
    """A full-frame plane fit with uncertainty and quality-gate values.

    Angles in radians, lengths in metres; intervals are ``(lo, hi)`` at ``confidence``.
    The flat names of the estimates (``angle_rad``, ``angle_sigma_rad``, ``angle_ci_rad``,
    ``tilt_x_*``, ``tilt_y_*``, ``height_m``, ``height_sigma_m``, ``height_ci_m``) are
    read-only properties over the :class:`Estimate` fields.

    Attributes:
        plane: The plane in the camera frame, normal toward the camera.
        angle: Angle between the plane and the optical axis (pi/2 looking straight),
            rad; interval clipped to [0, pi/2].
        tilt_x: Camera tilt about its x axis (:meth:`Plane.tilt_about_x_rad`), rad.
        tilt_y: Same about y, rad.
        height: Distance from the optical centre along the optical axis to the plane,
            metres (NaN when the axis misses the plane).
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
        residual_unit_rms_m: The inliers' RMS orthogonal residual the noise model predicts
            per metre of range-noise sigma at 1 m (with given sigmas: the RMS they
            predict, metres); ``expected_noise_m`` times it is the expected RMS.
        sigma_given: Per-point sigmas replaced the noise model.
        flatness_m: Largest departure of a local plane from the global fit beyond
            ``flatness_sigma`` of its uncertainty, metres (0 when none departs; NaN for
            raw point clouds).
        flatness_where: The region of that departure ("" when none departs).
        multipath: Range bias at the image border relative to the centre (growing with
            the squared image radius), estimated from the residual pattern, metres: a
            bias such as multipath, which the intervals do not cover.
        multipath_shift: How much each value (``angle_rad``, ``tilt_x_rad``,
            ``tilt_y_rad``, ``height_m``) would change if that radial pattern were
            fitted as a bias: the size of the error it may cause.
        mixed_margin_px: Rings of pixels dropped around outlier patches (mixed pixels).
        n_mixed: Inliers dropped near depth edges and invalid patches.
        settings: The settings of the fit.
        measurement: The camera's measurement model the fit used (the frames').
        native_space: Where the fit measured residuals: ``"range"`` (along the rays) or
            ``"disparity"`` (stereo and structured light).
        residual_expected_m: The inliers' RMS orthogonal residual the sensor model predicts
            (its noise, or ``expected_noise_m``, and its quantisation), metres.
        residual_floor_m: The least RMS orthogonal residual the sensor can deliver for these
            inliers: the quantisation step ``q/sqrt(12)`` projected across the plane, metres
            (0 when the camera states no step).
        sigma_stated: The camera (or the caller's sigmas) stated its noise, so that
            ``residual_expected_m`` is a floor as well (gate ``residual_floor``).
        multipath_allowance_m: The camera's multipath allowance added to the
            ``residual_rms_m`` gate's threshold, metres.
        lock_on: Why the fit sat on one quantisation level ("" when it did not).
        expected_departure: Angle (rad) and offset difference (m) of the plane from the
            expected one (None without one).
        expected_tolerance: The expected plane's tolerances (rad, m) (None without one).
        region_pixels: Pixels of the region of interest (all frames; the whole image without one).
        interval_factors: What widened the intervals (:class:`IntervalFactors`).
        interval_notes: Short sentences saying so, for reports.
        noise_normal_covariance: The part of ``normal_covariance`` from the fit's noise alone (3x3),
            without the camera's systematic allowance; equal to it when nothing systematic was added.
        noise_offset_sigma_m: Same for :attr:`offset_sigma_m`, metres.
        noise_normal_offset_covariance: Same for ``normal_offset_covariance`` (3,), m.
        systematic_shifts: Per term of the camera's systematic allowance (``scale``, ``offset``,
            ``field:<shape>``), its 1-sigma shift of the plane ``(normal_delta (3,), offset_delta_m)``
            in the camera frame (the convention of ``plane.normal`` / ``plane.offset_m``). A term is
            common to every pose of the same camera: consumers that combine poses treat it as one
            coefficient, not as per-pose noise (ADR 0059, "Amended"). The noise part plus the sum of
            the shifts' outer products is the total covariance. Empty without an allowance.
    """

    plane: Plane
    angle: Estimate
    tilt_x: Estimate
    tilt_y: Estimate
    height: Estimate
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
    residual_unit_rms_m: float
    sigma_given: bool
    flatness_m: float
    flatness_where: str
    multipath: Estimate
    multipath_shift: dict[str, float]
    mixed_margin_px: int
    n_mixed: int
    settings: FullFrameSettings
    measurement: MeasurementModel = UNKNOWN_MODEL
    native_space: str = "range"
    residual_expected_m: float = math.nan
    residual_floor_m: float = 0.0
    sigma_stated: bool = False
    multipath_allowance_m: float = 0.0
    lock_on: str = ""
    expected_departure: tuple[float, float] | None = None
    expected_tolerance: tuple[float, float] | None = None
    region_pixels: int = 0
    interval_factors: IntervalFactors = field(default_factory=IntervalFactors)
    interval_notes: tuple[str, ...] = ()
    noise_normal_covariance: FloatArray = field(default_factory=lambda: np.full((3, 3), np.nan))
    noise_offset_sigma_m: float = math.nan
    noise_normal_offset_covariance: FloatArray = field(default_factory=lambda: np.full(3, np.nan))
    systematic_shifts: dict[str, tuple[FloatArray, float]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        """Without a stated noise-only part (NaN), the noise part is the total."""
        if not math.isfinite(self.noise_offset_sigma_m):
            object.__setattr__(self, "noise_normal_covariance", np.array(self.normal_covariance, dtype=np.float64))
            object.__setattr__(self, "noise_offset_sigma_m", self.offset_sigma_m)
            object.__setattr__(self, "noise_normal_offset_covariance",
                               np.array(self.normal_offset_covariance, dtype=np.float64))

    @property
    def angle_rad(self) -> float:
        """Angle between the plane and the optical axis, rad."""
        return self.angle.value

    @property
    def angle_sigma_rad(self) -> float:
        """1-sigma of :attr:`angle_rad`, rad."""
        return self.angle.sigma

    @property
    def angle_ci_rad(self) -> tuple[float, float]:
        """Interval of :attr:`angle_rad` (clipped to [0, pi/2]), rad."""
        return self.angle.interval

    @property
    def tilt_x_rad(self) -> float:
        """Camera tilt about its x axis, rad."""
        return self.tilt_x.value

    @property
    def tilt_x_sigma_rad(self) -> float:
        """1-sigma of :attr:`tilt_x_rad`, rad."""
        return self.tilt_x.sigma

    @property
    def tilt_x_ci_rad(self) -> tuple[float, float]:
        """Interval of :attr:`tilt_x_rad`, rad."""
        return self.tilt_x.interval

    @property
    def tilt_y_rad(self) -> float:
        """Camera tilt about its y axis, rad."""
        return self.tilt_y.value

    @property
    def tilt_y_sigma_rad(self) -> float:
        """1-sigma of :attr:`tilt_y_rad`, rad."""
        return self.tilt_y.sigma

    @property
    def tilt_y_ci_rad(self) -> tuple[float, float]:
        """Interval of :attr:`tilt_y_rad`, rad."""
        return self.tilt_y.interval

    @property
    def height_m(self) -> float:
        """Distance along the optical axis to the plane, metres (NaN if it misses)."""
        return self.height.value

    @property
    def height_sigma_m(self) -> float:
        """1-sigma of :attr:`height_m`, metres."""
        return self.height.sigma

    @property
    def height_ci_m(self) -> tuple[float, float]:
        """Interval of :attr:`height_m`, metres."""
        return self.height.interval

    @property
    def error_budget(self) -> ErrorBudget | None:
        """What a 1 % depth scale and a 1 mm depth offset do to this plane, and the allowance's share (ADR 0059)."""
        return self.interval_factors.systematic

    @property
    def passed(self) -> bool:
        """Whether every gate passed."""
        return all(ok for _, _, ok in self.gates.values())

    @property
    def offset_sigma_m(self) -> float:
        """1-sigma of ``plane.offset_m``, metres."""
        return math.sqrt(max(self.offset_variance_m2, 0.0))

    @property
    def noise_ratio(self) -> float:
        """The inliers' RMS residual over the RMS the sensor model (or ``expected_noise_m``) predicts for them."""
        e = self.residual_expected_m
        return self.residual_rms_m / e if e > 0 else math.nan

    def to_dict(self) -> dict[str, Any]:
        """JSON form: degrees and metres for humans."""
        num = _finite_or_none
        shift = self.multipath_shift
        return {
            "method": "full_frame",
            **self.angle.to_dict("angle", "deg", math.degrees),
            **self.tilt_x.to_dict("tilt_x", "deg", math.degrees),
            **self.tilt_y.to_dict("tilt_y", "deg", math.degrees),
            **self.height.to_dict("height", "m", num),
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
            "noise_ratio": num(self.noise_ratio),
            "flatness_m": num(self.flatness_m),
            "flatness_where": self.flatness_where,
            **self.multipath.to_dict("multipath_border", "m", num),
            "multipath_shift": {"angle_deg": math.degrees(shift["angle_rad"]),
                                "tilt_x_deg": math.degrees(shift["tilt_x_rad"]),
                                "tilt_y_deg": math.degrees(shift["tilt_y_rad"]), "height_m": shift["height_m"]},
            "mixed_margin_px": self.mixed_margin_px,
            "n_mixed": self.n_mixed,
            "measurement": self.measurement.to_dict(),
            "native_space": self.native_space,
            "residual_expected_m": num(self.residual_expected_m),
            "residual_floor_m": self.residual_floor_m,
            "multipath_allowance_m": self.multipath_allowance_m,
            "lock_on": self.lock_on,
            "expected_departure": None if self.expected_departure is None else
            {"angle_deg": math.degrees(self.expected_departure[0]), "offset_m": self.expected_departure[1]},
            "interval_factors": self.interval_factors.to_dict(),
            "interval_notes": list(self.interval_notes),
            "error_budget": None if self.error_budget is None else self.error_budget.to_dict(),
            "noise_normal_covariance": np.asarray(self.noise_normal_covariance).tolist(),
            "noise_offset_sigma_m": self.noise_offset_sigma_m,
            "noise_normal_offset_covariance": np.asarray(self.noise_normal_offset_covariance).tolist(),
            "systematic_shifts": {k: {"normal": [float(x) for x in n], "offset_m": float(c)}
                                  for k, (n, c) in self.systematic_shifts.items()},
        }
