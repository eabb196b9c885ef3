"""The full-frame fit as a pipeline over a measurement space: points, space, honesty, flatness, result.

Points are in the camera frame (OpenCV: x right, y down, z along the optical axis), metres,
with the sensor at the origin; the fitted normal points toward the camera (``offset_m > 0``).
The frames' measurement model chooses the space the plane is fitted in (``space.py``): a
stereo or structured-light camera's disparities (``disparity.py``), else ranges along the
rays (``range_space.py``). Method and rationale: docs/adr/0007-full-frame-fit.md; region of
interest, expected plane, quantisation floor: docs/adr/0028-honest-full-frame-fit.md; the
spaces: docs/adr/0047-measurement-spaces.md.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellcal.core.methods.fullframe.assemble import Extras, assemble
from cellcal.core.methods.fullframe.disparity import DisparitySpace
from cellcal.core.methods.fullframe.expected import ExpectedPlane
from cellcal.core.methods.fullframe.flatness import fit_flatness
from cellcal.core.methods.fullframe.gates import image_coverage
from cellcal.core.methods.fullframe.honesty import allow_rounding, honest_intervals
from cellcal.core.methods.fullframe.passes import Model
from cellcal.core.methods.fullframe.points import cloud_points, frame_points, pixel_inliers
from cellcal.core.methods.fullframe.range_space import RangeSpace
from cellcal.core.methods.fullframe.result import FullFrameResult
from cellcal.core.methods.fullframe.settings import FullFrameSettings
from cellcal.core.methods.fullframe.space import MeasurementSpace
from cellcal.devices.measurement import UNKNOWN_MODEL
from cellcal.devices.types import Frame

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
    flat, honest = allow_rounding(fit_flatness(fit, data, space.noise_shape, cfg), honest, fit.residual_rms_m)
    mask = pixel_inliers(fit.inliers, data.masks, data.shape)
    extras = Extras(image_coverage(mask, cfg, data.region), flat, honest)
    return assemble(fit, cfg, sigma_given=False, n_points=data.n, valid_fraction=data.n / data.n_pixels,
                    inlier_mask=mask, n_frames=len(data.frames), extras=extras)


def _space_of(frame: Frame, settings: FullFrameSettings) -> MeasurementSpace:
    """The space a camera measures in: disparity for stereo and structured light, else range."""
    if frame.measurement.triangulating:
        return DisparitySpace(settings, frame.measurement)
    return RangeSpace.of_camera(frame.measurement, frame.intrinsics, settings)


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
    space = RangeSpace(cfg, Model(cfg.weighted, cfg.noise_exponent(UNKNOWN_MODEL), sigma))
    fit = space.fit(data, None)
    mask = np.zeros(rows.size, dtype=bool)
    mask[rows] = fit.inliers
    return assemble(fit, cfg, sigma_given=sigma is not None, n_points=data.n, valid_fraction=data.n / data.n_pixels,
                    inlier_mask=mask, n_frames=1, extras=Extras())
