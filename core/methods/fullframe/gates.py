"""Quality gates of a full-frame fit: the gate table, :func:`check_gates` and image coverage."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from cellcal.core.methods.fullframe.result import FullFrameResult
from cellcal.core.methods.fullframe.settings import FullFrameSettings
from cellcal.devices.errors import CalibrationQualityError

__all__ = ["GATE_NAMES", "check_gates"]

#: Gate names in the order they are checked.
#: Flatness comes early: a second surface (a step, a roof) also halves the inliers and the coverage,
#: and naming it says why.
GATE_NAMES = ("valid_fraction", "flatness", "inlier_fraction", "residual_rms_m", "coverage")

#: Gate name -> (what is measured, how it failed, display unit) for the error message.
_GATE_TEXT = {
    "valid_fraction": ("valid pixels", "below the minimum", "%"),
    "inlier_fraction": ("plane inliers among the valid pixels", "below the minimum", "%"),
    "residual_rms_m": ("inlier residual RMS", "above the maximum", "mm"),
    "coverage": ("image cells holding plane inliers", "below the minimum", "%"),
    "flatness": ("a local plane departs from the global fit (beyond its uncertainty) by", "above the tolerance",
                 "mm"),
}


def residual_threshold_m(settings: FullFrameSettings, unit_rms_m: float, sigma_given: bool) -> float:
    """The ``residual_rms_m`` gate's threshold: ``max_noise_ratio`` times the expected RMS, capped.

    Args:
        settings: ``max_noise_ratio``, ``expected_noise_m`` and the optional cap ``max_residual_rms_m``.
        unit_rms_m: The inliers' RMS orthogonal residual the noise model predicts per metre
            of noise at 1 m (with given sigmas: the RMS they predict, metres).
        sigma_given: The fit used per-point sigmas (then ``expected_noise_m`` does not apply).
    """
    expected = unit_rms_m * (1.0 if sigma_given else settings.expected_noise_m)
    threshold = float(settings.max_noise_ratio * expected)
    if settings.max_residual_rms_m is not None:
        threshold = min(threshold, settings.max_residual_rms_m)
    return threshold


def gate_table(settings: FullFrameSettings, valid_fraction: float, inlier_fraction: float,
               residual_rms_m: float, unit_rms_m: float, sigma_given: bool, coverage: float,
               flatness_m: float) -> dict[str, tuple[float, float, bool]]:
    """Gate name -> (value, threshold, passed); coverage and flatness are skipped when NaN (no image)."""
    rms_max = residual_threshold_m(settings, unit_rms_m, sigma_given)
    gates = {
        "valid_fraction": (valid_fraction, settings.min_valid_fraction,
                           valid_fraction >= settings.min_valid_fraction),
        "inlier_fraction": (inlier_fraction, settings.min_inlier_fraction,
                            inlier_fraction >= settings.min_inlier_fraction),
        "residual_rms_m": (residual_rms_m, rms_max, residual_rms_m <= rms_max),
    }
    if math.isfinite(coverage):
        gates["coverage"] = (coverage, settings.min_coverage, coverage >= settings.min_coverage)
    if math.isfinite(flatness_m):
        gates["flatness"] = (flatness_m, settings.flatness_tolerance_m, flatness_m <= settings.flatness_tolerance_m)
    return gates


def _message(name: str, value: float, threshold: float, result: FullFrameResult,
             settings: FullFrameSettings) -> str:
    what, side, unit = _GATE_TEXT[name]
    k = 1000.0 if unit == "mm" else 100.0
    unit_s = " mm" if unit == "mm" else " %"
    text = (f"{what} {value * k:.3g}{unit_s}, {abs(value - threshold) * k:.3g}{unit_s} {side} of "
            f"{threshold * k:.3g}{unit_s}")
    expected = result.residual_unit_rms_m * (1.0 if result.sigma_given else settings.expected_noise_m)
    if name == "residual_rms_m" and expected > 0:
        text += f" ({value / expected:.3g} x the {expected * 1000.0:.3g} mm the noise model expects for these pixels)"
    elif name == "flatness" and result.flatness_where:
        text += f" (in {result.flatness_where})"
    return text


def check_gates(result: FullFrameResult, settings: FullFrameSettings | None = None) -> None:
    """Raise for the first quality gate the result fails.

    Args:
        result: A fit from :func:`fit_full_frame` or :func:`fit_plane_points`.
        settings: Thresholds to apply; None re-applies the ones the fit was made with.
            (``flatness_grid`` and ``flatness_sigma`` shape the measured value: changing
            them needs a new fit.)

    Raises:
        CalibrationQualityError: Naming the gate, the value, the threshold and by how
            much it was missed.
    """
    cfg = settings or result.settings
    gates = result.gates if settings is None else gate_table(
        settings, result.valid_fraction, result.inlier_fraction, result.residual_rms_m,
        result.residual_unit_rms_m, result.sigma_given, result.coverage, result.flatness_m)
    for name in GATE_NAMES:
        if name not in gates:
            continue
        value, threshold, ok = gates[name]
        if not ok:
            raise CalibrationQualityError(name, value, threshold, _message(name, value, threshold, result, cfg))


def image_coverage(mask: NDArray[np.bool_], settings: FullFrameSettings) -> float:
    """Fraction of the ``coverage_grid`` cells with at least ``min_cell_inlier_fraction`` inliers.

    Args:
        mask: (H, W) inlier mask of the image.
        settings: Grid and per-cell threshold.
    """
    h, w = mask.shape
    cols, rows = settings.coverage_grid
    rows, cols = min(rows, h), min(cols, w)              # no more cells than pixels
    r_edges = (np.arange(rows) * h) // rows              # first row / column of each cell
    c_edges = (np.arange(cols) * w) // cols
    per_row = np.add.reduceat(mask.view(np.uint8), r_edges, axis=0, dtype=np.int32)
    counts = np.add.reduceat(per_row, c_edges, axis=1)   # inliers per cell
    r_size = np.diff(np.append(r_edges, h))
    c_size = np.diff(np.append(c_edges, w))
    area = np.outer(r_size, c_size)                      # pixels per cell
    return float(np.mean(counts >= settings.min_cell_inlier_fraction * area))
