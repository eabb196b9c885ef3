"""Does the stated noise explain the residuals? A chi2 test both ways and the Birge scaling of the intervals.

The hand-eye fit weighs every pose by a stated noise (the full-frame plane's covariance plus
the arm's read-back noise). Its chi2 over the degrees of freedom tells whether that noise
is right: far above 1, the noise is understated and absolute intervals would be too
narrow, so the covariance is scaled by chi2/dof (the Birge ratio squared) and the
intervals take Student-t quantiles (the scale is estimated from the data); so far above
that the model is plainly wrong, the fit is refused (gate ``noise_model``); far below 1,
the noise is overstated or the residuals are not independent, which is said, but the
intervals are never narrowed below the absolute ones (ADR 0030).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.errors import CalibrationQualityError

FloatArray = NDArray[np.float64]
Verdict = Literal["consistent", "scaled", "too_good", "untested"]

#: Default level of the chi2 test, each tail (a correct noise model is flagged in 1 % of runs per tail).
NOISE_TEST_LEVEL = 0.01
#: Default largest interval scale (residuals 10x the stated noise) before the fit is refused.
MAX_INTERVAL_SCALE = 10.0


@dataclass(frozen=True)
class NoiseCheck:
    """The verdict on the stated noise and what it does to the intervals.

    Attributes:
        chi2: Sum of the squared whitened residuals (with the given values' prior terms).
        dof: Residuals minus estimated parameters.
        level: Level of the test, each tail.
        verdict: ``consistent``; ``scaled`` (chi2 too large: covariance times chi2/dof);
            ``too_good`` (chi2 too small: intervals kept absolute); ``untested`` (no dof).
        interval_scale: Factor on every 1-sigma (sqrt of chi2/dof when scaled, else 1).
        interval_z: Half-width of the intervals in (scaled) sigmas: normal, or Student-t with
            ``dof`` degrees of freedom when the scale comes from the data.
        confidence: Level of the intervals.
    """

    chi2: float
    dof: int
    level: float
    verdict: Verdict
    interval_scale: float
    interval_z: float
    confidence: float

    @property
    def chi2_per_dof(self) -> float:
        """chi2/dof (NaN without dof)."""
        return self.chi2 / self.dof if self.dof > 0 else math.nan

    @property
    def p_above(self) -> float:
        """Probability of a chi2 at least this large if the stated noise holds."""
        from scipy.stats import chi2

        return float(chi2.sf(self.chi2, self.dof)) if self.dof > 0 else math.nan

    @property
    def p_below(self) -> float:
        """Probability of a chi2 at most this small if the stated noise holds."""
        from scipy.stats import chi2

        return float(chi2.cdf(self.chi2, self.dof)) if self.dof > 0 else math.nan

    def note(self) -> str | None:
        """One line saying what the test found and what it did to the intervals (None when consistent)."""
        if self.verdict == "scaled":
            return (f"chi2/dof {self.chi2_per_dof:.2f} is more than {self.dof} dof allow (p = {self.p_above:.2g} "
                    f"< {self.level:g}): the residuals exceed the stated noise, so the intervals are scaled by "
                    f"{self.interval_scale:.2f} (sqrt of chi2/dof) with Student-t quantiles ({self.dof} dof)")
        if self.verdict == "too_good":
            return (f"chi2/dof {self.chi2_per_dof:.2f} is less than {self.dof} dof allow (p = {self.p_below:.2g} "
                    f"< {self.level:g}): the stated noise is too pessimistic or the poses' residuals are not "
                    "independent; the intervals keep the stated noise (not narrowed)")
        if self.verdict == "untested":
            return "no degrees of freedom left: the noise model cannot be checked, the intervals assume it"
        return None

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {"verdict": self.verdict, "chi2_per_dof": None if self.dof <= 0 else self.chi2_per_dof,
                "p_above": None if self.dof <= 0 else self.p_above, "p_below": None if self.dof <= 0 else self.p_below,
                "test_level": self.level, "interval_scale": self.interval_scale, "interval_z": self.interval_z,
                "note": self.note()}


def normal_z(confidence: float) -> float:
    """Half-width of a two-sided normal interval at ``confidence``, in sigmas."""
    from scipy.stats import norm

    return float(norm.ppf(0.5 + confidence / 2.0))


def check_noise(chi2: float, dof: int, *, confidence: float, level: float = NOISE_TEST_LEVEL,
                max_interval_scale: float = MAX_INTERVAL_SCALE, detail: str = "") -> NoiseCheck:
    """Test chi2 against its distribution with ``dof`` degrees of freedom, both tails at ``level``.

    Args:
        chi2: Sum of squared whitened residuals.
        dof: Degrees of freedom.
        confidence: Level of the intervals.
        level: Level of each tail of the test.
        max_interval_scale: Largest sqrt(chi2/dof) the intervals are scaled to; above it the fit is refused.
        detail: Appended to the refusal's message (e.g. the worst pose).

    Raises:
        CalibrationQualityError: Gate ``noise_model`` when sqrt(chi2/dof) exceeds ``max_interval_scale``
            and the test rejects the stated noise.
    """
    from scipy.stats import chi2 as chi2_dist
    from scipy.stats import t as student_t

    z = normal_z(confidence)
    if dof <= 0:
        return NoiseCheck(chi2, dof, level, "untested", 1.0, z, confidence)
    if chi2_dist.sf(chi2, dof) < level:  # more residual than the stated noise allows
        scale = math.sqrt(chi2 / dof)
        if scale > max_interval_scale:
            raise CalibrationQualityError(
                "noise_model", scale, max_interval_scale,
                f"the residuals are {scale:.1f}x the stated noise (chi2 {chi2:.4g} over {dof} dof): the noise "
                "model ([handeye] arm_translation_sigma_m / arm_rotation_sigma_deg) or a given value is wrong, "
                "or the plane moved" + (f"; {detail}" if detail else ""))
        t_z = float(student_t.ppf(0.5 + confidence / 2.0, dof))  # the scale is estimated: t quantile
        return NoiseCheck(chi2, dof, level, "scaled", scale, t_z, confidence)
    if chi2_dist.cdf(chi2, dof) < level:  # less residual than the stated noise allows
        return NoiseCheck(chi2, dof, level, "too_good", 1.0, z, confidence)
    return NoiseCheck(chi2, dof, level, "consistent", 1.0, z, confidence)


def scaled_covariance(info_data: FloatArray, info_prior: FloatArray, scale: float) -> FloatArray:
    """Covariance of the fitted parameters with the data's noise scaled by ``scale`` (not the priors').

    Args:
        info_data: ``JᵀJ`` of the whitened data residuals.
        info_prior: Information of the given values' priors (diagonal, 1/sigma²; 0 for free parameters).
        scale: Factor on the data's 1-sigma (the Birge ratio); 1 gives the absolute covariance.
    """
    info = np.asarray(info_data / scale**2 + info_prior, dtype=np.float64)  # data variance times scale²
    cov: FloatArray = np.asarray(np.linalg.inv(info), dtype=np.float64)
    return cov


__all__ = ["MAX_INTERVAL_SCALE", "NOISE_TEST_LEVEL", "NoiseCheck", "check_noise", "normal_z", "scaled_covariance"]
