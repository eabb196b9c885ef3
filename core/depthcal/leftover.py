"""What a depth calibration leaves of the image field it did not fit: its share of the intervals (ADR 0056).

The field order is chosen by held-out error, and a field well below the noise (a ToF camera's
millimetre bow under 3 mm of range noise) is not chosen: the held-out RMS cannot tell it. Unfitted,
it is not gone: its mean over the image looks like a depth offset, its tilt like the plane's.
Each of the camera's smooth field shapes the chosen order does not span (the full-frame fit's
:data:`~cellcal.core.methods.fullframe.systematic.FIELD_SHAPES`, each 1 at the image corner, the
allowance shared among them as there) is propagated to first order through the fit,
``dx = H⁻¹ Jᵀ W field``, into the intervals, unscaled.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.methods.fullframe.systematic import FIELD_SHAPES, field_shapes
from cellcal.devices.measurement import MeasurementModel

__all__ = ["SHAPE_DEGREES", "leftover_field_covariance"]

FloatArray = NDArray[np.float64]

#: The polynomial degree of each field shape (a fit of that order or higher spans it).
SHAPE_DEGREES: dict[str, int] = {"radial bow": 2, "u^2": 2, "v^2": 2, "uv": 2, "u": 1, "v": 1}


def leftover_field_covariance(prob: Any, fit: Any, model: MeasurementModel, order: int,
                              columns: tuple[FloatArray, FloatArray] | None = None) -> FloatArray:
    """(p, p) covariance of the fit's parameters from the field shapes a fit of ``order`` leaves (zeros: none).

    Args:
        prob: The final fit's problem.
        fit: Its solution (``x``, the inlier points with their normalised pixel coordinates, noise, normal matrix).
        model: The camera's measurement model: its field allowance (native unit at the image corner).
        order: The field order fitted (0: none).
        columns: ``prob.columns(fit.x, fit.pts)`` when already computed.
    """
    field = model.allowance[2]
    left = [k for k, name in enumerate(FIELD_SHAPES) if SHAPE_DEGREES[name] > order]
    p = fit.fisher.shape[0]
    if field <= 0.0 or not left:
        return np.zeros((p, p))
    inv_sigma = 1.0 / fit.sigma
    cols, _ = columns if columns is not None else prob.columns(fit.x, fit.pts)
    h_inv = np.linalg.pinv(fit.fisher + np.diag(fit.prior))
    shapes = field_shapes(fit.pts.u, fit.pts.v)                   # (N, 6), each 1 at the corner
    sigma = field / math.sqrt(len(FIELD_SHAPES))                  # the allowance shared as the full frame shares it
    cov = np.zeros((p, p))
    for k in left:
        d = h_inv @ ((cols * inv_sigma) @ (shapes[:, k] * sigma * inv_sigma))  # the fit's answer to that shape
        cov += np.outer(d, d)
    return cov
