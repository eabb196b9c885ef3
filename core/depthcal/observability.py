"""What a depth-calibration plan can and cannot see: per parameter, its 1-sigma, seen or not, and why.

From the Fisher information ``F = JᵀJ`` of the whitened residuals (what the fit's covariance
is the inverse of): a parameter is *seen* when its 1-sigma is below its limit, what a
calibration must beat to be worth anything (the camera's systematic allowance for the
correction's terms, 1 cm / 10 mrad for the geometry). An unseen parameter is named with the
parameter it is confounded with (the largest correlation) and the plan's fault when the plan
shows one: a single height (the scale cannot be told from the plane's height) or a single
inclination (the offset cannot be told from the plane's height). Rationale: ADR 0056.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["GEOMETRY_LIMITS", "MIN_HEIGHT_SPREAD_M", "MIN_INCLINATION_SPREAD_DEG", "Observability",
           "ParameterSight", "analyse", "fisher_covariance"]

FloatArray = NDArray[np.float64]

#: 1-sigma limits of the geometry's parameters (rad for angles, m for lengths): beyond them, not seen.
GEOMETRY_LIMITS: dict[str, float] = {"plane_tilt_a_rad": 0.01, "plane_tilt_b_rad": 0.01, "plane_offset_m": 0.01,
                                     "mount_rx_rad": 0.01, "mount_ry_rad": 0.01, "mount_rz_rad": 0.01,
                                     "mount_tx_m": 0.01, "mount_ty_m": 0.01, "mount_tz_m": 0.01}
#: Camera heights above the plane spanning less than this (m) are one height.
MIN_HEIGHT_SPREAD_M = 0.05
#: Angles between the optical axis and the plane normal spanning less than this (deg) are one inclination.
MIN_INCLINATION_SPREAD_DEG = 5.0
#: Eigenvalues of the column-scaled Fisher matrix below this share of the largest are null directions.
NULL_SHARE = 1e-13
#: A correlation above this names the confounded partner.
CONFOUNDED = 0.9


@dataclass(frozen=True)
class ParameterSight:
    """One fitted parameter as the plan sees it.

    Attributes:
        name: The parameter's name (the correction's names, ``plane_*``, ``mount_*``).
        sigma: Its 1-sigma from the Fisher information alone (the noise's), in its unit; inf when not determined.
        limit: The 1-sigma above which it counts as not seen.
        observable: Whether ``sigma < limit``.
        reason: Why not, and what would show it ("" when seen).
    """

    name: str
    sigma: float
    limit: float
    observable: bool
    reason: str = ""

    def to_dict(self) -> dict[str, Any]:
        """JSON form (inf written as null)."""
        return {"name": self.name, "sigma": self.sigma if math.isfinite(self.sigma) else None,
                "limit": self.limit, "observable": self.observable, "reason": self.reason}


@dataclass(frozen=True)
class Observability:
    """Per parameter what the plan sees, the problem's condition and the plan's spread.

    Attributes:
        parameters: Every fitted parameter, in the fit's order.
        condition: Largest over smallest singular value of the whitened, column-scaled Jacobian (inf if singular).
        height_spread_m: Range of the camera's heights above the plane over the views, m.
        inclination_spread_deg: Range of the optical axis' angles to the plane normal, deg.
    """

    parameters: tuple[ParameterSight, ...]
    condition: float
    height_spread_m: float
    inclination_spread_deg: float

    @property
    def observable(self) -> bool:
        """Whether the plan sees every parameter."""
        return all(p.observable for p in self.parameters)

    @property
    def unseen(self) -> list[ParameterSight]:
        """The parameters the plan cannot see."""
        return [p for p in self.parameters if not p.observable]

    def sight(self, name: str) -> ParameterSight:
        """The named parameter's entry (KeyError if it was not fitted)."""
        for p in self.parameters:
            if p.name == name:
                return p
        raise KeyError(name)

    def message(self) -> str:
        """One line: all seen, or what is not and why."""
        if self.observable:
            return f"the plan sees every parameter (condition {self.condition:.3g})"
        return "; ".join(f"{p.name} not seen: {p.reason}" for p in self.unseen)

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {"observable": self.observable,
                "condition": self.condition if math.isfinite(self.condition) else None,
                "height_spread_m": self.height_spread_m, "inclination_spread_deg": self.inclination_spread_deg,
                "parameters": [p.to_dict() for p in self.parameters], "message": self.message()}


def fisher_covariance(fisher: FloatArray) -> tuple[FloatArray, FloatArray, float]:
    """Covariance from a Fisher matrix, the 1-sigmas (inf along null directions) and the condition.

    The matrix is scaled to a unit diagonal first (units do not decide what is singular); the
    covariance returned is finite (null directions regularised), for correlations and intervals
    of the parameters that are determined.
    """
    f = np.asarray(fisher, dtype=np.float64)
    d = np.sqrt(np.maximum(np.diag(f), 0.0))
    d = np.where(d > 0, d, 1.0)
    fs = f / np.outer(d, d)
    w, vecs = np.linalg.eigh(fs)
    w_max = float(max(w.max(), 0.0)) if w.size else 0.0
    null = w <= NULL_SHARE * w_max if w_max > 0 else np.ones_like(w, dtype=bool)
    w_safe = np.where(null, NULL_SHARE * max(w_max, 1e-300), w)
    cov_s = (vecs / w_safe) @ vecs.T
    cov = cov_s / np.outer(d, d)
    sigma = np.sqrt(np.maximum(np.diag(cov), 0.0))
    in_null = (np.abs(vecs[:, null]) > 1e-3).any(axis=1) if null.any() else np.zeros(len(w), dtype=bool)
    sigma = np.where(in_null, np.inf, sigma)
    w_min = float(w.min()) if w.size else 0.0
    condition = math.sqrt(w_max / w_min) if w_min > NULL_SHARE * w_max and w_min > 0 else math.inf
    return cov, sigma, condition


def _plan_fault(name: str, height_spread_m: float, inclination_spread_deg: float, estimate_mount: bool) -> str:
    """The plan's shape that hides the named parameter, in words ("" when none applies)."""
    one_height = height_spread_m < MIN_HEIGHT_SPREAD_M
    one_incl = inclination_spread_deg < MIN_INCLINATION_SPREAD_DEG
    if one_height and name in ("fb_error", "scale_error", "plane_offset_m"):
        return (f"the views are at one height (spread {height_spread_m * 1000:.0f} mm): the depth scale cannot be "
                "told from the plane's height; add views at other heights (the arm's known motion fixes the scale)")
    if one_incl and name in ("disparity_offset_px", "offset_m", "plane_offset_m"):
        return (f"the views are at one inclination (spread {inclination_spread_deg:.1f} deg): the offset cannot be "
                "told from the plane's height; add views at other inclinations")
    if one_incl and name.startswith("field_") and estimate_mount:
        return ("one inclination: the field's linear terms cannot be told from a rotation of the mount; "
                "add views at other inclinations")
    if name.startswith("wiggle_"):
        return "the views' ranges do not span the wiggling's period; add views at heights a quarter period apart"
    return ""


def analyse(fisher: FloatArray, names: Sequence[str], limits: Sequence[float], *, height_spread_m: float,
            inclination_spread_deg: float, estimate_mount: bool = False) -> Observability:
    """What the plan sees of each parameter (see the module docstring).

    Args:
        fisher: ``JᵀJ`` of the whitened residuals over the fitted parameters, in ``names`` order.
        names: The parameters' names.
        limits: Per parameter, the 1-sigma above which it is not seen.
        height_spread_m: Range of the camera's heights above the plane, m.
        inclination_spread_deg: Range of the optical axis' angles to the normal, deg.
        estimate_mount: Whether the mount was fitted too (a rotation of it mimics the field's linear terms).
    """
    cov, sigma, condition = fisher_covariance(fisher)
    sd = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    corr = cov / np.outer(sd, sd)
    out = []
    for k, name in enumerate(names):
        seen = bool(sigma[k] < limits[k])
        reason = ""
        if not seen:
            size = "not determined" if not math.isfinite(sigma[k]) else f"1-sigma {sigma[k]:.3g} >= {limits[k]:.3g}"
            row = np.abs(corr[k]).copy()
            row[k] = 0.0
            partner = int(np.argmax(row)) if row.size > 1 else k
            why = _plan_fault(name, height_spread_m, inclination_spread_deg, estimate_mount)
            if not why and partner != k and row[partner] > CONFOUNDED:
                why = f"confounded with {names[partner]} (correlation {corr[k, partner]:+.3f})"
            reason = size + (f"; {why}" if why else "")
        out.append(ParameterSight(name, float(sigma[k]), float(limits[k]), seen, reason))
    return Observability(tuple(out), float(condition), float(height_spread_m), float(inclination_spread_deg))
