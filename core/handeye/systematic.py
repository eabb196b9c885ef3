"""The camera's systematic error in the hand-eye estimate: common to every pose, not per-pose noise; the budget.

A full-frame fit's covariance carries the camera's uncorrected systematic allowance (ADR 0059):
right for one pose, wrong for a fit that combines poses, because the same camera's scale, offset
and field err alike at every pose. Taken as independent per-pose noise it deflated chi2/dof (0.01
on the sim) and inflated the mount's intervals by an error that is not random. So the poses are
weighed by the fits' noise alone (:attr:`~cellcal.core.handeye.model.PlaneObservation.noise`), and
each systematic term ``k`` is one coefficient common to the poses: every pose's measured plane
moves by its own 1-sigma shift ``δ_k`` (the fit's ``systematic_shifts``), the estimate by the
first-order response at the solution ``Δx_k = -(JᵀWJ + P)⁻¹ JᵀW δr_k`` (:class:`Linearised`;
linear, not re-solved), and the covariance gains ``Σ_k Δx_k Δx_kᵀ`` — never scaled by chi2/dof.

The test of the stated noise must not take a systematic pattern the mount and plane cannot absorb
for noise either: its chi2 is that of the fit re-solved with one coefficient per term under the
prior N(0, 1) (generalised least squares with the allowance's covariance across the poses; the
whitened residuals move by the term's :func:`pattern`). The estimate itself is not taken from that
joint fit: it would tell the terms apart by the small differences between the views, which an error
outside the model (the sim's ToF wiggle) turns into millimetres of mount (ADR 0059, "Amended").

The same responses to a 1 % depth scale and a 1 mm depth offset (the fits' own budget shifts, or
the offset 1 % and 1 mm longer for documents without them), the arm's stated accuracy propagated as
the estimate takes it, and per group of terms (scale, offset, field) their responses are the
mount's error budget (``error_budget`` in ``handeye.json``): ``terms`` per unit, ``at_allowance``
1-sigma, the ``dominant`` term judged there (by the largest move of the mount's translation) and
what to calibrate ``next``. Rationale: docs/adr/0059-systematic-allowance-and-error-budget.md
("Amended"), docs/adr/0055 for the arm.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.calibration.budget import NEXT_STEP
from cellcal.core.handeye.model import PARAMETERS, PlaneObservation
from cellcal.devices.pose import Pose

FloatArray = NDArray[np.float64]

__all__ = ["BUDGET_OFFSET_M", "BUDGET_SCALE", "BUDGET_VALUES", "GROUPS", "Linearised", "budget_values",
           "error_budget", "pattern", "systematic_note", "systematic_terms"]

#: Depth scale (relative) and depth offset (m) of the budget's per-unit terms.
BUDGET_SCALE = 0.01
BUDGET_OFFSET_M = 0.001
#: The budget's values per term: the mount's translation (flange frame, m), roll/pitch/yaw (rad), the plane's offset.
BUDGET_VALUES: tuple[str, ...] = ("tx_m", "ty_m", "tz_m", "roll_rad", "pitch_rad", "yaw_rad", "plane_offset_m")
#: The per-unit terms standing for the judged ones when no pose states an allowance.
_PER_UNIT: dict[str, str] = {"depth_scale_1pct": "depth_scale", "depth_offset_1mm": "depth_offset",
                             "arm_accuracy": "arm_accuracy"}
_STEP = 1e-6

Shift = tuple[FloatArray, float]


def pattern(bases: FloatArray, whiten: FloatArray, shifts: Sequence[Shift]) -> FloatArray:
    """(3N,) how the whitened residuals move when pose ``i``'s measured plane moves by ``shifts[i]``.

    ``bases``: (N, 3, 2) tangent bases of the measured normals; ``whiten``: (N, 3, 3) the poses'
    inverse Cholesky factors. A residual is predicted minus measured: a measured plane moved by
    ``+delta`` moves it by ``-delta``.
    """
    dn = np.stack([np.asarray(n, dtype=np.float64) for n, _ in shifts])
    dc = np.array([float(c) for _, c in shifts])
    dr = np.column_stack([-np.einsum("nij,ni->nj", bases, dn), -dc])
    out: FloatArray = np.einsum("nij,nj->ni", whiten, dr).ravel()
    return out


@dataclass(frozen=True)
class Linearised:
    """The estimate's linear answer to a change of the measured planes, at the solution.

    Attributes:
        fitted: Indices (into :data:`PARAMETERS`) of the fitted parameters (the first ``len(fitted)``
            columns; further columns, if any, are coefficients estimated with them).
        jac: (3N, k) whitened Jacobian of the data residuals at the solution.
        h_inv: (k, k) inverse of ``JᵀJ`` plus the priors' information (the given values').
        bases: (N, 3, 2) tangent bases of the measured normals (the residuals' components).
        whiten: (N, 3, 3) the poses' inverse Cholesky factors.
    """

    fitted: Sequence[int]
    jac: FloatArray
    h_inv: FloatArray
    bases: FloatArray
    whiten: FloatArray

    def _full(self, dx: FloatArray) -> FloatArray:
        out = np.zeros(len(PARAMETERS))
        out[list(self.fitted)] = dx[:len(self.fitted)]
        return out

    def response(self, shifts: Sequence[Shift]) -> FloatArray:
        """(9,) change of the parameters when pose ``i``'s measured plane moves by ``shifts[i]`` (normal, offset)."""
        white = pattern(self.bases, self.whiten, shifts)
        return self._full(-self.h_inv @ (self.jac.T @ white))

    def propagate(self, covariances: Sequence[FloatArray]) -> FloatArray:
        """(9, 9) covariance of the parameters from independent per-pose residual covariances (3x3 each)."""
        n = len(covariances)
        jac = self.jac.reshape(n, 3, -1)
        info = np.zeros((jac.shape[2], jac.shape[2]))
        for j, w, c in zip(jac, self.whiten, covariances, strict=True):
            info += j.T @ (w @ c @ w.T) @ j
        k = len(self.fitted)
        cov_fitted = (self.h_inv @ info @ self.h_inv)[:k, :k]
        out = np.zeros((len(PARAMETERS), len(PARAMETERS)))
        out[np.ix_(list(self.fitted), list(self.fitted))] = cov_fitted
        return out


def systematic_terms(observations: Sequence[PlaneObservation]) -> dict[str, list[Shift]]:
    """Per systematic term (the union over the poses), every pose's 1-sigma shift (zero where a pose lacks it)."""
    keys: list[str] = []
    for o in observations:
        keys += [k for k in o.systematic_shifts if k not in keys]
    zero: Shift = (np.zeros(3), 0.0)
    return {k: [o.systematic_shifts.get(k, zero) for o in observations] for k in keys}


#: The judged groups of systematic terms (``at_allowance``) and the term keys they hold.
GROUPS: dict[str, Callable[[str], bool]] = {"depth_scale": lambda k: k == "scale",
                                             "depth_offset": lambda k: k == "offset",
                                             "depth_field": lambda k: k.startswith("field")}


def _rpy_jacobian(mount: Pose) -> FloatArray:
    """(3, 3) d(roll, pitch, yaw)/d(turn about the flange axes), rad/rad (central differences)."""
    from scipy.spatial.transform import Rotation

    rpy = mount.as_xyz_rpy()[3:]

    def rpy_of(step: FloatArray) -> FloatArray:
        turned = Pose(Rotation.from_rotvec(step) * mount.rotation, mount.translation)
        out: FloatArray = np.unwrap([rpy, turned.as_xyz_rpy()[3:]], axis=0)[1]
        return out

    return np.column_stack([(rpy_of(_STEP * e) - rpy_of(-_STEP * e)) / (2 * _STEP) for e in np.eye(3)])


def budget_values(mount: Pose, dx: FloatArray | None = None, cov: FloatArray | None = None) -> dict[str, float]:
    """The budget's values (:data:`BUDGET_VALUES`) of a parameter change ``dx`` (9,), or 1-sigma of ``cov`` (9x9)."""
    g = _rpy_jacobian(mount)
    if dx is not None:
        vals = np.concatenate([dx[3:6], g @ dx[:3], [dx[8]]])
    else:
        c = np.zeros((9, 9)) if cov is None else cov
        rpy_var = np.diag(g @ c[:3, :3] @ g.T)
        vals = np.sqrt(np.clip(np.concatenate([np.diag(c)[3:6], rpy_var, [c[8, 8]]]), 0.0, None))
    return {k: float(v) for k, v in zip(BUDGET_VALUES, vals, strict=True)}


def _size(values: Mapping[str, float]) -> float:
    """How far a term moves the mount: its largest translation component, m."""
    return max(abs(values[k]) for k in ("tx_m", "ty_m", "tz_m"))


def error_budget(lin: Linearised, observations: Sequence[PlaneObservation], mount: Pose,
                 group_covariances: Mapping[str, FloatArray], arm_covariance: FloatArray) -> dict[str, Any]:
    """The mount's error budget (``handeye.json`` ``error_budget``).

    Args:
        lin: The estimate's linear answer (:class:`Linearised`).
        observations: The poses' planes (their ``budget_shifts`` when present).
        mount: The estimated mount (for roll/pitch/yaw).
        group_covariances: Per judged group of systematic terms present (:data:`GROUPS`), the 9x9
            covariance its terms add (the sum of their responses' outer products).
        arm_covariance: 9x9 covariance the arm's stated accuracy puts on the parameters (common and per pose).

    Returns:
        ``{"terms": {depth_scale_1pct, depth_offset_1mm, arm_accuracy: {tx_m, ..., plane_offset_m}},
        "at_allowance": {depth_scale, depth_offset, depth_field, arm_accuracy: {...}} (1-sigma),
        "judged": "allowance" | "per unit", "dominant": name, "next": what to calibrate next}``. Depth
        terms are signed changes of the estimate (depths longer); the arm's are 1-sigma.
    """
    def unit(key: str, approx: float, absolute: float) -> dict[str, float]:
        shifts = [o.budget_shifts.get(key, (np.zeros(3), approx * o.offset_m + absolute)) for o in observations]
        return budget_values(mount, lin.response(shifts))

    arm = budget_values(mount, cov=arm_covariance)
    terms = {"depth_scale_1pct": unit("depth_scale_1pct", BUDGET_SCALE, 0.0),
             "depth_offset_1mm": unit("depth_offset_1mm", 0.0, BUDGET_OFFSET_M), "arm_accuracy": arm}
    at_allowance = {k: budget_values(mount, cov=c) for k, c in group_covariances.items()}
    if at_allowance:
        at_allowance["arm_accuracy"] = arm
        judged, dominant = "allowance", max(at_allowance, key=lambda k: _size(at_allowance[k]))
        step = NEXT_STEP[dominant]
    else:
        judged, dominant = "per unit", max(terms, key=lambda k: _size(terms[k]))
        step = NEXT_STEP[_PER_UNIT[dominant]]
    return {"terms": terms, "at_allowance": at_allowance, "judged": judged, "dominant": dominant, "next": step}


#: Names of the parameters for the widening note.
_NAMES = {"mount_rot_x": "turn x", "mount_rot_y": "turn y", "mount_rot_z": "turn z", "mount_x": "tx",
          "mount_y": "ty", "mount_z": "tz", "plane_tilt_a": "plane tilt a", "plane_tilt_b": "plane tilt b",
          "plane_offset": "plane offset"}


def systematic_note(before: FloatArray, after: FloatArray, observations: Sequence[PlaneObservation],
                    n_terms: int) -> str:
    """One sentence for the notes: the allowance as a common error, and how much it widened which values."""
    sb, sa = np.sqrt(np.clip(np.diag(before), 0, None)), np.sqrt(np.clip(np.diag(after), 0, None))
    ratios = [(sa[i] / sb[i], _NAMES[name]) for i, name in enumerate(PARAMETERS) if sb[i] > 0]
    ratios.sort(reverse=True)
    wide = ", ".join(f"{name} x{r:.3g}" for r, name in ratios[:4] if r >= 1.05) or "nothing by 5 % or more"
    tz = PARAMETERS.index("mount_z")
    return (f"the camera's uncorrected systematic allowance ({n_terms} terms: scale, offset, field shapes; "
            f"until cellcal depthcal) is an error common to the {len(observations)} poses, not per-pose noise: "
            f"the poses are weighed by their fits' noise alone, each term's effect on the mount and plane added "
            f"as one coefficient common to them (never scaled by chi2/dof); it widens {wide} "
            f"(tz 1-sigma {1000 * sb[tz]:.3g} -> {1000 * sa[tz]:.3g} mm)")

