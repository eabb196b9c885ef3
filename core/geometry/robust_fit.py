"""The robust plane fit: seeded RANSAC with MSAC scoring, then TLS on the inliers (:func:`fit_plane_robust`).

For clouds with clutter off the plane (boxes, the arm, mixed pixels): triplet hypotheses
drawn in vectorised batches and scored on a fixed random subset, the best one's inliers
refit with the total least squares of :mod:`.planes` (its first-order 1-sigma uncertainty
included) until they are stable. Points in metres, any frame; the fitted normal faces the
origin. docs/adr/0007-full-frame-fit.md ("The plane fits of geometry.planes").
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellcal.core.geometry.planes import (
    BoolArray,
    FloatArray,
    Plane,
    PlaneFit,
    check_spread,
    scatter,
    tls_fit,
    validate_points,
)
from cellcal.devices.errors import CalibrationError

__all__ = ["fit_plane_robust"]


def _hypotheses(p: FloatArray, idx: NDArray[np.intp]) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Planes through point triplets: unit normals (K, 3), offsets (K,), valid mask."""
    a, b, c = p[idx[:, 0]], p[idx[:, 1]], p[idx[:, 2]]
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1)
    scale = np.maximum(np.linalg.norm(b - a, axis=1) * np.linalg.norm(c - a, axis=1), 1e-300)
    valid = norm > 1e-9 * scale
    n = n / np.where(valid, norm, 1.0)[:, None]
    d = -np.einsum("kj,kj->k", n, a)
    return n, d, valid


def _check_robust_args(threshold_m: float, max_iterations: int, confidence: float) -> None:
    if not (math.isfinite(threshold_m) and threshold_m > 0):
        raise CalibrationError(f"threshold_m must be positive, got {threshold_m!r}")
    if max_iterations < 1:
        raise CalibrationError(f"max_iterations must be >= 1, got {max_iterations}")
    if not (0.0 < confidence < 1.0):
        raise CalibrationError(f"confidence must be in (0, 1), got {confidence}")


def _ransac(p: FloatArray, threshold_m: float, max_iterations: int, confidence: float,
            rng: np.random.Generator, max_score_points: int) -> Plane:
    """Seeded RANSAC with MSAC scoring: the best triplet plane (see :func:`fit_plane_robust`).

    Raises:
        CalibrationError: If no non-degenerate triplet was drawn (points collinear).
    """
    n_pts = p.shape[0]
    # hypotheses are scored on a fixed random subset (drawn with replacement)
    score_pts = p if n_pts <= max_score_points else p[rng.integers(0, n_pts, max_score_points)]
    t2 = threshold_m * threshold_m
    best_cost = math.inf
    best: tuple[FloatArray, float] | None = None
    drawn = 0
    needed = float(max_iterations)
    batch = 64
    while drawn < min(needed, max_iterations):
        k = int(min(batch, max_iterations - drawn))
        idx = rng.integers(0, n_pts, size=(k, 3))          # a batch of random triplets
        drawn += k
        normals, offsets, valid = _hypotheses(p, idx)
        if not valid.any():
            continue
        normals, offsets = normals[valid], offsets[valid]
        dist2 = (score_pts @ normals.T + offsets) ** 2     # (M, K) squared distances
        cost = np.minimum(dist2, t2).sum(axis=0)           # MSAC: squared distance capped at the threshold
        j = int(np.argmin(cost))
        if cost[j] < best_cost:
            best_cost = float(cost[j])
            best = (normals[j].copy(), float(offsets[j]))
            best_ratio = float(np.count_nonzero(dist2[:, j] <= t2)) / score_pts.shape[0]   # inlier ratio
            if best_ratio >= 1.0:
                needed = 0.0
            elif best_ratio > 0:
                # draws after which an all-inlier triplet was drawn with probability `confidence`
                needed = math.log(1 - confidence) / math.log(1 - best_ratio**3)
    if best is None:
        _, w, _ = scatter(p)
        check_spread(w)
        raise CalibrationError("RANSAC drew no non-degenerate sample; points may be collinear")
    return Plane(best[0], best[1])


def _refit_inliers(p: FloatArray, plane: Plane, threshold_m: float, refine_iterations: int) -> PlaneFit:
    """TLS on the points within ``threshold_m`` of ``plane``; re-select and refit until stable."""
    inliers = np.abs(plane.signed_distance(p)) <= threshold_m
    fit: PlaneFit | None = None
    for _ in range(max(refine_iterations, 0) + 1):
        if np.count_nonzero(inliers) < 3:
            raise CalibrationError(
                f"robust plane fit found only {int(np.count_nonzero(inliers))} inlier(s) "
                f"within {threshold_m} m")
        fit = tls_fit(np.compress(inliers, p, axis=0), "robust", inliers)
        new = np.abs(fit.plane.signed_distance(p)) <= threshold_m   # inliers of the refit plane
        if np.array_equal(new, inliers):
            break
        inliers = new
    assert fit is not None
    return fit  # its inlier mask is the one it was fitted on


def fit_plane_robust(points: ArrayLike, threshold_m: float, *, max_iterations: int = 1000,
                     confidence: float = 0.999, seed: int | None = 0,
                     max_score_points: int = 2000, refine_iterations: int = 2) -> PlaneFit:
    """Robust plane: seeded RANSAC (MSAC scoring) then a TLS refit on the inliers.

    Hypotheses are drawn in vectorised batches and scored on a fixed random subset
    (drawn with replacement) of ``max_score_points`` points; sampling stops once ``confidence`` is reached
    for the best inlier ratio seen. The best hypothesis's inliers (over all points) are
    refit with TLS, and inliers/refit are iterated ``refine_iterations`` times.

    Args:
        points: Shape (N, 3), metres, N >= 3, finite (mask invalid pixels first).
        threshold_m: Inlier distance threshold, metres (e.g. 3-5x the depth noise).
        max_iterations: Maximum number of RANSAC hypotheses.
        confidence: Probability of having drawn an all-inlier sample before stopping.
        seed: Seed of the random generator (same seed, same result).
        max_score_points: Size of the subset used to score hypotheses.
        refine_iterations: Inlier re-selection / refit rounds after RANSAC.

    Returns:
        The fit on the inliers, with ``inliers`` the mask over the input points.

    Raises:
        CalibrationError: On invalid input or if fewer than 3 non-collinear inliers exist.
    """
    p = validate_points(points)
    _check_robust_args(threshold_m, max_iterations, confidence)
    rng = np.random.default_rng(seed)
    plane = _ransac(p, threshold_m, max_iterations, confidence, rng, max_score_points)
    return _refit_inliers(p, plane, threshold_m, refine_iterations)
