"""The image field's order of a depth calibration, chosen by the residuals of views held out of the fit (ADR 0056).

Every order tried is fitted on the training views and scored by the residual RMS of the held-out views
(their inliers); the lowest order within noise of the best is chosen (:func:`choose_order`). The
highest order starts from the robust pass's solution; each lower one from the highest's, projected
through its normal equations (the field terms are extra linear columns, so the projection is exact for
the linear part) and takes one Gauss-Newton step (:func:`_start_from`). The fit without correction
(order None) gives the held-out views' "before".
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cellcal.core.depthcal.problem import FloatArray, _Points, _Problem, _rms
from cellcal.core.depthcal.solver import _evaluate, _Fit, _inliers, _solve
from cellcal.devices.measurement import MeasurementModel
from cellcal.devices.pose import Pose

__all__ = ["OrderChoice", "ProblemFactory", "choose_order"]

#: The problem of a field order (None: no correction at all) on the named views.
ProblemFactory = Callable[[int | None, Sequence[int]], _Problem]


@dataclass(frozen=True)
class OrderChoice:
    """The chosen field order, the scores, and the held-out views' residuals the per-view table needs.

    Attributes:
        order: The field order chosen.
        scores: Held-out residual RMS (native unit) per order tried.
        points: The held-out views' points (all of them, in the order of the held-out views).
        resid_before: Their native residuals to the fit without correction.
        to_m_before: Metres per native unit of those residuals, per point.
        resid_after: Their native residuals to the chosen order's fit (without them).
        sigma_after: The noise of those, native unit, per point.
        to_m_after: Metres per native unit of those residuals, per point.
        keep: The held-out inliers of the chosen order's fit.
        fit: The chosen order's fit on the training views.
        fit_none: The fit without correction on the training views.
    """

    order: int
    scores: dict[int, float]
    points: _Points
    resid_before: FloatArray
    to_m_before: FloatArray
    resid_after: FloatArray
    sigma_after: FloatArray
    to_m_after: FloatArray
    keep: NDArray[np.bool_]
    fit: _Fit
    fit_none: _Fit

    @property
    def rms_before(self) -> float:
        """Held-out RMS without correction, native unit."""
        return _rms(self.resid_before[self.keep])

    @property
    def rms_after(self) -> float:
        """Held-out RMS with the correction fitted without them, native unit."""
        return _rms(self.resid_after[self.keep])

    @property
    def noise_rms(self) -> float:
        """What the noise alone would give on the held-out inliers, native unit."""
        return _rms(self.sigma_after[self.keep])


def _start_from(prob: _Problem, src: _Problem, x: FloatArray, normal: FloatArray | None = None) -> FloatArray:
    """``prob``'s parameters from ``src``'s solution ``x``: the geometry and the terms both have.

    With ``src``'s normal matrix at ``x`` (its solution on the same points), the terms ``prob`` lacks are
    dropped and the rest moved as the normal equations say (exact for a linear problem, so the lower
    orders of the held-out pass start a step or two from their own solutions).
    """
    ng = prob.n_geometry
    src_names = [src.template.names[k] for k in src.free]
    kept = list(range(ng)) + [ng + src_names.index(prob.template.names[k]) if prob.template.names[k] in src_names
                              else -1 for k in prob.free]
    if normal is None or -1 in kept:
        names = dict(zip(src.template.names, src.vector(x), strict=True))
        terms = [names.get(prob.template.names[k], 0.0) for k in prob.free]
        return np.concatenate([x[:ng], np.asarray(terms, dtype=np.float64)])
    dropped = [i for i in range(x.size) if i not in kept]
    out = x[kept].copy()
    if dropped:
        a_kk = normal[np.ix_(kept, kept)]
        d = np.sqrt(np.maximum(np.diag(a_kk), 1e-300))
        rhs = normal[np.ix_(kept, dropped)] @ x[dropped]
        out += np.linalg.lstsq(a_kk / np.outer(d, d), rhs / d, rcond=1e-12)[0] / d
    return out


def choose_order(problem: ProblemFactory, orders: Sequence[int], model: MeasurementModel, *, train: Sequence[int],
                 held: Sequence[int], held_flanges: list[Pose], inliers: _Points, sigma: FloatArray,
                 pts_all: _Points, start: tuple[_Problem, FloatArray]) -> OrderChoice:
    """Fit each order (and no correction) on the training views, score it on the held-out ones, choose.

    Args:
        problem: The problem of an order on the named views.
        orders: The field orders to try, ascending.
        model: The camera's measurement model (the held-out residuals' noise).
        train: Indices of the training views.
        held: Indices of the held-out views.
        held_flanges: Their reported flange poses.
        inliers: Every view's inlier points (the robust pass's).
        sigma: Their noise, native unit.
        pts_all: Every view's sampled points.
        start: The robust pass's problem and solution, where the highest order starts.
    """
    train_idx = inliers.index(train)
    inl_train = inliers.subset(train)
    held_pts = pts_all.subset(held)
    scores: dict[int, float] = {}
    held_eval: dict[int, tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]] = {}
    train_fits: dict[int | None, _Fit] = {}
    top: tuple[_Problem, _Fit] | None = None
    for order in [*reversed(orders), None]:              # the highest from the robust solution, the rest from it
        prob = problem(order, train)
        if top is None:
            fit = _solve(prob, inl_train, sigma[train_idx], _start_from(prob, *start), 20)
            top = prob, fit
        else:
            # from the projected start one step leaves about 0.01 sigma (it converges quadratically): enough to
            # score an order on the held-out views, whose RMS it changes by less than 1e-4
            normal = top[1].fisher + np.diag(top[1].prior)
            fit = _solve(prob, inl_train, sigma[train_idx], _start_from(prob, top[0], top[1].x, normal), 1)
        train_fits[order] = fit
        hp = dataclasses.replace(prob, flanges=held_flanges)
        resid, sig, to_m = _evaluate(hp, model, fit.x, held_pts, float(np.median(fit.sigma)))
        if order is None:
            resid_b, to_m_b = resid, to_m
            continue
        k = _inliers(resid / sig)
        scores[order] = _rms(resid[k])
        held_eval[order] = (resid, sig, to_m, k)
    best = min(scores.values())
    n_held = int(np.count_nonzero(held_eval[min(scores, key=lambda k: scores[k])][3]))
    # within noise of the best: two sigmas of an RMS over n points (relative sigma 1/sqrt(2n)), at least 0.5 %
    tol = best * max(0.005, 2.0 / math.sqrt(2.0 * max(n_held, 1)))
    order = min(o for o in orders if scores[o] <= best + tol)
    resid_a, sig_a, to_m_a, keep_a = held_eval[order]
    return OrderChoice(order, scores, held_pts, resid_b, to_m_b, resid_a, sig_a, to_m_a, keep_a,
                       train_fits[order], train_fits[None])
