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

from cellcal.core.methods.fullframe.systematic import FIELD_SHAPE_DEGREES, FIELD_SHAPES, field_shapes
from cellcal.devices.measurement import MeasurementModel

__all__ = ["leftover_field_covariance"]

FloatArray = NDArray[np.float64]


def leftover_field_covariance(fit: Any, model: MeasurementModel, order: int, jw: FloatArray, h_inv: FloatArray
                              ) -> FloatArray:
    """(p, p) covariance of the fit's parameters from the field shapes a fit of ``order`` leaves (zeros: none).

    Args:
        fit: The final fit's solution (its inlier points' normalised pixel coordinates and noise).
        model: The camera's measurement model: its field allowance (native unit at the image corner).
        order: The field order fitted (0: none).
        jw: (p, N) the whitened d(predicted)/d(parameters) at the solution.
        h_inv: (p, p) the inverse of the fit's normal matrix, priors included.
    """
    field = model.allowance[2]
    left = [k for k, degree in enumerate(FIELD_SHAPE_DEGREES) if degree > order]
    p = h_inv.shape[0]
    if field <= 0.0 or not left:
        return np.zeros((p, p))
    shapes = field_shapes(fit.pts.u, fit.pts.v)                   # (N, 6), each 1 at the corner
    sigma = field / math.sqrt(len(FIELD_SHAPES))                  # the allowance shared as the full frame shares it
    cov = np.zeros((p, p))
    for k in left:
        d = h_inv @ (jw @ (shapes[:, k] * (sigma / fit.sigma)))   # the fit's answer to that shape
        cov += np.outer(d, d)
    return cov
