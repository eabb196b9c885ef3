"""How a 3D camera measures: :class:`MeasurementModel` (``tof``, ``stereo``, ``structured_light``, ``unknown``).

Every :class:`~cellcal.devices.camera.Camera3D` states one; frames, recordings and replays
carry it, and the full-frame fit takes its noise law, quantisation and native space from it.
Rationale and the figures measured on real cameras: docs/adr/0027-measurement-model.md and
docs/real-sensors.md.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .config import check_value, parse_section
from .errors import ConfigError

__all__ = ["DEFAULT_ALLOWANCES", "DEFAULT_WIGGLE", "KINDS", "TRIANGULATING_KINDS", "UNKNOWN_MODEL", "MeasurementModel"]

Kind = Literal["tof", "stereo", "structured_light", "unknown"]
#: The kinds of measurement a camera can state.
KINDS: tuple[str, ...] = ("tof", "stereo", "structured_light", "unknown")
#: Kinds that measure a disparity ``f·B/Z`` (the fit works in disparity, ADR 0027).
TRIANGULATING_KINDS: tuple[str, ...] = ("stereo", "structured_light")
#: Sources of a model, for reports: who stated it.
SOURCES: tuple[str, ...] = ("unstated", "device", "backend", "sim", "config", "recording")
#: Systematic allowances ``(scale, offset, field)`` per kind, 1-sigma, when a camera states none: the
#: vendors' stated *accuracy*, not their repeatability (issue #39, ADR 0053). Stereo: Luxonis states a
#: median depth error below 2 % under 4 m (scale 1 %, offset 0.1 px, field 0.5 px at the corner, about
#: the column pattern of real OAK frames); ToF: range scale 0.2 %, offset 5 mm, field 2 mm (ifm's O3R
#: accuracy class, a few mm plus a fraction of a percent).
DEFAULT_ALLOWANCES: dict[str, tuple[float, float, float]] = {
    "stereo": (0.01, 0.1, 0.5),
    "tof": (0.002, 0.005, 0.002),
}
#: A ToF camera's wiggling allowance when it states none: 1 mm (1-sigma amplitude) with the period
#: ``c / (8 · 60 MHz)`` = 0.6246 m (ADR 0053).
DEFAULT_WIGGLE: tuple[float, float] = (0.001, 299_792_458.0 / (8.0 * 60e6))


@dataclass(frozen=True)
class MeasurementModel:
    """What a camera measures and how noisy it is (the ``[camera.model]`` table).

    ``tof``: the range along each pixel ray; its 1-sigma is
    ``sigma_at_1m_m · (range / 1 m)^distance_exponent / sqrt(cos incidence)``, plus a
    ``multipath_m`` allowance for the bias of light returned twice, rounded to ``range_step_m``.

    ``stereo`` / ``structured_light``: a disparity ``d = f·B/Z`` (px) of Z-depth ``Z`` (m),
    ``f = focal_px``, ``B = baseline_m`` (the projector's for structured light), measured with
    a 1-sigma ``disparity_sigma_px`` and rounded to ``2^-subpixel_bits`` px, so that the depth
    step at ``Z`` is ``q(Z) = Z² / (f·B) · 2^-subpixel_bits`` (m).

    ``unknown``: nothing is stated; the fit uses the ``[full_frame]`` defaults.

    Attributes:
        kind: One of :data:`KINDS`.
        sigma_at_1m_m: ToF range noise 1-sigma at 1 m, normal incidence, metres (None: not stated).
        distance_exponent: ToF: exponent of the range in the noise law.
        multipath_m: ToF: allowance for a range bias from multipath, metres.
        range_step_m: ToF: the range quantisation step, metres (0: none).
        baseline_m: Stereo: the baseline between the two cameras (projector and camera), metres.
        focal_px: Stereo: focal length of the rectified depth image, pixels.
        subpixel_bits: Stereo: fractional bits of the disparity (0: integer disparity).
        disparity_sigma_px: Stereo: 1-sigma of the disparity before rounding, pixels.
        scale_allowance: 1-sigma of the uncorrected relative depth-scale error (stereo: of ``f·B``; ToF: of
            the range), dimensionless; None: the kind's default (:data:`DEFAULT_ALLOWANCES`, vendors' accuracy).
        offset_allowance: 1-sigma of the uncorrected constant offset, px (stereo) or m (ToF); None: default.
        field_allowance: 1-sigma of the uncorrected smooth image field at the image corner, px (stereo)
            or m (ToF); None: default. After ``cellcal depthcal`` the three are what the correction leaves.
        wiggle_allowance_m: ToF: 1-sigma amplitude of the uncorrected range-periodic error (wiggling), m;
            None: the default (:data:`DEFAULT_WIGGLE`). Its slope ``2π·A/P`` is a local range scale
            (1 mm at 0.62 m is 1 %), so it is carried apart from the scale.
        wiggle_period_m: ToF: the wiggling's period in range, m; None: :data:`DEFAULT_WIGGLE`'s
            (``c / (8 f)`` at 60 MHz: the correlation's 3rd and 5th harmonics alias four times per
            unambiguous range).
        source: Who stated the model (:data:`SOURCES`), for reports.
        settings: Device settings that shaped the model (e.g. the OAK's filters), JSON data.
    """

    kind: Kind = "unknown"
    sigma_at_1m_m: float | None = field(default=None, metadata={"gt": 0.0, "le": 1.0})
    distance_exponent: float = field(default=1.5, metadata={"ge": 0.0, "le": 4.0})
    multipath_m: float = field(default=0.0, metadata={"ge": 0.0, "le": 1.0})
    range_step_m: float = field(default=0.0, metadata={"ge": 0.0, "le": 0.1})
    baseline_m: float | None = field(default=None, metadata={"gt": 0.0, "le": 10.0})
    focal_px: float | None = field(default=None, metadata={"gt": 0.0, "le": 1e5})
    subpixel_bits: int = field(default=0, metadata={"ge": 0, "le": 8})
    disparity_sigma_px: float | None = field(default=None, metadata={"ge": 0.0, "le": 100.0})
    scale_allowance: float | None = field(default=None, metadata={"ge": 0.0, "le": 0.2})
    offset_allowance: float | None = field(default=None, metadata={"ge": 0.0, "le": 100.0})
    field_allowance: float | None = field(default=None, metadata={"ge": 0.0, "le": 100.0})
    wiggle_allowance_m: float | None = field(default=None, metadata={"ge": 0.0, "le": 0.1})
    wiggle_period_m: float | None = field(default=None, metadata={"gt": 0.0, "le": 100.0})
    source: str = "unstated"
    settings: dict[str, Any] = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            if f.name in ("kind", "source", "settings"):
                continue
            value = getattr(self, f.name)
            tp: Any = {"subpixel_bits": int}.get(f.name, float)
            if value is None:
                continue
            object.__setattr__(self, f.name, check_value(value, tp, f.metadata, f"camera.model.{f.name}"))
        if self.kind not in KINDS:
            raise ConfigError(f"must be one of {', '.join(KINDS)}, got {self.kind!r}", key="camera.model.kind")
        if self.kind in TRIANGULATING_KINDS:
            for name in ("baseline_m", "focal_px"):
                if getattr(self, name) is None:
                    raise ConfigError(f"a {self.kind} model needs {name} (> 0)", key=f"camera.model.{name}")

    # ------------------------------------------------------------------ facts
    @property
    def known(self) -> bool:
        """Whether the camera stated how it measures."""
        return self.kind != "unknown"

    @property
    def triangulating(self) -> bool:
        """Whether the camera measures a disparity (stereo or structured light)."""
        return self.kind in TRIANGULATING_KINDS

    @property
    def fb_px_m(self) -> float:
        """``f·B``, px·m: disparity (px) times Z-depth (m). Raises ValueError for other kinds."""
        if not self.triangulating:
            raise ValueError(f"a {self.kind} camera has no disparity")
        assert self.focal_px is not None and self.baseline_m is not None
        return self.focal_px * self.baseline_m

    @property
    def allowance(self) -> tuple[float, float, float]:
        """The systematic allowance ``(scale, offset, field)``: stated values, else the kind's defaults.

        Units: relative; px (stereo) or m (ToF); px or m at the image corner. All 0 for ``unknown``.
        """
        default = DEFAULT_ALLOWANCES.get("stereo" if self.triangulating else self.kind, (0.0, 0.0, 0.0))
        stated = (self.scale_allowance, self.offset_allowance, self.field_allowance)
        return (stated[0] if stated[0] is not None else default[0],
                stated[1] if stated[1] is not None else default[1],
                stated[2] if stated[2] is not None else default[2])

    @property
    def wiggle(self) -> tuple[float, float]:
        """ToF: the wiggling allowance ``(amplitude_m, period_m)``, stated or the default; ``(0, 0)`` otherwise."""
        if self.kind != "tof":
            return (0.0, 0.0)
        amp = self.wiggle_allowance_m if self.wiggle_allowance_m is not None else DEFAULT_WIGGLE[0]
        return (amp, self.wiggle_period_m if self.wiggle_period_m is not None else DEFAULT_WIGGLE[1])

    @property
    def disparity_step_px(self) -> float:
        """The disparity quantisation step ``2^-subpixel_bits``, px (stereo kinds)."""
        return 2.0 ** -self.subpixel_bits

    @property
    def disparity_noise_px(self) -> float:
        """Effective 1-sigma of a disparity: noise and rounding (Sheppard, ``q²/12``), px."""
        sigma = self.disparity_sigma_px or 0.0
        return math.sqrt(sigma * sigma + self.disparity_step_px ** 2 / 12.0)

    def depth_step_m(self, z_m: ArrayLike) -> NDArray[np.float64]:
        """The depth quantisation step at Z-depth ``z_m`` (m): ``Z²/(f·B)·2^-bits`` or the ToF range step."""
        z = np.asarray(z_m, dtype=np.float64)
        if self.triangulating:
            out: NDArray[np.float64] = z * z / self.fb_px_m * self.disparity_step_px
            return out
        return np.full_like(z, self.range_step_m if self.kind == "tof" else 0.0)

    def range_sigma_m(self, range_m: ArrayLike, cos_incidence: ArrayLike = 1.0) -> NDArray[np.float64] | None:
        """The 1-sigma of a measured range (ToF) or Z-depth (stereo), metres; None when not stated.

        Stereo: ``Z²/(f·B) · sigma_d`` with the rounding included (``range_m`` read as Z).
        ToF: the noise law above, the range step's ``q²/12`` added.
        """
        r = np.asarray(range_m, dtype=np.float64)
        if self.triangulating:
            out: NDArray[np.float64] = r * r / self.fb_px_m * self.disparity_noise_px
            return out
        if self.kind == "tof" and self.sigma_at_1m_m is not None:
            c = np.maximum(np.asarray(cos_incidence, dtype=np.float64), 1e-3)
            sigma = self.sigma_at_1m_m * r ** self.distance_exponent / np.sqrt(c)
            return np.sqrt(sigma * sigma + self.range_step_m ** 2 / 12.0)
        return None

    # ------------------------------------------------------------------ (de)serialisation
    def with_source(self, source: str) -> MeasurementModel:
        """The same model stated by ``source``."""
        return dataclasses.replace(self, source=source)

    def to_dict(self) -> dict[str, Any]:
        """JSON form: the kind, the stated values (None ones left out), source and settings."""
        out: dict[str, Any] = {"kind": self.kind}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "kind" or value is None or (f.name == "settings" and not value):
                continue
            out[f.name] = value
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None, *, where: str = "camera.model",
                  source: str | None = None) -> MeasurementModel:
        """Parse a ``[camera.model]`` table or a recording's model (unknown keys and bad values: one line).

        Raises:
            ConfigError: Naming the key (``camera.model.baseline_m``) and what was wrong.
        """
        if data is None:
            return UNKNOWN_MODEL
        try:  # parsed under the name __post_init__ reports (camera.model), then renamed to ``where``
            return parse_section(cls, data, where="camera.model", source=source)
        except ConfigError as exc:
            key = exc.key.replace("camera.model", where, 1) if exc.key else where
            raise ConfigError(exc.reason, source=exc.source or source, key=key) from None

    def describe(self) -> str:
        """One line for humans (mm, px)."""
        if self.triangulating:
            return (f"{self.kind}: baseline {self.baseline_m * 1000:.4g} mm, focal {self.focal_px:.5g} px, "  # type: ignore[operator]
                    f"{self.subpixel_bits} subpixel bits, disparity sigma "
                    f"{'unstated' if self.disparity_sigma_px is None else f'{self.disparity_sigma_px:.3g} px'}"
                    f" ({self.source})")
        if self.kind == "tof":
            sig = "unstated" if self.sigma_at_1m_m is None else f"{self.sigma_at_1m_m * 1000:.3g} mm at 1 m"
            return (f"tof: range sigma {sig}, exponent {self.distance_exponent:.3g}, multipath allowance "
                    f"{self.multipath_m * 1000:.3g} mm ({self.source})")
        return "unknown (the camera states no model; [full_frame] defaults apply)"


#: The model of a camera that states none.
UNKNOWN_MODEL = MeasurementModel()
