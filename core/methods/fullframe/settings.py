"""The ``[full_frame]`` configuration table: the full-frame fit's knobs and quality gates."""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["MIN_POINTS", "FullFrameSettings"]

#: A fit needs at least this many valid points.
MIN_POINTS = 16


@dataclass(frozen=True)
class FullFrameSettings:
    """The ``[full_frame]`` configuration table: the fit's knobs and its quality gates.

    Attributes:
        weighted: Weight points by the range-noise model (ADR 0007, "Weighting").
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
