"""The simulated ToF camera's measurement model: return amplitude, range noise, drift, switches.

The ``[sim.artefacts]`` table (:class:`ArtefactsConfig`) switches each real-camera
artefact on or off; all are on by default at the levels argued, with their sources, in
docs/adr/0014-simulated-cell.md. Mixed pixels and multipath are computed in
:mod:`cellcal.sims.mixed_pixels` and :mod:`cellcal.sims.multipath`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellcal.devices.errors import ConfigError
from cellcal.devices.measurement import MeasurementModel

from .scene import DEFAULT_REFLECTIVITY

FloatArray = NDArray[np.float64]

#: Distance-noise sigma at 1 m, normal incidence, reference target, metres.
SIGMA_AT_1M_M = 0.0032
#: Exponent of the distance in the data-sheet noise law (``amplitude_noise = false``).
SIGMA_DISTANCE_EXPONENT = 1.5
#: The defaults: the amplitude law set against a real O3R frame (:func:`amplitude_sigma_m`, ADR 0014): the
#: range-independent per-pixel noise, m; the shot-noise term of the reference return at 1 m, m; the ambient +
#: dark floor, relative to the reference return at 1 m.
PIXEL_NOISE_M = 0.0027
SHOT_NOISE_AT_1M_M = 0.00224
NOISE_FLOOR = 0.9
#: The same three as ``[sim.artefacts]`` keys: ``ArtefactsConfig(**O3R_MEASURED_NOISE)`` is the default.
O3R_MEASURED_NOISE = {"pixel_noise_m": PIXEL_NOISE_M, "shot_noise_at_1m_m": SHOT_NOISE_AT_1M_M,
                      "noise_floor": NOISE_FLOOR}
#: The earlier defaults, the amplitude law fitted to ifm's quoted repeatability alone (no per-pixel term):
#: ``ArtefactsConfig(**DATASHEET_FIT_NOISE)`` draws it (1.0 mm on the real frame's face, 3 x too quiet).
DATASHEET_FIT_NOISE = {"pixel_noise_m": 0.0, "shot_noise_at_1m_m": SIGMA_AT_1M_M, "noise_floor": 0.25}
#: Reflectivity of the reference target: amplitude 1 (relative) at 1 m, normal incidence.
REFERENCE_REFLECTIVITY = DEFAULT_REFLECTIVITY
#: Speed of light, m/s.
SPEED_OF_LIGHT_M_S = 299_792_458.0


@dataclass(frozen=True)
class ArtefactsConfig:
    """The ``[sim.artefacts]`` table: the real-camera artefacts of the simulated ToF camera.

    Amplitudes are *relative*: 1 is the return of the reference target (reflectivity
    0.5) at 1 m, normal incidence; a surface of reflectivity ``rho`` at range ``d`` and
    incidence ``theta`` returns ``(rho / 0.5) cos(theta) / d**2``.
    """

    mixed_pixels: bool = field(default=True, metadata={
        "doc": "a pixel straddling a depth edge returns the blend of the depths it sees"})
    psf_sigma_px: float = field(default=0.4, metadata={
        "ge": 0.0, "le": 1.0, "doc": "lens blur (Gaussian sigma) widening a pixel's footprint, px"})
    supersampling: int = field(default=3, metadata={"ge": 2, "le": 8,
                                                    "doc": "sub-rays per pixel width over an edge pixel's footprint"})
    multipath: bool = field(default=True, metadata={
        "doc": "light reflected twice (concave corners, strong reflectors) biases the range long"})
    multipath_patches: int = field(default=56, metadata={
        "ge": 8, "le": 512, "doc": "width of the patch grid the second bounce is computed on"})
    amplitude_noise: bool = field(default=True, metadata={
        "doc": "range noise from the return amplitude; invalidate low and saturated amplitudes "
               "(false: the data-sheet law 3.2 mm (d/1 m)^1.5 / sqrt(cos))"})
    noise_floor: float = field(default=NOISE_FLOOR, metadata={
        "ge": 0.0, "le": 100.0, "doc": "ambient + dark noise, in units of the reference return at 1 m"})
    shot_noise_at_1m_m: float = field(default=SHOT_NOISE_AT_1M_M, metadata={
        "ge": 0.0, "le": 0.1, "doc": "amplitude-law noise of the reference return at 1 m, m"})
    pixel_noise_m: float = field(default=PIXEL_NOISE_M, metadata={
        "ge": 0.0, "le": 0.1, "doc": "range-independent per-pixel noise in quadrature, m (measured on a real O3R)"})
    min_amplitude: float = field(default=0.05, metadata={
        "ge": 0.0, "le": 10.0, "doc": "relative amplitude below which a pixel is invalid (low amplitude)"})
    saturation_amplitude: float = field(default=100.0, metadata={
        "gt": 0.0, "le": 1e6, "doc": "relative amplitude above which a pixel is invalid (saturated)"})
    temperature_drift: bool = field(default=True, metadata={
        "doc": "range offset decaying as the camera warms up (simulated clock)"})
    drift_m: float = field(default=0.004, metadata={
        "ge": -0.05, "le": 0.05, "doc": "range offset of a cold camera, m"})
    drift_time_constant_s: float = field(default=300.0, metadata={
        "gt": 0.0, "le": 86400.0, "doc": "time constant of the warm-up, s"})
    warm_up_s: float = field(default=3600.0, metadata={
        "ge": 0.0, "le": 1e7, "doc": "how long the camera has been on when the world starts, s (0: cold)"})
    modulation_frequency_hz: float = field(default=60e6, metadata={
        "ge": 1e6, "le": 1e9, "doc": "modulation frequency (phase of blended returns), Hz"})

    def __post_init__(self) -> None:
        if self.saturation_amplitude <= self.min_amplitude:
            raise ConfigError(f"must exceed min_amplitude ({self.min_amplitude})",
                              key="sim.artefacts.saturation_amplitude")

    @classmethod
    def off(cls) -> ArtefactsConfig:
        """Every artefact switched off (the sim as it was before them)."""
        return cls(mixed_pixels=False, multipath=False, amplitude_noise=False, temperature_drift=False)

    @property
    def wavenumber_rad_m(self) -> float:
        """Phase per metre of *range* (the light travels it twice): ``4 pi f / c``, rad/m."""
        return 4.0 * math.pi * self.modulation_frequency_hz / SPEED_OF_LIGHT_M_S


def relative_amplitude(distance_m: ArrayLike, cos_incidence: ArrayLike,
                       reflectivity: ArrayLike = REFERENCE_REFLECTIVITY) -> FloatArray:
    """Return amplitude relative to the reference target at 1 m, normal: ``(rho / 0.5) cos / d**2``.

    A Lambertian surface lit by the camera's own illuminator: irradiance ``cos / d**2``,
    radiance ``rho / pi`` of it; the pixel's solid angle cancels the footprint's growth.
    """
    d = np.asarray(distance_m, dtype=np.float64)
    c = np.clip(np.asarray(cos_incidence, dtype=np.float64), 0.0, 1.0)
    rho = np.asarray(reflectivity, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        out: FloatArray = (rho / REFERENCE_REFLECTIVITY) * c / np.square(d)
    return out


def amplitude_sigma_m(amplitude: ArrayLike, noise_floor: float = NOISE_FLOOR, noise_scale: float = 1.0, *,
                      shot_noise_at_1m_m: float = SHOT_NOISE_AT_1M_M, pixel_noise_m: float = PIXEL_NOISE_M
                      ) -> FloatArray:
    """Range-noise sigma (m) from the relative return amplitude ``a``.

    ``sigma = noise_scale * sqrt(F**2 + (S * sqrt((a + n) / (1 + n)) / a)**2)``: the phase
    noise of a lock-in pixel (Lange 2000; Lefloch et al. 2013), photon shot noise of the
    signal ``1 / sqrt(a)`` for strong returns, the ambient/dark floor ``n`` giving ``1 / a``
    for weak ones, plus ``F``, a per-pixel noise that does not fall as the return grows.

    Set against a real O3R frame (ifm's ``O3RBuffer.data``, 224 x 172, scene at 0.2-2 m): the
    pixel-to-pixel range scatter (robust second differences of the range image, MAD / sqrt 6;
    equal at lags 1 and 2, so white at the pixel scale) is 3.0 mm on a flat box face at
    0.28 m (incidence 50 deg, amplitude 1.26), 3.0-4.2 mm in every range bin 0.2-1 m and
    3.4-3.7 mm at normalised amplitudes 0.2-1.3; only weak returns are noisier (4.8-6.2 mm
    below amplitude 0.2, 5.3 mm at 1-2 m). The camera's own noise image (chunk 105) says
    0.3-1.2 mm there, 2.4-10 x less (it falls with range: each pixel's exposure is chosen
    for its return). The defaults, :data:`O3R_MEASURED_NOISE` (``F = 2.7 mm``, ``S = 2.24 mm``,
    ``n = 0.9``), give 2.77 mm on the face (the sim's frame measured as the real one: 2.68 mm
    against 2.96 mm), 3.0 mm head-on at 0.7 m (3.3 mm at 50 deg), and still meet the quoted
    repeatability read as 2 sigma for the grey target (5.7 mm at 0.5 m, 6.97 mm at 0.99 m: < 7 mm
    under 1 m; 10.1 / 15.0 mm at 1.5 / 2 m: ~15 mm; 51.3 mm at 4 m: 51 mm). The earlier defaults,
    :data:`DATASHEET_FIT_NOISE` (``F = 0``, ``S = 3.2 mm``, ``n = 0.25``, fitted to the quoted
    repeatability alone), give 1.0 mm on that face and grow ~d with range: 3 x too quiet at
    0.3 m. One frame cannot tell temporal noise from a fixed per-pixel pattern: the sim draws
    all of it anew each frame.

    Args:
        amplitude: Relative amplitude (1 = reference target at 1 m, normal), > 0.
        noise_floor: ``n``, in the same units.
        noise_scale: Multiplier (0 = noise-free).
        shot_noise_at_1m_m: ``S``, metres.
        pixel_noise_m: ``F``, metres.
    """
    a = np.maximum(np.asarray(amplitude, dtype=np.float64), 1e-9)
    # the amplitude-dependent term, then the per-pixel term in quadrature
    shot = shot_noise_at_1m_m * np.sqrt((a + noise_floor) / (1.0 + noise_floor)) / a
    out: FloatArray = noise_scale * np.sqrt(shot * shot + pixel_noise_m * pixel_noise_m)
    return out


def datasheet_sigma_m(distance_m: ArrayLike, cos_incidence: ArrayLike = 1.0, noise_scale: float = 1.0
                      ) -> FloatArray:
    """The data-sheet noise law, used with ``amplitude_noise = false``.

    ``sigma = noise_scale * 3.2 mm * (d / 1 m)**1.5 / sqrt(cos θ)``: reading ifm's quoted
    repeatability as 2 sigma at normal incidence this gives 2.3 mm at 0.6 m, 6.4 mm at 1 m
    (quoted < 7 mm under 1 m), 11.8 mm at 1.5 m and 18.1 mm at 2 m (quoted ~15 mm at
    1-2 m) and 51 mm at 4 m (quoted up to 51 mm beyond 4 m).
    """
    d = np.asarray(distance_m, dtype=np.float64)
    c = np.clip(np.asarray(cos_incidence, dtype=np.float64), 1e-6, 1.0)
    # d**1.5 via sqrt: several times faster than pow
    out: FloatArray = (noise_scale * SIGMA_AT_1M_M) * d * np.sqrt(d / c)
    return out


def noise_sigma_m(distance_m: ArrayLike, cos_incidence: ArrayLike = 1.0, noise_scale: float = 1.0,
                  reflectivity: ArrayLike = REFERENCE_REFLECTIVITY, noise_floor: float = NOISE_FLOOR, *,
                  shot_noise_at_1m_m: float = SHOT_NOISE_AT_1M_M, pixel_noise_m: float = PIXEL_NOISE_M
                  ) -> FloatArray:
    """Range-noise sigma (m) of the default camera for a surface at ``distance_m``.

    :func:`amplitude_sigma_m` of :func:`relative_amplitude` (mixed pixels and multipath
    aside, which change the amplitude).

    Args:
        distance_m: True radial distance, metres.
        cos_incidence: Cosine of the angle between ray and surface normal (0..1].
        noise_scale: Multiplier (0 = noise-free).
        reflectivity: Surface reflectivity (the reference target by default).
        noise_floor: Ambient + dark noise, relative amplitude.
        shot_noise_at_1m_m: Amplitude-law noise of the reference return at 1 m, metres.
        pixel_noise_m: Range-independent per-pixel noise, metres.
    """
    c = np.clip(np.asarray(cos_incidence, dtype=np.float64), 1e-6, 1.0)
    return amplitude_sigma_m(relative_amplitude(distance_m, c, reflectivity), noise_floor, noise_scale,
                             shot_noise_at_1m_m=shot_noise_at_1m_m, pixel_noise_m=pixel_noise_m)


def drift_offset_m(config: ArtefactsConfig, elapsed_s: float) -> float:
    """Range offset (m) from the camera's temperature at simulated time ``elapsed_s``.

    ``drift_m * exp(-(warm_up_s + elapsed_s) / drift_time_constant_s)``: the offset of a
    cold camera decays as it warms up; 0 with ``temperature_drift`` off.
    """
    if not config.temperature_drift:
        return 0.0
    return config.drift_m * math.exp(-(config.warm_up_s + max(0.0, elapsed_s)) / config.drift_time_constant_s)


#: Ranges (m) and incidence cosines over which the amplitude law is summarised as a power law.
STATED_RANGE_M = (0.25, 1.2)
STATED_COS = (0.5, 1.0)


def stated_tof_model(config: ArtefactsConfig, *, noise: bool = True, noise_scale: float = 1.0,
                     range_step_m: float = 0.0, systematic: bool = True) -> MeasurementModel:
    """The :class:`~cellcal.devices.measurement.MeasurementModel` the simulated ToF camera states.

    The model's law is ``sigma_at_1m_m * (d / 1 m)^distance_exponent / sqrt(cos)``.

    * ``amplitude_noise = false``: the camera draws exactly that law (:func:`datasheet_sigma_m`):
      3.2 mm x ``noise_scale``, exponent 1.5.
    * ``amplitude_noise = true`` (default): the camera draws :func:`noise_sigma_m` of the
      return's amplitude, which no power law of the range matches everywhere. The stated law
      is its least-squares fit in ``log sigma`` for the reference target (reflectivity 0.5)
      over ``STATED_RANGE_M`` (0.25-1.2 m, the cell's working range) and ``STATED_COS``
      (incidence 0-60 deg), on a 16 x 6 grid: for the defaults (:data:`O3R_MEASURED_NOISE`)
      3.3 mm at 1 m, exponent 0.31, within -22 %/+24 % of the drawn sigma there (the model's
      ``1/sqrt(cos)`` is steeper than the sim's, and than the real O3R's, incidence
      dependence); for :data:`DATASHEET_FIT_NOISE` 3.3 mm, exponent 1.11, within -11 %/+5 %;
      darker or brighter surfaces are noisier or quieter than it says.
    * ``noise = false`` or ``noise_scale = 0``: ``sigma_at_1m_m`` is None (not stated), so
      nothing expects noise of a noise-free frame and nothing is told "zero" of a noisy one.

    ``range_step_m`` is the distance quantisation; ``multipath_m`` stays 0 (the sim's
    multipath is a bias of the scene, not a per-pixel allowance; ADR 0014 gives its levels).

    The systematic allowance: with ``[sim.systematic]`` on (``systematic``) the ToF default (None: a sim
    states what a vendor would, not its own truth); off, zeros (an ideal camera knows it is ideal). ADR 0054.

    Args:
        config: The world's ``[sim.artefacts]``.
        noise: The camera's ``noise`` key.
        noise_scale: The camera's ``noise_scale`` key.
        range_step_m: The camera's ``quantisation_m``, metres.
        systematic: Whether ``[sim.systematic]`` is enabled.
    """
    value = None if systematic else 0.0
    allowance: dict[str, Any] = {"scale_allowance": value, "offset_allowance": value, "field_allowance": value,
                                 "wiggle_allowance_m": value}
    settings: dict[str, Any] = {"noise_law": "amplitude" if config.amplitude_noise else "datasheet",
                                "noise_scale": noise_scale}
    if not noise or noise_scale <= 0.0:
        return MeasurementModel(kind="tof", sigma_at_1m_m=None, range_step_m=range_step_m, source="sim",
                                settings={**settings, "noise": False}, **allowance)
    if not config.amplitude_noise:
        return MeasurementModel(kind="tof", sigma_at_1m_m=SIGMA_AT_1M_M * noise_scale,
                                distance_exponent=SIGMA_DISTANCE_EXPONENT, range_step_m=range_step_m,
                                source="sim", settings=settings, **allowance)
    s1, p = _fit_power_law(config.noise_floor, config.shot_noise_at_1m_m, config.pixel_noise_m)
    return MeasurementModel(kind="tof", sigma_at_1m_m=s1 * noise_scale, distance_exponent=p,
                            range_step_m=range_step_m, source="sim",
                            settings={**settings, "noise_floor": config.noise_floor,
                                      "shot_noise_at_1m_m": config.shot_noise_at_1m_m,
                                      "pixel_noise_m": config.pixel_noise_m,
                                      "fitted_over_range_m": list(STATED_RANGE_M),
                                      "fitted_over_cos": list(STATED_COS)}, **allowance)


@functools.lru_cache(maxsize=16)
def _fit_power_law(noise_floor: float, shot_noise_at_1m_m: float, pixel_noise_m: float) -> tuple[float, float]:
    """``(sigma_at_1m_m, exponent)`` of the power law nearest :func:`noise_sigma_m` in log space."""
    # the grid: ranges (log-spaced) x incidence cosines
    d, c = np.meshgrid(np.geomspace(*STATED_RANGE_M, 16), np.linspace(*STATED_COS, 6))
    sigma = noise_sigma_m(d, c, 1.0, REFERENCE_REFLECTIVITY, noise_floor, shot_noise_at_1m_m=shot_noise_at_1m_m,
                          pixel_noise_m=pixel_noise_m)
    # log sigma + 0.5 log cos = log s1 + p log d: linear least squares in (log s1, p)
    a = np.column_stack([np.ones(d.size), np.log(d).ravel()])
    coef, *_ = np.linalg.lstsq(a, (np.log(sigma) + 0.5 * np.log(c)).ravel(), rcond=None)
    return float(np.exp(coef[0])), float(coef[1])
