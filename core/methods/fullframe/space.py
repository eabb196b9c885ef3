"""The measurement space a full-frame fit works in: the one interface the fit consults, and what it returns.

A camera's noise is simple only where it measures: a ToF camera ranges along fixed rays
(:class:`~cellcal.core.methods.fullframe.range_space.RangeSpace`), a stereo or
structured-light camera matches disparities over the image
(:class:`~cellcal.core.methods.fullframe.disparity.DisparitySpace`). A space owns what depends
on that: the residuals and their sigma, the inlier band, the robust start and the refinement,
the quantisation and the floors the honesty checks hold the fit to. The rest of the fit
(pooling the frames, the honesty checks, flatness, coverage, the result) is the same for
every space. A new kind of measurement (structured light with its own noise, a depth
correction) is one new class with this interface. Rationale: docs/adr/0050-measurement-spaces.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar, Protocol

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import Plane

if TYPE_CHECKING:
    from cellcal.core.methods.fullframe.points import ExpectedPlane, Points, Sample
    from cellcal.core.methods.fullframe.systematic import Response

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
F32 = NDArray[np.float32]

__all__ = ["EdgeReport", "Floors", "MeasurementSpace", "Model", "SpaceFit"]


@dataclass(frozen=True)
class Model:
    """How range residuals are normalised: the noise law's exponent, or given sigmas.

    Attributes:
        weighted: Weight by the noise law ``sigma ∝ t^exponent / sqrt|cos|`` (False: all alike).
        exponent: Exponent of the range in the noise law.
        sigma: (N,) given per-point range sigmas, metres (replace the law), or None.
    """

    weighted: bool
    exponent: float
    sigma: F32 | None = None


@dataclass
class EdgeReport:
    """What the last clean-up dropped.

    Attributes:
        margin_px: Rings (chessboard pixels) dropped around outlier patches.
        floor_px: Rings dropped around any patch (outliers or invalid), whatever the data say.
        n_dropped: Inliers dropped.
    """

    margin_px: int = 0
    floor_px: int = 0
    n_dropped: int = 0


@dataclass
class SpaceFit:
    """A plane fitted in a measurement space, in the shape the rest of the fit takes (metres, radians).

    Attributes:
        plane: The plane, camera frame, normal toward the camera.
        cov: 3x3 covariance of the plane's steps ``(d_e1, d_e2, d_offset)`` (rad², rad², m²).
        e1, e2: The tangent basis of ``cov`` (``passes.basis(plane.normal)``).
        inliers: (N,) bool, the points the plane rests on.
        residual_rms_m: The inliers' RMS orthogonal residual, metres.
        noise_scale_m: The noise scale found (range: sigma at 1 m head-on; disparity: ``sigma_d / (f·B)``), m.
        unit_rms_m: Range space: the inliers' RMS orthogonal residual the noise law predicts per
            metre of sigma at 1 m (NaN elsewhere).
        multipath: Range space: (border bias, its sigma, the plane step it implies) (NaN, NaN, 0 elsewhere).
        resid: Per point whitened residual, 0 off the inliers, while the honesty checks need it (else None).
        expected_rms_m: Disparity space: what the model predicts for the inliers, metres.
        floor_rms_m: Disparity space: their quantisation floor, metres.
        notes: What widened the intervals, in short sentences.
        edge: What the mixed-pixel clean-up dropped (None: no clean-up ran).
    """

    plane: Plane
    cov: FloatArray
    e1: FloatArray
    e2: FloatArray
    inliers: BoolArray
    residual_rms_m: float
    noise_scale_m: float
    unit_rms_m: float
    multipath: tuple[float, float, FloatArray]
    resid: F32 | None = None
    expected_rms_m: float = math.nan
    floor_rms_m: float = math.nan
    notes: tuple[str, ...] = ()
    edge: EdgeReport | None = None


@dataclass(frozen=True)
class Floors:
    """What the sensor can deliver for a fit's inliers: the references of the honesty checks.

    Attributes:
        floor_m: RMS orthogonal quantisation floor of the inliers, metres (0: no stated step).
        expected_m: The RMS orthogonal residual the sensor model expects for them, metres.
        stated: The sensor stated its noise, so that ``expected_m`` is a floor as well.
        multipath_m: The camera's multipath allowance, metres.
        depth: (N,) what the sensor quantises, per point, metres (the lock-on check looks at its levels).
        resid: (N,) residuals, 0 off the inliers, whose spatial correlation widens the intervals;
            None when the space has already allowed for it in its own units.
        notes: The space's own sentences on the intervals (before the shared ones).
    """

    floor_m: float
    expected_m: float
    stated: bool
    multipath_m: float
    depth: F32
    resid: F32 | None
    notes: tuple[str, ...] = ()


class MeasurementSpace(Protocol):
    """Where a camera measures, and how a plane is fitted there.

    Attributes:
        name: ``FullFrameResult.native_space`` ("range", "disparity").
    """

    name: ClassVar[str]

    @property
    def noise_shape(self) -> Model:
        """The range-noise shape the flatness gate weights local planes with (the scale is the fit's)."""
        ...

    def fit(self, points: Points, expected: ExpectedPlane | None) -> SpaceFit:
        """Robust start, refinement and covariance of the plane in this space.

        Args:
            points: The pooled valid points (camera frame, metres).
            expected: Only planes within its tolerances may start the fit (None: the dominant plane).

        Raises:
            CalibrationError: No plane is defined.
            CalibrationQualityError: ``expected_plane`` (no plane near the expected one), or
                ``valid_fraction`` (too few points left after a clean-up).
        """
        ...

    def floors(self, fit: SpaceFit, points: Points, sample: Sample) -> Floors:
        """The quantisation floor and the expected RMS of the inliers (``sample``: a strided sample of them)."""
        ...

    def response(self, fit: SpaceFit, points: Points, sample: Sample) -> Response:
        """How the fitted plane answers a perturbation of what the camera measures (ADR 0059).

        ``sample``: a strided sample of the inliers; the fit's own Jacobian and weights there.
        """
        ...
