"""The sequential change test on normalised innovations, and which block a change was (ADR 0040).

A one-sided CUSUM on each frame's normalised innovation chi2 (3 dof when nothing changed):
``g = max(0, g + min(chi2, clip) - reference)``, alarm when ``g > threshold``. Clipping
bounds what one outlier frame adds (a bad plane fit cannot alarm alone), the reference
far above the mean (3) makes the statistic drift back to 0, and the threshold asks for
several frames well off the model. With the defaults (8, 40, 120) an alarm needs at least
four frames with chi2 above 38 in a row; under the model that has a probability of
about 1e-28 per frame, so 10 000 frames give no alarm (the benchmark runs 10 000).

After an alarm the frames since the statistic last left 0 (the estimated change point)
are fitted twice: a new mount with the plane held to its pre-change information, and a
new plane with the mount held likewise. The one the chi2 test accepts while it rejects
the other is the change; when both fit (the frames since the change do not vary the
pose enough) the kind stays "mount or plane".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cellcal.core.handeye.model import MOUNT_ROTATION, MOUNT_TRANSLATION, PLANE_OFFSET, PLANE_TILT
from cellcal.core.track.linear import Frames, LinearModel
from cellcal.core.track.refit import Refit, marginal_info, refit

FloatArray = NDArray[np.float64]
MOUNT = np.r_[np.arange(9)[MOUNT_ROTATION], np.arange(9)[MOUNT_TRANSLATION]]
PLANE = np.r_[np.arange(9)[PLANE_TILT], PLANE_OFFSET]

KIND_MOUNT = "mount"
KIND_PLANE = "plane"
KIND_EITHER = "mount or plane"


class Cusum:
    """One-sided CUSUM of clipped chi2 values.

    Args:
        reference: Subtracted from every frame's chi2 (the drift back to 0).
        clip: Largest chi2 one frame adds.
        threshold: The statistic above which a change is declared.
    """

    def __init__(self, reference: float = 8.0, clip: float = 40.0, threshold: float = 120.0) -> None:
        if not 0 < reference < clip or threshold <= 0:
            raise ValueError(f"CUSUM needs 0 < reference < clip, threshold > 0; got {reference}, {clip}, {threshold}")
        self.reference, self.clip, self.threshold = reference, clip, threshold
        self.statistic = 0.0
        #: Frames since the statistic last was 0 (those after the estimated change point).
        self.run_length = 0

    def update(self, chi2: float) -> bool:
        """Add one frame's chi2; whether the statistic crossed the threshold."""
        self.statistic = max(0.0, self.statistic + min(chi2, self.clip) - self.reference)
        self.run_length = self.run_length + 1 if self.statistic > 0 else 0
        return self.statistic > self.threshold

    def reset(self) -> None:
        """Back to no evidence of change."""
        self.statistic, self.run_length = 0.0, 0


@dataclass(frozen=True)
class Hypothesis:
    """A fit of the frames after a change with one block new and the other held to its earlier information.

    Attributes:
        kind: The block taken as changed (``"mount"``, ``"plane"``, or ``"mount or plane"``: both new).
        fit: The fit; p_value: probability of its chi2 if the hypothesis holds (1 without dof).
    """

    kind: str
    fit: Refit
    p_value: float


def hypothesis(kind: str, model: LinearModel, frames: Frames, anchor_x: FloatArray, anchor_info: FloatArray,
               weak: float) -> Hypothesis:
    """Fit the frames with ``kind``'s block new (weak prior at the configured values) and the other kept.

    The kept block's prior is its pre-change information (the changed block marginalised out)
    about its pre-change value; ``weak`` (information per parameter) is added everywhere.
    """
    from scipy.stats import chi2 as chi2_dist

    changed = {KIND_MOUNT: MOUNT, KIND_PLANE: PLANE}.get(kind, np.arange(9))
    kept = np.setdiff1d(np.arange(9), changed)
    held = marginal_info(anchor_info, kept, weak) if len(kept) else np.zeros((9, 9))
    prior = held + weak * np.eye(9)
    # the kept block at its old value, the new block toward the configured one
    mean = np.asarray(np.linalg.solve(prior, held @ anchor_x), dtype=np.float64)
    start = anchor_x.copy()
    fit = refit(model, frames, start, prior, mean)
    dof = fit.n_residuals - len(changed)  # the priors add as many terms as parameters they hold
    p = float(chi2_dist.sf(fit.chi2, dof)) if dof > 0 else 1.0
    return Hypothesis(kind, fit, p)


def classify(model: LinearModel, frames: Frames, anchor_x: FloatArray, anchor_info: FloatArray, weak: float,
             accept_level: float, reject_level: float) -> tuple[str | None, Hypothesis, Hypothesis]:
    """Which block changed: ``"mount"``, ``"plane"``, ``"mount or plane"`` (neither alone fits) or None (both do).

    Args:
        accept_level: A hypothesis fits when its p-value is at least this.
        reject_level: It is ruled out when its p-value is below this.
    """
    mount = hypothesis(KIND_MOUNT, model, frames, anchor_x, anchor_info, weak)
    plane = hypothesis(KIND_PLANE, model, frames, anchor_x, anchor_info, weak)
    if mount.p_value >= accept_level and plane.p_value < reject_level:
        return KIND_MOUNT, mount, plane
    if plane.p_value >= accept_level and mount.p_value < reject_level:
        return KIND_PLANE, mount, plane
    if mount.p_value < reject_level and plane.p_value < reject_level:
        return KIND_EITHER, mount, plane  # neither alone: both changed (or a bad stretch of frames)
    return None, mount, plane


__all__ = ["KIND_EITHER", "KIND_MOUNT", "KIND_PLANE", "MOUNT", "PLANE", "Cusum", "Hypothesis", "classify",
           "hypothesis"]
