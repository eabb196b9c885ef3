"""The result of a depth calibration (:class:`DepthcalResult`, ``cellcal.depthcal/1``) and :func:`load_correction`.

``DIR/depthcal.json`` holds the correction (``cellcal.systematic/1`` under ``"correction"``, with its
covariance), the plane in the base frame, the field order and its held-out scores, per view the
residual RMS before and after the correction, the observability report and, when estimated, the
mount. Every quantity is in SI units or the camera's native unit (px for stereo, m for ToF), said
in the key's name or beside it.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.calibration.report import write_json_atomic
from cellcal.core.depthcal.observability import Observability
from cellcal.devices.errors import ConfigError
from cellcal.devices.pose import Pose
from cellcal.devices.systematic import SystematicError

__all__ = ["RESULT_SCHEMA", "DepthcalResult", "ViewResidual", "load_correction"]

#: Schema of ``depthcal.json``.
RESULT_SCHEMA = "cellcal.depthcal/1"
FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ViewResidual:
    """One view's residual to the calibrated model, before and after the correction.

    Attributes:
        name: The view's label.
        held_out: Whether the view was left out of the fit the figures come from (a fair test).
        n_points: Points used (inliers of the view's sample).
        rms_before: Residual RMS with no correction (the plane refitted without it), native unit (px or m).
        rms_after: Residual RMS with the correction, native unit.
        rms_before_m: The same in depth along the optical axis (stereo) or range (ToF), m.
        rms_after_m: The same after the correction, m.
    """

    name: str
    held_out: bool
    n_points: int
    rms_before: float
    rms_after: float
    rms_before_m: float
    rms_after_m: float

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {"name": self.name, "held_out": self.held_out, "n_points": self.n_points,
                "rms_before": self.rms_before, "rms_after": self.rms_after,
                "rms_before_m": self.rms_before_m, "rms_after_m": self.rms_after_m}


@dataclass(frozen=True)
class DepthcalResult:
    """A depth calibration: the correction with its covariance, the plane, the held-out errors, what was seen.

    Attributes:
        correction: The fitted systematic error (its ``covariance`` that of the fitted parameters; terms
            not estimated, e.g. the wiggling without a period, have zero variance).
        plane_normal_base: Unit normal of the plane in the base frame (towards the camera).
        plane_offset_m: ``n · x = offset`` for points ``x`` of the plane, base frame, m.
        plane_covariance: 3x3 over the normal's two tilt angles (rad) and the offset (m).
        field_order: The image field's order the held-out error chose.
        order_scores: Held-out residual RMS (native unit) per field order tried.
        views: Per view, the residual before and after.
        holdout_rms_before: RMS over the held-out views without correction, native unit.
        holdout_rms_after: RMS over the held-out views with the correction fitted without them, native unit.
        noise_only_rms: What the noise alone would give on the held-out views, native unit.
        observability: What the plan sees of each parameter.
        mount: The mount ``T_flange_camera`` when estimated, else None.
        mount_covariance: 6x6 over the mount's rotation vector (rad) and translation (m) perturbation, or None.
        kind: ``"stereo"`` or ``"tof"`` (the native unit: px or m).
        variance_factor: What the covariance was multiplied by (chi-square per degree of freedom and the
            design effect of correlated residuals, never below 1).
        n_points: Inlier points of the final fit.
        elapsed_s: Time the fit took, s.
        notes: Sentences for the report (intervals widened, parameters not seen).
    """

    correction: SystematicError
    plane_normal_base: FloatArray
    plane_offset_m: float
    plane_covariance: FloatArray
    field_order: int
    order_scores: dict[int, float]
    views: list[ViewResidual]
    holdout_rms_before: float
    holdout_rms_after: float
    noise_only_rms: float
    observability: Observability
    mount: Pose | None = None
    mount_covariance: FloatArray | None = None
    kind: str = "stereo"
    variance_factor: float = 1.0
    n_points: int = 0
    elapsed_s: float = 0.0
    notes: tuple[str, ...] = field(default=())

    @property
    def unit(self) -> str:
        """The native unit of the residuals: ``"px"`` (stereo) or ``"m"`` (ToF)."""
        return "px" if self.kind == "stereo" else "m"

    def sigma(self, name: str) -> float:
        """1-sigma of one of the correction's parameters (:attr:`SystematicError.names`)."""
        return float(self.correction.leftover_sigma([name])[0])

    def to_dict(self) -> dict[str, Any]:
        """JSON form, schema ``cellcal.depthcal/1`` (SI units; residuals in the native unit and in metres)."""
        def finite(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None
        return {
            "schema": RESULT_SCHEMA,
            "kind": self.kind,
            "native_unit": self.unit,
            "correction": self.correction.to_dict(),
            "correction_sigma": dict(zip(self.correction.names,
                                         self.correction.leftover_sigma(self.correction.names).tolist(), strict=True)),
            "plane": {"normal_base": [float(x) for x in self.plane_normal_base],
                      "offset_m": float(self.plane_offset_m),
                      "covariance_tilt_a_rad_tilt_b_rad_offset_m": np.asarray(self.plane_covariance).tolist()},
            "field_order": self.field_order,
            "order_scores": {str(k): finite(v) for k, v in sorted(self.order_scores.items())},
            "holdout": {"rms_before": finite(self.holdout_rms_before), "rms_after": finite(self.holdout_rms_after),
                        "noise_only_rms": finite(self.noise_only_rms)},
            "views": [v.to_dict() for v in self.views],
            "observability": self.observability.to_dict(),
            "mount": None if self.mount is None else self.mount.to_dict(),
            "mount_covariance_rotvec_rad_translation_m": (None if self.mount_covariance is None
                                                          else np.asarray(self.mount_covariance).tolist()),
            "variance_factor": self.variance_factor,
            "n_points": self.n_points,
            "elapsed_s": self.elapsed_s,
            "notes": list(self.notes),
        }

    def write(self, path: str | Path) -> None:
        """Write :meth:`to_dict` to ``path`` atomically (a temp file in the same directory, then a rename)."""
        write_json_atomic(path, self.to_dict())


def load_correction(path: str | Path) -> SystematicError:
    """The correction of a ``depthcal.json`` (its ``"correction"``) or of a bare ``cellcal.systematic/1`` file.

    Raises:
        ConfigError: One line naming the file and what is wrong (missing, not JSON, not a correction).
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError("no such file (run `cellcal depthcal` to make one)", source=str(p)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot be read: {getattr(exc, 'strerror', None) or exc}", source=str(p)) from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"is not JSON (line {exc.lineno}: {exc.msg})", source=str(p)) from None
    if not isinstance(data, dict):
        raise ConfigError(f"expected a JSON object, got {type(data).__name__}", source=str(p))
    schema = data.get("schema")
    if schema == RESULT_SCHEMA:
        if "correction" not in data:
            raise ConfigError("a depthcal result without its correction", source=str(p), key="correction")
        table, where = data["correction"], "correction"
    elif schema == "cellcal.systematic/1":
        table, where = data, "systematic"
    else:
        raise ConfigError(f"schema {schema!r} is neither {RESULT_SCHEMA!r} nor 'cellcal.systematic/1'",
                          source=str(p), key="schema")
    try:
        return SystematicError.from_dict(table, where=where)
    except ConfigError as exc:
        raise ConfigError(exc.reason, source=str(p), key=exc.key) from None
