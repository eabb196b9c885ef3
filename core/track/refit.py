"""Gauss-Newton over a bounded stack of frames with a Gaussian prior: the batch step behind a restart."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cellcal.core.track.linear import Frames, LinearModel

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Refit:
    """A fit of the nine parameters to frames and a prior.

    Attributes:
        x: The parameters (9,).
        info: ``JᵀJ`` of the frames' whitened residuals at ``x`` (9x9; the data's information, no prior).
        chi2: Sum of the squared whitened residuals plus the prior's term.
        n_residuals: Residuals of the frames (3 per frame).
    """

    x: FloatArray
    info: FloatArray
    chi2: float
    n_residuals: int


def refit(model: LinearModel, frames: Frames, x0: FloatArray, prior_info: FloatArray, prior_mean: FloatArray,
          iterations: int = 4) -> Refit:
    """Minimise ``|r(x)|² + (x - prior_mean)ᵀ prior_info (x - prior_mean)`` from ``x0`` by Gauss-Newton.

    ``prior_info`` must make the normal equations regular (an isotropic weak prior on top of
    any block prior keeps a direction no frame sees where the prior puts it).
    """
    x = np.array(x0, dtype=np.float64)
    for _ in range(iterations):
        r, jac = model.linearise(x, frames)  # (N, 3), (N, 3, 9)
        j2 = jac.reshape(-1, 9)
        h = j2.T @ j2 + prior_info  # normal matrix
        g = j2.T @ r.ravel() + prior_info @ (x - prior_mean)  # gradient / 2
        x = x - np.linalg.solve(h, g)  # Gauss-Newton step
    r, jac = model.linearise(x, frames)
    j2 = jac.reshape(-1, 9)
    d = x - prior_mean
    chi2 = float(r.ravel() @ r.ravel() + d @ prior_info @ d)
    return Refit(x, j2.T @ j2, chi2, r.size)


def marginal_info(info: FloatArray, keep: NDArray[np.intp], weak: float) -> FloatArray:
    """The information on the ``keep`` parameters with the others marginalised out (9x9, zero elsewhere).

    ``weak`` (information per parameter) regularises the block marginalised out, so that a
    direction the data never saw does not make the Schur complement singular.
    """
    drop = np.setdiff1d(np.arange(info.shape[0]), keep)
    a = info[np.ix_(keep, keep)]
    b = info[np.ix_(keep, drop)]
    d = info[np.ix_(drop, drop)] + weak * np.eye(len(drop))
    out = np.zeros_like(info)
    out[np.ix_(keep, keep)] = a - b @ np.linalg.solve(d, b.T)  # Schur complement
    return out


__all__ = ["Refit", "marginal_info", "refit"]
