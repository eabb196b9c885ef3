"""The measurement models' numbers pinned against independent computations (issue #32).

Interval widths come from the model's sigmas, so each is checked against something the
model does not compute itself: a Monte Carlo of a camera that rounds a noisy disparity, a
finite difference of ``Z = f·B/d``, the ToF noise law's slopes in log-log, Sheppard's
``q²/12`` against a simulated rounding. Every field limit is tried on both sides of its
boundary, and the texts a user reads (errors, ``describe``) are pinned whole.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from cellcal.devices.errors import ConfigError
from cellcal.devices.measurement import KINDS, TRIANGULATING_KINDS, UNKNOWN_MODEL, MeasurementModel

F_PX, B_M = 440.0, 0.075        # an OAK-D at 400P: f·B = 33 px·m (docs: /work/shared/spec/sensors.md)
FB = F_PX * B_M


def stereo(bits: int = 3, sigma_px: float | None = 0.1, kind: str = "stereo") -> MeasurementModel:
    return MeasurementModel(kind=kind, baseline_m=B_M, focal_px=F_PX, subpixel_bits=bits,  # type: ignore[arg-type]
                            disparity_sigma_px=sigma_px)


def simulated_depths(z_true: np.ndarray, sigma_px: float, bits: int, rng: np.random.Generator) -> np.ndarray:
    """What a stereo camera reports for true Z-depths: ``f·B / round(f·B/Z + noise, 2^-bits)``, metres."""
    q = 2.0**-bits
    d = FB / z_true + sigma_px * rng.standard_normal(z_true.shape)
    return FB / (np.round(d / q) * q)


# ---------------------------------------------------------------- the disparity noise and its rounding
@pytest.mark.parametrize(("bits", "sigma_px"), [(0, 0.0), (1, 0.1), (3, 0.05), (0, 0.3), (2, None)])
def test_disparity_noise_matches_a_simulated_rounding(bits: int, sigma_px: float | None) -> None:
    """Sheppard's ``sqrt(σ² + q²/12)`` against the scatter of rounded noisy disparities at random phases."""
    rng = np.random.default_rng(10 + bits)
    d_true = rng.uniform(20.0, 80.0, 400_000)                   # true disparities, every phase against the grid
    q = 2.0**-bits
    measured = np.round((d_true + (sigma_px or 0.0) * rng.standard_normal(d_true.size)) / q) * q
    simulated = float(np.std(measured - d_true))
    model = stereo(bits, sigma_px)
    assert model.disparity_noise_px == pytest.approx(simulated, rel=0.006)
    assert model.disparity_noise_px == pytest.approx(math.sqrt((sigma_px or 0.0) ** 2 + q * q / 12.0), rel=1e-12)


@pytest.mark.parametrize("bits", range(9))
def test_disparity_step_is_two_to_minus_bits(bits: int) -> None:
    assert stereo(bits).disparity_step_px == 1.0 / (1 << bits)


# ---------------------------------------------------------------- depth step and depth sigma
@pytest.mark.parametrize(("bits", "z_m"), [(0, 0.7), (3, 0.7), (5, 1.9), (0, 3.0)])
def test_depth_step_is_the_gap_between_adjacent_depth_levels(bits: int, z_m: float) -> None:
    """``Z²/(f·B)·q`` against the levels either side: ``f·B/(d - q/2) - f·B/(d + q/2)`` at ``d = f·B/Z``."""
    q = 2.0**-bits
    d = FB / z_m
    gap = FB / (d - q / 2.0) - FB / (d + q / 2.0)               # = Z²q/(fB) / (1 - q²/(4d²)): exact to (q/2d)²
    step = stereo(bits).depth_step_m(z_m)
    assert float(step) == pytest.approx(gap, rel=(q / d) ** 2)
    assert float(step) == pytest.approx(z_m * z_m / FB * q, rel=1e-12)


def test_depth_step_takes_any_shape_and_the_kind_decides() -> None:
    z = np.array([[0.5, 1.0], [2.0, 4.0]])
    assert np.allclose(stereo(0).depth_step_m(z), z * z / 33.0, rtol=1e-12)
    tof = MeasurementModel(kind="tof", range_step_m=0.005)
    ints = tof.depth_step_m([1, 2, 3])                            # integer depths: the step is still 5 mm
    assert ints.dtype == np.float64 and ints.tolist() == [0.005, 0.005, 0.005]
    assert tof.depth_step_m(z).shape == (2, 2)
    # an unknown camera quantises nothing, whatever it was given
    assert MeasurementModel(kind="unknown", range_step_m=0.005).depth_step_m([1.0, 2.0]).tolist() == [0.0, 0.0]


@pytest.mark.parametrize(("bits", "sigma_px", "z_m"), [(3, 0.1, 0.7), (0, 0.3, 1.2), (0, 0.0, 0.9), (1, 0.2, 2.5)])
def test_stereo_depth_sigma_is_the_scatter_of_simulated_depths(bits: int, sigma_px: float, z_m: float) -> None:
    """``Z²/(f·B)·σ_eff`` against a Monte Carlo of the camera and against the derivative of ``f·B/d``."""
    rng = np.random.default_rng(20 + bits)
    d_mid = round(FB / z_m)                                     # true disparities over exactly 4 px: every phase
    z_true = FB / rng.uniform(d_mid - 2.0, d_mid + 2.0, 300_000)
    z_meas = simulated_depths(z_true, sigma_px, bits, rng)
    model = stereo(bits, sigma_px)
    sigma = model.range_sigma_m(z_true)
    assert sigma is not None and sigma.shape == z_true.shape
    assert float(np.std((z_meas - z_true) / sigma)) == pytest.approx(1.0, abs=0.012)
    # first order: |dZ/dd| (central difference of Z = f·B/d) times the disparity noise
    d, h = FB / z_m, 1e-4
    dz_dd = (FB / (d - h) - FB / (d + h)) / (2.0 * h)
    assert float(model.range_sigma_m(z_m)) == pytest.approx(dz_dd * model.disparity_noise_px, rel=1e-7)  # type: ignore[arg-type]


def test_structured_light_follows_the_same_law_as_stereo() -> None:
    sl = stereo(2, 0.15, kind="structured_light")
    assert sl.triangulating and sl.fb_px_m == pytest.approx(33.0, rel=1e-15)
    assert float(sl.range_sigma_m(1.5)) == pytest.approx(float(stereo(2, 0.15).range_sigma_m(1.5)), rel=1e-15)  # type: ignore[arg-type]


def test_tof_sigma_follows_its_law_in_range_and_incidence() -> None:
    """The slopes of the law (log-log in range, ``cos^-1/2`` in incidence) and its value at hand-computed points."""
    tof = MeasurementModel(kind="tof", sigma_at_1m_m=0.004, distance_exponent=1.3)
    sig = tof.range_sigma_m
    # d log σ / d log r by a central difference: the distance exponent
    r, h = 1.7, 1e-5
    slope = (math.log(float(sig(r * math.exp(h)))) - math.log(float(sig(r * math.exp(-h))))) / (2 * h)  # type: ignore[arg-type]
    assert slope == pytest.approx(1.3, abs=1e-6)
    assert float(sig(1.0)) == pytest.approx(0.004, rel=1e-12)    # the stated figure at 1 m, normal incidence  # type: ignore[arg-type]
    assert float(sig(1.0)) == float(sig(1.0, 1.0))               # the incidence defaults to normal  # type: ignore[arg-type]
    assert float(sig(2.0, 0.25)) == pytest.approx(0.004 * 2.0**1.3 / 0.5, rel=1e-12)  # type: ignore[arg-type]
    # an array of ranges with an array of incidences, element by element
    out = sig(np.array([0.5, 1.0, 2.0]), np.array([1.0, 0.64, 0.01]))
    assert out is not None and out.shape == (3,)
    assert np.allclose(out, [0.004 * 0.5**1.3, 0.004 / 0.8, 0.004 * 2.0**1.3 / 0.1], rtol=1e-12)


def test_tof_incidence_is_clamped_at_one_thousandth() -> None:
    """Grazing (cos 0) or back-facing (cos < 0) pixels get the sigma of cos = 1e-3, finite; above it, the law."""
    tof = MeasurementModel(kind="tof", sigma_at_1m_m=0.002, distance_exponent=1.0)
    at_clamp = 0.002 / math.sqrt(1e-3)
    assert float(tof.range_sigma_m(1.0, 1e-3)) == pytest.approx(at_clamp, rel=1e-12)  # type: ignore[arg-type]
    assert float(tof.range_sigma_m(1.0, 0.0)) == pytest.approx(at_clamp, rel=1e-12)  # type: ignore[arg-type]
    assert float(tof.range_sigma_m(1.0, -0.5)) == pytest.approx(at_clamp, rel=1e-12)  # type: ignore[arg-type]
    assert float(tof.range_sigma_m(1.0, 1.2e-3)) == pytest.approx(0.002 / math.sqrt(1.2e-3), rel=1e-12)  # type: ignore[arg-type]
    assert float(tof.range_sigma_m(1.0, 0.5)) == pytest.approx(0.002 / math.sqrt(0.5), rel=1e-12)  # type: ignore[arg-type]


def test_tof_range_step_adds_the_variance_of_a_simulated_rounding() -> None:
    """Sheppard's ``q²/12`` in range: the scatter of ranges with the law's noise, rounded to 2 cm."""
    tof = MeasurementModel(kind="tof", sigma_at_1m_m=0.003, distance_exponent=1.5, range_step_m=0.02)
    rng = np.random.default_rng(30)
    r_true = rng.uniform(1.19, 1.21, 400_000)
    noise = 0.003 * r_true**1.5 * rng.standard_normal(r_true.size)
    measured = np.round((r_true + noise) / 0.02) * 0.02
    assert float(tof.range_sigma_m(1.2)) == pytest.approx(float(np.std(measured - r_true)), rel=0.006)  # type: ignore[arg-type]
    assert float(tof.range_sigma_m(1.2)) == pytest.approx(math.hypot(0.003 * 1.2**1.5, 0.02 / math.sqrt(12)),  # type: ignore[arg-type]
                                                          rel=1e-12)


def test_no_sigma_without_a_stated_noise() -> None:
    assert MeasurementModel(kind="tof").range_sigma_m(1.0) is None                    # ToF, noise not stated
    assert MeasurementModel(kind="unknown", sigma_at_1m_m=0.004).range_sigma_m(1.0) is None
    assert UNKNOWN_MODEL.range_sigma_m([1.0, 2.0]) is None
    # a stereo camera with no stated disparity noise still has its rounding
    assert float(stereo(0, None).range_sigma_m(1.0)) == pytest.approx(1.0 / 33.0 / math.sqrt(12.0), rel=1e-12)  # type: ignore[arg-type]


# ---------------------------------------------------------------- facts
def test_kinds_and_what_each_can_tell() -> None:
    assert KINDS == ("tof", "stereo", "structured_light", "unknown")
    assert TRIANGULATING_KINDS == ("stereo", "structured_light")
    tof, unknown, st = MeasurementModel(kind="tof"), MeasurementModel(), stereo()
    assert (tof.known, tof.triangulating) == (True, False)
    assert (unknown.known, unknown.triangulating) == (False, False)
    assert (st.known, st.triangulating) == (True, True)
    assert st.fb_px_m == pytest.approx(33.0, rel=1e-15)
    for model in (tof, unknown):
        with pytest.raises(ValueError, match=f"^a {model.kind} camera has no disparity$"):
            _ = model.fb_px_m


def test_defaults_and_the_unknown_model() -> None:
    m = MeasurementModel()
    assert (m.kind, m.sigma_at_1m_m, m.distance_exponent, m.multipath_m, m.range_step_m) == ("unknown", None, 1.5,
                                                                                             0.0, 0.0)
    assert (m.baseline_m, m.focal_px, m.subpixel_bits, m.disparity_sigma_px) == (None, None, 0, None)
    assert (m.source, m.settings) == ("unstated", {})
    assert m == UNKNOWN_MODEL and not UNKNOWN_MODEL.known


def test_settings_do_not_make_two_models_differ_and_with_source_keeps_the_rest() -> None:
    a = MeasurementModel(kind="tof", sigma_at_1m_m=0.004, settings={"filter": "median"})
    assert a == MeasurementModel(kind="tof", sigma_at_1m_m=0.004, settings={"filter": "none"})
    b = a.with_source("config")
    assert b.source == "config" and a.source == "unstated"
    assert b.to_dict() == {**a.to_dict(), "source": "config"}


# ---------------------------------------------------------------- the schema: every limit on both sides
LIMITS = [  # field, last refused below, first accepted, last accepted, first refused above, message below / above
    ("sigma_at_1m_m", 0.0, 1e-9, 1.0, 1.0 + 1e-9, "must be > 0.0", "must be <= 1.0"),
    ("distance_exponent", -1e-9, 0.0, 4.0, 4.0 + 1e-9, "must be >= 0.0", "must be <= 4.0"),
    ("multipath_m", -1e-9, 0.0, 1.0, 1.0 + 1e-9, "must be >= 0.0", "must be <= 1.0"),
    ("range_step_m", -1e-9, 0.0, 0.1, 0.1 + 1e-9, "must be >= 0.0", "must be <= 0.1"),
    ("baseline_m", 0.0, 1e-9, 10.0, 10.0 + 1e-9, "must be > 0.0", "must be <= 10.0"),
    ("focal_px", 0.0, 1e-9, 1e5, 1e5 + 1e-6, "must be > 0.0", "must be <= 100000.0"),
    ("subpixel_bits", -1, 0, 8, 9, "must be >= 0", "must be <= 8"),
    ("disparity_sigma_px", -1e-9, 0.0, 100.0, 100.0 + 1e-9, "must be >= 0.0", "must be <= 100.0"),
]


@pytest.mark.parametrize(("name", "low_bad", "low_ok", "high_ok", "high_bad", "low_why", "high_why"), LIMITS)
def test_every_limit_is_exact_on_both_sides(name: str, low_bad: float, low_ok: float, high_ok: float,
                                            high_bad: float, low_why: str, high_why: str) -> None:
    base: dict[str, Any] = {"kind": "stereo", "baseline_m": 0.075, "focal_px": 440.0}
    for ok in (low_ok, high_ok):
        assert getattr(MeasurementModel(**{**base, name: ok}), name) == ok
    for bad, why in ((low_bad, low_why), (high_bad, high_why)):
        with pytest.raises(ConfigError) as err:
            MeasurementModel(**{**base, name: bad})
        assert str(err.value) == f"key 'camera.model.{name}': {why}, got {bad!r}"
        assert err.value.key == f"camera.model.{name}"


def test_a_bad_value_is_refused_whatever_fields_before_it_are_unset() -> None:
    """The checks skip the unset (None) fields and go on: a bad field after them is still refused."""
    with pytest.raises(ConfigError, match=r"^key 'camera\.model\.disparity_sigma_px': must be >= 0\.0, got -1\.0$"):
        MeasurementModel(disparity_sigma_px=-1.0)
    with pytest.raises(ConfigError, match=r"^key 'camera\.model\.subpixel_bits': must be <= 8, got 9$"):
        MeasurementModel(kind="tof", subpixel_bits=9)


def test_values_are_converted_to_their_types() -> None:
    m = MeasurementModel(kind="stereo", baseline_m=1, focal_px=400, subpixel_bits=2, disparity_sigma_px=0,
                         source="device", settings={"median": 7})
    assert type(m.baseline_m) is float and type(m.focal_px) is float and type(m.disparity_sigma_px) is float
    assert type(m.subpixel_bits) is int and type(m.distance_exponent) is float
    assert (m.kind, m.source, m.settings) == ("stereo", "device", {"median": 7})
    with pytest.raises(ConfigError, match=r"^key 'camera\.model\.subpixel_bits': expected an integer, got float 2\.5$"):
        MeasurementModel(subpixel_bits=2.5)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=r"^key 'camera\.model\.focal_px': expected a number, got bool True$"):
        MeasurementModel(focal_px=True)


def test_the_kind_and_the_stereo_geometry_are_required() -> None:
    with pytest.raises(ConfigError) as err:
        MeasurementModel(kind="lidar")  # type: ignore[arg-type]
    assert str(err.value) == ("key 'camera.model.kind': must be one of tof, stereo, structured_light, unknown, "
                              "got 'lidar'")
    for kind in TRIANGULATING_KINDS:
        with pytest.raises(ConfigError) as err:
            MeasurementModel(kind=kind, focal_px=440.0)  # type: ignore[arg-type]
        assert str(err.value) == f"key 'camera.model.baseline_m': a {kind} model needs baseline_m (> 0)"
        with pytest.raises(ConfigError) as err:
            MeasurementModel(kind=kind, baseline_m=0.075)  # type: ignore[arg-type]
        assert str(err.value) == f"key 'camera.model.focal_px': a {kind} model needs focal_px (> 0)"
    # a ToF camera needs neither
    assert MeasurementModel(kind="tof").baseline_m is None


# ---------------------------------------------------------------- (de)serialisation
def test_to_dict_holds_every_stated_key_and_nothing_unset() -> None:
    oak = MeasurementModel(kind="stereo", baseline_m=0.075, focal_px=440.0, subpixel_bits=3, disparity_sigma_px=0.1,
                           source="device", settings={"median": "KERNEL_7x7"})
    assert oak.to_dict() == {"kind": "stereo", "distance_exponent": 1.5, "multipath_m": 0.0, "range_step_m": 0.0,
                             "baseline_m": 0.075, "focal_px": 440.0, "subpixel_bits": 3, "disparity_sigma_px": 0.1,
                             "source": "device", "settings": {"median": "KERNEL_7x7"}}
    assert next(iter(oak.to_dict())) == "kind"
    tof = MeasurementModel(kind="tof", sigma_at_1m_m=0.004, multipath_m=0.002, range_step_m=0.001)
    assert tof.to_dict() == {"kind": "tof", "sigma_at_1m_m": 0.004, "distance_exponent": 1.5, "multipath_m": 0.002,
                             "range_step_m": 0.001, "subpixel_bits": 0, "source": "unstated"}
    assert UNKNOWN_MODEL.to_dict() == {"kind": "unknown", "distance_exponent": 1.5, "multipath_m": 0.0,
                                       "range_step_m": 0.0, "subpixel_bits": 0, "source": "unstated"}
    for model in (oak, tof, UNKNOWN_MODEL):
        back = MeasurementModel.from_dict(model.to_dict())
        assert back == model and back.settings == model.settings


def test_from_dict_of_nothing_is_the_unknown_model() -> None:
    assert MeasurementModel.from_dict(None) is UNKNOWN_MODEL
    assert MeasurementModel.from_dict({}, source="cell.toml") == UNKNOWN_MODEL
    assert MeasurementModel.from_dict({"kind": "tof"}, source="cell.toml").source == "unstated"


@pytest.mark.parametrize(("where", "source"), [("camera.model", None), ("camera.model", "cell.toml"),
                                               ("frame.measurement", "s.mcap"), ("cameras.left.model", None)])
def test_from_dict_names_the_key_where_it_is(where: str, source: str | None) -> None:
    """A bad value, an unknown key, and a stereo model without its baseline: one line naming source and key."""
    prefix = f"{source}: " if source else ""
    cases = [
        ({"baseline_m": -1}, "baseline_m", "must be > 0.0, got -1.0"),
        ({"kind": "stereo", "focal_px": 440.0}, "baseline_m", "a stereo model needs baseline_m (> 0)"),
        ({"kind": "structured_light", "baseline_m": 0.1}, "focal_px",
         "a structured_light model needs focal_px (> 0)"),
        ({"kind": "lidar"}, "kind",
         "expected one of 'tof', 'stereo', 'structured_light', 'unknown', got str 'lidar'"),
        ({"focal": 440.0}, "focal", "unknown key; did you mean 'focal_px'? (expected one of: baseline_m, "
         "disparity_sigma_px, distance_exponent, field_allowance, focal_px, kind, multipath_m, offset_allowance, "
         "range_step_m, scale_allowance, settings, sigma_at_1m_m, source, subpixel_bits, wiggle_allowance_m, "
         "wiggle_period_m)"),
    ]
    for data, key, why in cases:
        with pytest.raises(ConfigError) as err:
            MeasurementModel.from_dict(data, where=where, source=source)
        message = str(err.value)
        assert message == f"{prefix}key '{where}.{key}': {why}"
        assert err.value.key == f"{where}.{key}" and err.value.source == source and "\n" not in message


def test_from_dict_names_the_camera_model_table_by_default() -> None:
    with pytest.raises(ConfigError) as err:
        MeasurementModel.from_dict({"kind": "stereo", "focal_px": 440.0})
    assert str(err.value) == "key 'camera.model.baseline_m': a stereo model needs baseline_m (> 0)"
    with pytest.raises(ConfigError) as err:
        MeasurementModel.from_dict({"focal_px": 0})
    assert str(err.value) == "key 'camera.model.focal_px': must be > 0.0, got 0.0"


def test_from_dict_renames_only_the_table_not_a_key_that_repeats_its_name() -> None:
    """An unknown key spelt ``camera.model`` inside a recording's model: the table is renamed, the key is not."""
    with pytest.raises(ConfigError) as err:
        MeasurementModel.from_dict({"camera.model": 1}, where="frame.measurement")
    assert err.value.key == "frame.measurement.camera.model"
    assert str(err.value).startswith("key 'frame.measurement.camera.model': unknown key;")


def test_sigmas_of_float32_depths_are_float64() -> None:
    """Frames hold float32 depths; the sigmas (and steps) come back in float64 as the API states."""
    z = np.array([0.7, 1.3], dtype=np.float32)
    for m in (stereo(3, 0.1), MeasurementModel(kind="tof", sigma_at_1m_m=0.004, range_step_m=0.001)):
        sigma = m.range_sigma_m(z)
        assert sigma is not None and sigma.dtype == np.float64
        assert m.depth_step_m(z).dtype == np.float64
    exact = stereo(3, 0.1).range_sigma_m(z.astype(np.float64))
    assert np.array_equal(stereo(3, 0.1).range_sigma_m(z), exact)  # type: ignore[arg-type]


# ---------------------------------------------------------------- what a user reads
def test_describe_in_millimetres_and_pixels() -> None:
    oak = MeasurementModel(kind="stereo", baseline_m=0.075, focal_px=441.25, subpixel_bits=3, disparity_sigma_px=0.1,
                           source="device")
    assert oak.describe() == ("stereo: baseline 75 mm, focal 441.25 px, 3 subpixel bits, disparity sigma 0.1 px "
                              "(device)")
    sl = MeasurementModel(kind="structured_light", baseline_m=0.12345, focal_px=580.0)
    assert sl.describe() == ("structured_light: baseline 123.5 mm, focal 580 px, 0 subpixel bits, disparity sigma "
                             "unstated (unstated)")
    tof = MeasurementModel(kind="tof", sigma_at_1m_m=0.0045, distance_exponent=1.25, multipath_m=0.0995,
                           source="config")
    assert tof.describe() == "tof: range sigma 4.5 mm at 1 m, exponent 1.25, multipath allowance 99.5 mm (config)"
    assert MeasurementModel(kind="tof").describe() == ("tof: range sigma unstated, exponent 1.5, multipath allowance "
                                                       "0 mm (unstated)")
    assert UNKNOWN_MODEL.describe() == "unknown (the camera states no model; [full_frame] defaults apply)"
