"""The depth calibration's solver (ADR 0056): Gauss-Newton on the normal equations of a :class:`_Problem`.

The normal equations are built directly from the problem's analytic columns (``JᵀJ`` of ~200k x 15 is
milliseconds), robust (soft-L1, iteratively reweighted) or plain (:func:`_gauss_newton`, :func:`_solve`).
Gauss-Newton converges quadratically here, so a step below :data:`_STEP_SIGMAS` of every sigma ends it.
A fit on every view extends a fit on the training views by the held-out views' columns alone
(:func:`_extend`). :func:`_evaluate` gives the native residuals of a solution on any points, with their
noise and their size in metres; :func:`_inliers` tells the points within :data:`INLIER_SIGMAS`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cellcal.core.depthcal.problem import FloatArray, _dot, _gram, _Points, _Problem, _sq
from cellcal.devices.measurement import MeasurementModel
from cellcal.devices.pose import Pose

#: Points farther than this many (robust) sigmas from the robust fit are outliers (speckle, edges).
INLIER_SIGMAS = 5.0
#: Soft-L1 scale of the robust pass, in sigmas.
ROBUST_SCALE = 3.0
#: Gauss-Newton stops after a step below this share of every parameter's (conditional) sigma: it converges
#: quadratically here (a step of 2 sigmas is followed by one of about 0.01), so the next would be ~1e-4.
_STEP_SIGMAS = 0.1


@dataclass
class _Fit:
    """A plain fit's solution on its points, with what its covariance and its extension need."""

    x: FloatArray
    pts: _Points               # the inliers
    sigma: FloatArray          # their noise, native unit
    fisher: FloatArray         # JᵀJ of the whitened residuals at x (the data's alone, no prior)
    resid: FloatArray          # whitened residuals of the inliers
    prior: FloatArray          # the prior's information, diagonal over the parameters (0 for the geometry)


def _noise(prob: _Problem, model: MeasurementModel, x: FloatArray, pts: _Points, fallback: float) -> FloatArray:
    """Per point noise 1-sigma in the native unit (stereo: constant; ToF: the model's law at range and incidence)."""
    if prob.stereo:
        return np.full(pts.measured.size, model.disparity_noise_px)
    _, t, cos, _ = prob.true_values(x[:prob.n_geometry], pts)
    sig = model.range_sigma_m(t, cos)
    if sig is None:
        return np.full(pts.measured.size, fallback)
    return np.maximum(np.asarray(sig, dtype=np.float64), 1e-6)


def _gauss_newton(prob: _Problem, pts: _Points, sigma: FloatArray, x: FloatArray, robust: bool,
                  iterations: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Gauss-Newton on the normal equations (the problem is linear in the correction, nearly so in the plane).

    The normal equations are built from the analytic columns (:meth:`_Problem.columns`) and the weak prior
    is added to them directly. ``robust``: iteratively reweighted with soft-L1 weights of scale
    :data:`ROBUST_SCALE` (speckle and edges lose their pull). Singular directions (a plan that cannot see
    a parameter) get the minimum-norm step. A step that raises the cost is halved. Stops when a step is
    below :data:`_STEP_SIGMAS` of every parameter's (conditional) sigma.

    Returns:
        ``(x, fisher, resid)``: the solution, ``JᵀJ`` of the whitened residuals at the last linearisation
        (unweighted, no prior) and the whitened residuals at ``x``.
    """
    ng = prob.n_geometry
    prior_info = np.concatenate([np.zeros(ng), 1.0 / prob.prior ** 2])
    inv_sigma = 1.0 / sigma

    def cost(r: FloatArray, xx: FloatArray) -> float:
        p = float(np.sum(xx[ng:] ** 2 / prob.prior ** 2))
        if robust:
            k = ROBUST_SCALE
            return float(np.sum(2.0 * k * k * (np.sqrt(1.0 + (r / k) ** 2) - 1.0))) + p
        return _sq(r) + p

    cols, pred = prob.columns(x, pts)
    r = (pts.measured - pred) * inv_sigma
    c = cost(r, x)
    fisher = np.zeros((x.size, x.size))
    for it in range(iterations):
        jw = cols                                 # d(predicted)/dx whitened (rows): the residual's Jacobian is -jwᵀ
        jw *= inv_sigma                           # in place: a fresh (p, N) array page-faults on every use
        if robust:
            w = 1.0 / np.sqrt(1.0 + (r / ROBUST_SCALE) ** 2)
            jww = jw * w
            a = _gram(jww, jw)
            b = _dot(jww, r)
            fisher = a
        else:
            fisher = _gram(jw, jw)
            a = fisher
            b = _dot(jw, r)
        a = a + np.diag(prior_info)
        b = b - prior_info * x
        d = np.sqrt(np.maximum(np.diag(a), 1e-300))
        scaled = np.linalg.lstsq(a / np.outer(d, d), b / d, rcond=1e-12)[0]
        step = scaled / d
        accepted = last = False
        for _half in range(8):
            x_new = x + step
            last = it == iterations - 1 or float(np.max(np.abs(scaled))) < _STEP_SIGMAS
            if last:                              # the columns at x_new are not needed
                pred = prob.predicted(x_new, pts)
            else:
                cols_new, pred = prob.columns(x_new, pts)
            r_new = (pts.measured - pred) * inv_sigma
            c_new = cost(r_new, x_new)
            if c_new <= c:
                accepted = True
                break
            step = step / 2.0
            scaled = scaled / 2.0
        if not accepted:
            break
        x, r, c = x_new, r_new, c_new
        if last:
            break
        cols = cols_new
    return x, fisher, r


def _solve(prob: _Problem, pts: _Points, sigma: FloatArray, x0: FloatArray, iterations: int = 20) -> _Fit:
    """A plain (not robust) fit of the points from ``x0``."""
    x, fisher, r = _gauss_newton(prob, pts, sigma, x0, robust=False, iterations=iterations)
    prior = np.concatenate([np.zeros(prob.n_geometry), 1.0 / prob.prior ** 2])
    return _Fit(x, pts, sigma, fisher, r, prior)


def _extend(prob: _Problem, train: _Fit, pts: _Points, sigma: FloatArray, held: Sequence[int],
            held_flanges: list[Pose]) -> _Fit:
    """The fit on every view's points ``pts`` from the fit on the training views, by one Gauss-Newton step.

    At the training solution the training points' gradient is zero and their normal matrix is known, so
    the step needs the columns of the held-out views' points alone: ``(F_train + F_held + P) d = J_heldᵀ r_held
    - P x``. The step is small (the held-out views add a quarter of the data) and the problem converges
    quadratically: what it leaves is about 0.01 of a sigma. Should the cost rise, a full fit from there.
    """
    ng = prob.n_geometry
    x = train.x
    idx = pts.index(held)
    held_pts = pts.subset(held)
    held_prob = dataclasses.replace(prob, flanges=held_flanges)
    cols, pred = held_prob.columns(x, held_pts)
    inv_sigma = 1.0 / sigma[idx]
    jw = cols
    jw *= inv_sigma
    r_held = (held_pts.measured - pred) * inv_sigma
    fisher = train.fisher + _gram(jw, jw)
    a = fisher + np.diag(train.prior)
    b = _dot(jw, r_held) - train.prior * x
    d = np.sqrt(np.maximum(np.diag(a), 1e-300))
    x_new = x + np.linalg.lstsq(a / np.outer(d, d), b / d, rcond=1e-12)[0] / d
    r = (pts.measured - prob.predicted(x_new, pts)) / sigma
    before = _sq(train.resid) + _sq(r_held) + float(np.sum(x[ng:] ** 2 * train.prior[ng:]))
    if _sq(r) + float(np.sum(x_new[ng:] ** 2 * train.prior[ng:])) > before:
        return _solve(prob, pts, sigma, x)
    return _Fit(x_new, pts, sigma, fisher, r, train.prior)


def _evaluate(prob: _Problem, model: MeasurementModel, x: FloatArray, pts: _Points, fallback: float
              ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Native residuals, their noise and the metres-per-native-unit factor, per point."""
    true, t, cos, _ = prob.true_values(x[:prob.n_geometry], pts)
    resid = pts.measured - prob.predicted(x, pts, true)
    if prob.stereo:
        sigma = np.full(pts.measured.size, model.disparity_noise_px)
        z = t * pts.ray[2]
        to_m = z * z / prob.fb
    else:
        sig = model.range_sigma_m(t, cos)
        sigma = (np.full(pts.measured.size, fallback) if sig is None
                 else np.maximum(np.asarray(sig, dtype=np.float64), 1e-6))
        to_m = np.ones_like(t)
    return resid, sigma, to_m


def _inliers(w: FloatArray, ref: FloatArray | None = None) -> NDArray[np.bool_]:
    """Which whitened residuals ``w`` are within :data:`INLIER_SIGMAS` robust sigmas.

    The robust sigma: 1.4826 times the median of ``|ref|`` (default ``w`` itself), at least 1.
    """
    scale = max(1.4826 * float(np.median(np.abs(w if ref is None else ref))), 1.0)
    out: NDArray[np.bool_] = np.abs(w) < INLIER_SIGMAS * scale
    return out
