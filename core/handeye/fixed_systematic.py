"""The camera's systematic error in a fixed camera's fit: common to every plate view, not per-view noise.

As for the camera on the flange (:mod:`cellcal.core.handeye.systematic`, ADR 0059 "Amended"): a
full-frame fit's covariance carries the camera's uncorrected systematic allowance, right for one
view and wrong for a fit that combines views, since the same camera's depth scale, offset and
field err alike at every view. So the views are weighed by their fits' noise alone and each
systematic term ``k`` is one coefficient common to the views: every view's measured plane moves by
its own 1-sigma shift ``δ_k`` (the fit's ``systematic_shifts``), the estimate by the first-order
response ``Δx_k = -(JᵀJ + P)⁻¹ Jᵀ δr_k`` (whitened), and the covariance gains ``Σ_k Δx_k Δx_kᵀ``,
never scaled by chi2/dof. The chi2 the noise test sees is that of the fit with one coefficient per
term under the prior N(0, 1) (linear, at the solution), so a pattern the terms explain is not
taken for noise.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from cellcal.core.handeye.model import PlaneObservation
from cellcal.core.handeye.systematic import pattern, systematic_terms

FloatArray = NDArray[np.float64]

__all__ = ["systematic_columns", "systematic_response"]


def systematic_columns(observations: Sequence[PlaneObservation], bases: FloatArray, whiten: FloatArray,
                       n_rows: int) -> tuple[list[str], FloatArray]:
    """Each systematic term's whitened residual change when every view's plane moves by its 1-sigma shift.

    Args:
        observations: The plate views (their ``systematic_shifts``: ``{term: (normal_delta, offset_delta_m)}``).
        bases: (V, 3, 2) tangent bases across the measured normals (the residual's first two components).
        whiten: (V, 3, 3) the views' whitening matrices.
        n_rows: Rows of the whitened residual vector (3 x views, the measuring plane's included: 0 there).

    Returns:
        The terms' names and their columns (n_rows, K); rows of views without the term are 0.
    """
    terms = systematic_terms(observations)   # the union over the views, zero shifts where a view lacks one
    cols = np.zeros((n_rows, len(terms)))
    for j, shifts in enumerate(terms.values()):
        white = pattern(bases, whiten, shifts)
        cols[:white.size, j] = white
    return list(terms), cols


def systematic_response(jac: FloatArray, info: FloatArray, residual: FloatArray, cols: FloatArray
                        ) -> tuple[FloatArray, float]:
    """The terms' covariance on the parameters and the chi2 of the fit with the terms as common coefficients.

    Args:
        jac: (n_rows, P) whitened Jacobian at the solution.
        info: (P, P) ``JᵀJ`` plus the priors' information.
        residual: (n_rows,) whitened residual at the solution.
        cols: (n_rows, K) the terms' whitened columns (:func:`systematic_columns`).

    Returns:
        ``(Σ_k Δx_k Δx_kᵀ, chi2)``: the covariance the terms add (P, P) and the residual's chi2 once the
        terms, each N(0, 1), and the parameters absorb what they can (linearised at the solution).
    """
    if cols.shape[1] == 0:
        return np.zeros_like(info), float(residual @ residual)
    dx = -np.linalg.solve(info, jac.T @ cols)          # (P, K): each term's 1-sigma response
    cov: FloatArray = dx @ dx.T
    # the joint linear fit: parameters free (their priors in info), coefficients with unit information
    design = np.hstack([jac, cols])
    normal = design.T @ design
    normal[:info.shape[0], :info.shape[0]] = info
    normal[info.shape[0]:, info.shape[0]:] += np.eye(cols.shape[1])
    step = np.linalg.solve(normal, design.T @ residual)
    after = residual - design @ step
    chi2 = float(after @ after + step[info.shape[0]:] @ step[info.shape[0]:])
    return cov, chi2
