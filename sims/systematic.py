"""The sims' systematic depth errors: the ``[sim.systematic]`` table (:class:`SystematicConfig`, ADR 0054).

A real depth camera errs systematically, not only at random (issue #39): a stereo pair's ``f·B`` is
known to a fraction of a percent, its disparity carries an offset and a smooth field over the image;
a ToF camera's range has an offset, a scale error and a wiggle periodic in range. The sims draw them
as a :class:`~cellcal.devices.systematic.SystematicError` in the camera's native space (disparity or
range), applied to the true value before noise and rounding, so a frame is what such a camera
delivers. ``enabled = false`` is the ideal camera of the tests that pin noise-only figures.

Defaults (on, all within the vendors' stated accuracy and the model's stated allowance,
:data:`~cellcal.devices.measurement.DEFAULT_ALLOWANCES`):

* stereo: ``fb_error`` 0.5 % (Luxonis: median depth error < 2 % under 4 m), a disparity offset of
  0.05 px, a radial bow of +0.5 px at the image corner (real OAK frames show a fixed column pattern
  of -0.6..+1.2 px at 0.7 m; 0.5 px is 1 % of the depth at the corner at 0.7 m);
* ToF: a range offset of 3 mm and a scale error of 0.1 % (ifm: a few mm plus a fraction of a percent),
  a wiggle of 1 mm with the period ``c / (8 f)`` = 0.6246 m at f = 60 MHz (four-phase sampling of a
  not quite sinusoidal correlation: its 3rd and 5th harmonics alias to an error four times per
  unambiguous range ``c / (2 f)``), and a radial bow of 1 mm at the image corner.

Beyond the bow, ``disparity_field_px`` / ``range_field_m`` add any smooth field of order 2 (linear
terms: a camera whose depth tilts across the image); zero by default, drawn by the benchmarks that
draw a camera from its stated allowance (every shape the allowance states, not the bow alone).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from cellcal.devices.errors import ConfigError
from cellcal.devices.systematic import SystematicError

__all__ = ["WIGGLE_PERIOD_60MHZ_M", "SystematicConfig", "radial_bow_coeffs"]

#: ``c / (8 f)`` at f = 60 MHz, m: the period in range of a four-phase ToF camera's wiggling error.
WIGGLE_PERIOD_60MHZ_M = 299_792_458.0 / (8.0 * 60e6)


def radial_bow_coeffs(bow: float, width: int, height: int) -> tuple[float, ...]:
    """Field coefficients (order 2, :func:`~cellcal.devices.systematic.field_terms` order) of a radial bow.

    ``bow · r² / r_c²`` with ``r`` the distance in pixels from the principal point and ``r_c`` that of
    the normalised corner ``(u, v) = (±1, ±1)`` (half the image's diagonal): since ``u = Δcol / (W/2)``,
    ``v = Δrow / (H/2)``, ``r² = (W/2)² u² + (H/2)² v²``, so the bow is ``bow · (a² u² + v²) / (a² + 1)``
    with ``a = W / H``: the monomials ``u²`` and ``v²`` alone, exactly.
    """
    a2 = (width / height) ** 2
    # terms of order 2: u, v, u^2, uv, v^2
    return (0.0, 0.0, bow * a2 / (a2 + 1.0), 0.0, bow / (a2 + 1.0))


def _plus(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, ...]:
    """Two fields' coefficients (the same terms) summed."""
    return tuple(x + y for x, y in zip(a, b, strict=True))


@dataclass(frozen=True)
class SystematicConfig:
    """The ``[sim.systematic]`` table: the simulated cameras' systematic depth errors (module docstring)."""

    enabled: bool = field(default=True, metadata={
        "doc": "draw the systematic errors (false: an ideal camera, which then states a zero allowance)"})
    fb_error: float = field(default=0.005, metadata={
        "ge": -0.2, "le": 0.2, "doc": "stereo: relative error of f·B (0.01: disparities 1 % too large)"})
    disparity_offset_px: float = field(default=0.05, metadata={
        "ge": -5.0, "le": 5.0, "doc": "stereo: constant disparity offset, px"})
    disparity_bow_px: float = field(default=0.5, metadata={
        "ge": -10.0, "le": 10.0,
        "doc": "stereo: radial quadratic disparity field, px at the image corner (0 at the principal point)"})
    range_offset_m: float = field(default=0.003, metadata={
        "ge": -0.1, "le": 0.1, "doc": "ToF: constant range offset, m"})
    range_scale_error: float = field(default=0.001, metadata={
        "ge": -0.05, "le": 0.05, "doc": "ToF: relative range scale error"})
    wiggle_amplitude_m: float = field(default=0.001, metadata={
        "ge": 0.0, "le": 0.05, "doc": "ToF: amplitude of the range-periodic wiggling error, m"})
    wiggle_period_m: float = field(default=WIGGLE_PERIOD_60MHZ_M, metadata={
        "ge": 0.0, "le": 10.0, "doc": "ToF: period of the wiggling in range, m (c/(8 f): 0.6246 at 60 MHz; 0: none)"})
    wiggle_phase_deg: float = field(default=0.0, metadata={
        "ge": -360.0, "le": 360.0, "doc": "ToF: phase of the wiggling, A cos(2 pi r / P - phase), degrees"})
    range_bow_m: float = field(default=0.001, metadata={
        "ge": -0.05, "le": 0.05,
        "doc": "ToF: radial quadratic range field, m at the image corner (0 at the principal point)"})

    disparity_field_px: tuple[float, float, float, float, float] = field(default=(0.0, 0.0, 0.0, 0.0, 0.0), metadata={
        "doc": "stereo: further smooth disparity field, px, the coefficients of u, v, u^2, uv, v^2 (u, v: the "
        "pixel's offset from the principal point over half the image's width and height), added to the bow"})
    range_field_m: tuple[float, float, float, float, float] = field(default=(0.0, 0.0, 0.0, 0.0, 0.0), metadata={
        "doc": "ToF: further smooth range field, m, the coefficients of u, v, u^2, uv, v^2 (as "
        "disparity_field_px), added to the bow"})

    def __post_init__(self) -> None:
        for key in ("disparity_field_px", "range_field_m"):
            limit = 10.0 if key == "disparity_field_px" else 0.05
            if any(not math.isfinite(c) or abs(c) > limit for c in getattr(self, key)):
                raise ConfigError(f"each coefficient must be finite and within +-{limit:g}",
                                  key=f"sim.systematic.{key}")
        if self.wiggle_period_m > 0.0 and 2.0 * math.pi * self.wiggle_amplitude_m >= 0.5 * self.wiggle_period_m:
            # the measured range must grow with the true one (and the correction stays a contraction)
            raise ConfigError(f"too large for the period {self.wiggle_period_m} m: 2 pi A / P must stay below 0.5",
                              key="sim.systematic.wiggle_amplitude_m")

    @classmethod
    def off(cls) -> SystematicConfig:
        """An ideal camera: no systematic error drawn, a zero allowance stated."""
        return cls(enabled=False)

    def stereo(self, width: int, height: int) -> SystematicError:
        """The stereo camera's error (zero when disabled) for an image ``width`` x ``height``."""
        if not self.enabled:
            return SystematicError("stereo")
        return SystematicError("stereo", fb_error=self.fb_error, disparity_offset_px=self.disparity_offset_px,
                               field_order=2,
                               field_coeffs=_plus(radial_bow_coeffs(self.disparity_bow_px, width, height),
                                                  self.disparity_field_px))

    def tof(self, width: int, height: int) -> SystematicError:
        """The ToF camera's error (zero when disabled) for an image ``width`` x ``height``."""
        if not self.enabled:
            return SystematicError("tof")
        phase = math.radians(self.wiggle_phase_deg)
        return SystematicError("tof", scale_error=self.range_scale_error, offset_m=self.range_offset_m,
                               wiggle_cos_m=self.wiggle_amplitude_m * math.cos(phase),
                               wiggle_sin_m=self.wiggle_amplitude_m * math.sin(phase),
                               wiggle_period_m=self.wiggle_period_m, field_order=2,
                               field_coeffs=_plus(radial_bow_coeffs(self.range_bow_m, width, height),
                                                  self.range_field_m))

    @property
    def stated_allowance(self) -> dict[str, float | None]:
        """The allowance keyword arguments of the camera's stated model.

        On: None each (the kind's vendor default; a sim states what a vendor would, not its own truth);
        off: zeros (an ideal camera knows it is ideal).
        """
        value = None if self.enabled else 0.0
        return {"scale_allowance": value, "offset_allowance": value, "field_allowance": value}
