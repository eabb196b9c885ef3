"""The ``[full_frame]`` configuration table: the full-frame fit's knobs and quality gates.

The ranges in the field metadata (``gt``, ``ge``, ``lt``, ``le``) are the one place the
limits live: :func:`cellcal.devices.config.parse_section` applies them to a config file
and ``FullFrameSettings.__post_init__`` to a direct construction.
"""

from __future__ import annotations

import dataclasses
import functools
import typing
from dataclasses import dataclass, field
from typing import Any

from cellcal.devices.config import check_value
from cellcal.devices.errors import ConfigError
from cellcal.devices.measurement import MeasurementModel

__all__ = ["DEFAULT_EXPECTED_NOISE_M", "DEFAULT_NOISE_EXPONENT", "MIN_POINTS", "FullFrameSettings"]

#: A fit needs at least this many valid points.
MIN_POINTS = 16
#: Range-noise sigma at 1 m, normal incidence (m) when neither the config nor the camera states one.
DEFAULT_EXPECTED_NOISE_M = 0.0032
#: Exponent of the range in the noise law when neither the config nor the camera states one.
DEFAULT_NOISE_EXPONENT = 1.5


@dataclass(frozen=True)
class FullFrameSettings:
    """The ``[full_frame]`` configuration table: the fit's knobs and its quality gates.

    Attributes:
        weighted: Weight points by the range-noise model (ADR 0007, "Weighting").
        noise_distance_exponent: Exponent ``e`` of the range in the noise model; None: the
            camera's (a ``tof`` measurement model's ``distance_exponent``), else 1.5.
        inlier_threshold_sigma: Inlier cut-off, in robust standard deviations of the
            (noise-normalised) range residual.
        min_inlier_threshold_m: Lower bound of the cut-off at the median pixel's noise,
            metres (keeps noise-free data fittable).
        max_inlier_threshold_m: Upper bound of the cut-off at the median pixel, metres.
        confidence: Confidence level of the reported intervals.
        expected_noise_m: The camera's range-noise sigma at 1 m and normal incidence
            (data sheet), metres: the unit of the residual gate; None: the camera's (a
            ``tof`` measurement model's ``sigma_at_1m_m``), else 3.2 mm.
        max_noise_ratio: Gate ``residual_rms_m``: the inliers' RMS residual may be at most
            this many times what ``expected_noise_m`` predicts for the same pixels (plus
            the camera's multipath allowance).
        min_noise_ratio: Gate ``residual_floor``: the inliers' RMS residual must be at least
            this many times the least the sensor can deliver for them (its quantisation
            floor, or its stated noise when it states one); a fit sitting on one
            quantisation level fails it whatever the ratio.
        max_residual_rms_m: Optional absolute cap of the same gate, metres (None: none).
        min_valid_fraction: Gate: valid pixels / all pixels.
        min_inlier_fraction: Gate: plane pixels (inliers and the mixed pixels dropped near
            depth edges) / valid pixels.
        min_coverage: Gate: fraction of the ``coverage_grid`` cells holding inliers.
        coverage_grid: Cells across and down the image, ``(columns, rows)``.
        min_cell_inlier_fraction: A cell counts as covered when at least this fraction
            of its pixels are inliers.
        flatness_tolerance_m: Gate ``flatness``: how far (metres) a local plane may depart
            from the global fit beyond ``flatness_sigma`` of its own uncertainty.
        flatness_grid: Image cells, ``(columns, rows)``, each fitted with a local plane (and
            the image's halves and quarters made of them).
        flatness_sigma: Uncertainty multiple allowed before the tolerance counts.
        flatness_min_region: Connected off-plane regions at least this fraction of the
            valid pixels that are themselves planar are compared as well (a second table,
            a step, the other side of a roof).
        edge_margin_deg: Inliers within this angle (degrees of view; ``ceil(radians *
            focal length)`` pixels, 2 px at 224x172, 6 px at 1280x800) of a solid (at
            least 3x3 px) patch of outliers or invalid pixels are always dropped; beyond
            it, bands of as many rings around outlier patches are dropped while their
            residuals are biased (mixed pixels, ADR 0007). 0 disables both; raw point
            clouds never use them.
        mixed_ring_sigma: A band of rings around outlier patches is dropped while the
            sum of its residuals is this many standard errors from the clean level.
        hypotheses: Number of random triplet planes of the robust start.
        sample_points: Points scoring the hypotheses (a fixed stratified subsample).
        hypothesis_quantile: Quantile of the residuals that scores a hypothesis.
        refine_points: Points (strided subsample) of the reweighting passes.
        max_iterations: Maximum reweighting passes on the subsample.
        seed: Seed of the random triplets; None: a fixed set. The answer does not
            depend on it (the reweighting grows the scale from below to the smallest
            self-consistent one, ADR 0007 "Robustness").
    """

    weighted: bool = True
    noise_distance_exponent: float | None = field(default=None, metadata={"ge": 0.0, "le": 4.0})
    inlier_threshold_sigma: float = field(default=3.0, metadata={"ge": 1.5, "le": 20.0})
    min_inlier_threshold_m: float = field(default=0.0005, metadata={"ge": 0.0, "le": 0.1})
    max_inlier_threshold_m: float = field(default=0.1, metadata={"gt": 0.0, "le": 10.0})
    confidence: float = field(default=0.95, metadata={"gt": 0.0, "lt": 1.0})
    expected_noise_m: float | None = field(default=None, metadata={"gt": 0.0, "le": 1.0})
    max_noise_ratio: float = field(default=4.0, metadata={"ge": 1.0, "le": 1000.0})
    min_noise_ratio: float = field(default=0.25, metadata={"ge": 0.0, "le": 1.0})
    max_residual_rms_m: float | None = field(default=None, metadata={"gt": 0.0})
    min_valid_fraction: float = field(default=0.5, metadata={"ge": 0.0, "le": 1.0})
    min_inlier_fraction: float = field(default=0.5, metadata={"ge": 0.0, "le": 1.0})
    min_coverage: float = field(default=0.5, metadata={"ge": 0.0, "le": 1.0})
    coverage_grid: tuple[int, int] = field(default=(6, 6), metadata={"ge": 1, "le": 64})
    min_cell_inlier_fraction: float = field(default=0.2, metadata={"ge": 0.0, "le": 1.0})
    flatness_tolerance_m: float = field(default=0.001, metadata={"ge": 0.0, "le": 1.0})
    flatness_grid: tuple[int, int] = field(default=(4, 4), metadata={"ge": 1, "le": 64})
    flatness_sigma: float = field(default=5.0, metadata={"ge": 0.0, "le": 100.0})
    flatness_min_region: float = field(default=0.2, metadata={"gt": 0.0, "le": 1.0})
    edge_margin_deg: float = field(default=0.3, metadata={"ge": 0.0, "le": 10.0})
    mixed_ring_sigma: float = field(default=3.0, metadata={"gt": 0.0, "le": 100.0})
    hypotheses: int = field(default=96, metadata={"ge": 8, "le": 10000})
    sample_points: int = field(default=1024, metadata={"ge": 32, "le": 100000})
    hypothesis_quantile: float = field(default=0.25, metadata={"gt": 0.0, "lt": 1.0})
    refine_points: int = field(default=4096, metadata={"ge": 256, "le": 10_000_000})
    max_iterations: int = field(default=12, metadata={"ge": 1, "le": 100})
    seed: int | None = field(default=None, metadata={"ge": 0})

    def __post_init__(self) -> None:
        hints = _field_types()
        for f in dataclasses.fields(self):   # the config file's checks; store the converted value (int -> float)
            value = check_value(getattr(self, f.name), hints[f.name], f.metadata, f"full_frame.{f.name}")
            object.__setattr__(self, f.name, value)
        if self.max_inlier_threshold_m < self.min_inlier_threshold_m:
            raise ConfigError(f"max_inlier_threshold_m ({self.max_inlier_threshold_m}) must be "
                              f">= min_inlier_threshold_m ({self.min_inlier_threshold_m})", key="full_frame")

    def noise_at_1m_m(self, model: MeasurementModel) -> float:
        """Range-noise sigma at 1 m, normal incidence (m): the config's, else a ToF camera's, else 3.2 mm."""
        if self.expected_noise_m is not None:
            return self.expected_noise_m
        if model.kind == "tof" and model.sigma_at_1m_m is not None:
            return model.sigma_at_1m_m
        return DEFAULT_EXPECTED_NOISE_M


@functools.cache
def _field_types() -> dict[str, Any]:
    """The resolved field types of :class:`FullFrameSettings` (its annotations are strings)."""
    return typing.get_type_hints(FullFrameSettings)
