"""Given parameters: held exact, or fitted with a Gaussian prior of their stated uncertainty.

``[handeye] given`` names parameters the cell takes from ``[mount]`` / ``[reference]``
instead of estimating. Without a sigma a given value is held exact and the intervals are
conditional on it, which the result says. With ``given_sigma`` (metres or radians) the
value becomes a prior: the parameter is fitted with one extra residual
``(value - configured) / sigma``, so its uncertainty enters every interval through the
fit's covariance (where the data cannot see it, exactly ``(JᵀJ)⁻¹ + G Σ Gᵀ`` with
``G = (JᵀJ)⁻¹ Jᵀ J_g``), and where the data can see it they correct it (ADR 0030).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

from cellcal.core.handeye.model import MOUNT_TRANSLATION, PARAMETERS, PLANE_OFFSET
from cellcal.devices.errors import CalibrationError

#: Parameters in metres (the others are in radians).
METRE_PARAMETERS = frozenset(PARAMETERS[i] for i in (*range(MOUNT_TRANSLATION.start, MOUNT_TRANSLATION.stop),
                                                     PLANE_OFFSET))


def check_given_sigma(given: Sequence[str], given_sigma: Mapping[str, float]) -> dict[str, float]:
    """The sigmas of given parameters, checked: each names a given parameter and is finite and > 0.

    Raises:
        CalibrationError: Naming the offending parameter.
    """
    out = {}
    for name, sigma in given_sigma.items():
        if name not in given:
            raise CalibrationError(f"given_sigma names {name!r}, which is not in given {list(given)}")
        if isinstance(sigma, bool) or not isinstance(sigma, (int, float)) or not math.isfinite(sigma) or sigma <= 0:
            raise CalibrationError(f"given_sigma of {name!r} must be a finite number > 0, got {sigma!r}")
        out[name] = float(sigma)
    return out


def format_sigma(name: str, sigma: float) -> str:
    """A given parameter's sigma for people: mm or deg."""
    return f"{1000 * sigma:g} mm" if name in METRE_PARAMETERS else f"{math.degrees(sigma):g} deg"


def given_notes(given: Sequence[str], given_sigma: Mapping[str, float]) -> list[str]:
    """Lines saying which given values the intervals include and which they assume exact."""
    notes = []
    held = [name for name in given if name not in given_sigma]
    priors = [name for name in given if name in given_sigma]
    if held:
        notes.append(f"given {', '.join(held)} held exact: the intervals are conditional on "
                     f"{'these values' if len(held) > 1 else 'this value'} being right (set [handeye] given_sigma "
                     "to include its uncertainty)")
    if priors:
        notes.append("given " + ", ".join(f"{name} ± {format_sigma(name, given_sigma[name])}" for name in priors)
                     + " (1 sigma): fitted with that prior, its uncertainty is in the intervals")
    return notes


__all__ = ["METRE_PARAMETERS", "check_given_sigma", "format_sigma", "given_notes"]
