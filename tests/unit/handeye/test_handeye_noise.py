"""Honest hand-eye intervals: the chi2 test of the stated noise, Birge scaling, given values with a sigma (ADR 0030)."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest
from repo_paths import REPO_ROOT
from scipy.stats import t as student_t

from cellcal.core.calibration.config import parse_config
from cellcal.core.geometry.planes import Plane
from cellcal.core.handeye import estimate_mount, format_report, handeye_document, plane_sections
from cellcal.core.handeye.noise import check_noise, scaled_covariance
from cellcal.core.handeye.synthetic import Scenario, camera_views, coverage, observations, sim_scenario
from cellcal.devices.errors import CalibrationQualityError, ConfigError
from cellcal.devices.pose import Pose
from tests.support.numerics import assert_covariance_close

ARM_T, ARM_R = 1e-4, math.radians(0.01)  # the unmodelled read-back noise: 0.1 mm, 0.01 deg
CONFIG = REPO_ROOT / "configs" / "sim_handeye.toml"


def stated_noise_times(obs: list, factor: float) -> list:
    """The same observations with every stated plane covariance multiplied by ``factor``."""
    from dataclasses import replace

    return [replace(o, covariance=o.covariance * factor) for o in obs]


def test_the_birge_scale_and_t_quantile_by_hand() -> None:
    # chi2 = 60 over 15 dof: p = 2e-7 < 0.01, so every sigma is scaled by sqrt(60 / 15) = 2
    check = check_noise(60.0, 15, confidence=0.95)
    assert check.verdict == "scaled" and check.interval_scale == pytest.approx(2.0, rel=1e-12)
    assert check.interval_z == pytest.approx(2.1314, abs=1e-4)  # Student-t, 15 dof, two-sided 95 % (table value)
    info = np.array([[4.0, 1.0], [1.0, 2.0]])  # inverse [[2, -1], [-1, 4]] / 7
    np.testing.assert_allclose(scaled_covariance(info, np.zeros((2, 2)), 2.0),
                               4.0 * np.array([[2.0, -1.0], [-1.0, 4.0]]) / 7.0, rtol=1e-12)
    # chi2 = 15 over 15 dof is what the noise predicts; 3 over 15 is too good (p = 2e-4) and is not narrowed
    assert check_noise(15.0, 15, confidence=0.95).verdict == "consistent"
    too_good = check_noise(3.0, 15, confidence=0.95)
    assert too_good.verdict == "too_good" and too_good.interval_scale == 1.0
    assert too_good.interval_z == pytest.approx(1.95996, abs=1e-5) and "too pessimistic" in (too_good.note() or "")
    # 10x the stated noise (chi2/dof 100.0) is the limit; 100.1 is refused, naming the gate
    assert check_noise(1500.0, 15, confidence=0.95).interval_scale == pytest.approx(10.0)
    with pytest.raises(CalibrationQualityError, match=r"'noise_model' failed: 10\.0\d* vs threshold 10"):
        check_noise(1501.5, 15, confidence=0.95)


def test_scaled_intervals_do_not_depend_on_an_understated_noise() -> None:
    scenario = sim_scenario()
    obs = observations(scenario, np.random.default_rng(4))
    right = estimate_mount(obs, scenario.nominal_mount, scenario.nominal_plane)
    # the plane noise and the arm noise stated 4x too small: the same solution, chi2 16x larger
    low = estimate_mount(stated_noise_times(obs, 1 / 16), scenario.nominal_mount, scenario.nominal_plane,
                         arm_translation_sigma_m=2.5e-5 / 4)
    assert right.noise.verdict == "consistent" and low.noise.verdict == "scaled"
    assert low.chi2 == pytest.approx(16 * right.chi2, rel=1e-6)
    np.testing.assert_allclose(low.parameters, right.parameters, atol=1e-10)
    assert low.interval_scale == pytest.approx(math.sqrt(low.chi2 / low.dof))
    assert_covariance_close(low.covariance, low.absolute_covariance * low.chi2 / low.dof, rtol=1e-9)
    # scaled intervals equal the right model's rescaled by its own chi2/dof
    assert_covariance_close(low.covariance, right.covariance * right.chi2 / right.dof, rtol=1e-6)
    assert low.z == pytest.approx(float(student_t.ppf(0.975, low.dof)))
    assert any("scaled by" in note for note in low.notes)


@pytest.mark.statistical
def test_unmodelled_arm_noise_intervals_cover_the_truth() -> None:
    # the case: the arm reads back with 0.1 mm / 0.01 deg, the estimator is told 0.025 mm / 0
    noisy = sim_scenario().with_arm_noise(ARM_T, ARM_R)
    result = coverage(noisy, 60, seed=27)
    assert result.refused == 0 and result.scaled == 1.0 and 2.5 < result.median_scale < 5.0
    # 360 intervals: 95 % would give 342; a binomial band of 3 sigma (6.9 %) plus the t quantile's slack
    assert 0.88 <= float(result.inside.mean()) <= 1.0
    assert np.all(result.inside >= 0.83)  # each value over 60 runs: 95 % - 4 sigma
    assert float(result.inside_absolute.mean()) <= 0.65  # what absolute weights gave: about half


@pytest.mark.statistical
def test_a_right_noise_model_keeps_95_percent() -> None:
    result = coverage(sim_scenario(), 60, seed=28)
    assert result.refused == 0 and result.scaled <= 0.05  # 1 % of runs expected
    assert 0.90 <= float(result.inside.mean()) <= 0.985  # 360 intervals: 95 % +- 3 sigma
    np.testing.assert_allclose(result.inside, result.inside_absolute, atol=1 / 60 + 1e-12)  # no needless widening


def cone_scenario(offset_error_m: float) -> Scenario:
    """One inclination, four rolls, two azimuths (the normals seen from the flange on one cone), the table wrong."""
    base = sim_scenario()
    flanges = camera_views(base.true_mount, [0.3, 0.0, 0.0], 0.45, (70.0,), (0.0, 90.0, 180.0, 270.0), (0.0, 120.0))
    wrong = Plane(base.true_plane.normal, base.true_plane.offset_m + offset_error_m)
    from dataclasses import replace

    return replace(base, flanges=flanges, nominal_plane=wrong)


def test_a_given_sigma_propagates_exactly_where_the_data_cannot_see_the_given_value() -> None:
    delta, sigma = 0.004, 0.002
    scenario = cone_scenario(delta)
    views = observations(scenario, None)  # noise-free: the error is the given value's alone
    opts = {"given": ("plane_offset",), "max_interval_scale": math.inf}
    held = estimate_mount(views, scenario.nominal_mount, scenario.nominal_plane, **opts)
    prior = estimate_mount(views, scenario.nominal_mount, scenario.nominal_plane,
                           given_sigma={"plane_offset": sigma}, **opts)
    # linear theory: x moves by G delta and its covariance gains G sigma² Gᵀ, G = (JᵀJ)⁻¹ Jᵀ J_g
    shift = prior.mount.translation - scenario.true_mount.translation
    gain = np.diag(prior.covariance - held.covariance)[3:6]  # (G sigma)² per translation axis
    np.testing.assert_allclose(np.abs(shift), np.sqrt(gain) * delta / sigma, rtol=1e-4, atol=1e-9)
    assert abs(shift[2]) > 0.5 * delta  # the mount height follows the table height
    assert prior.plane.offset_m == pytest.approx(scenario.nominal_plane.offset_m, abs=1e-7)  # the prior's value
    assert prior.covariance[8, 8] == pytest.approx(sigma**2, rel=1e-4)  # the data add nothing to it
    assert any("held exact" in n for n in held.notes) and any("plane_offset ± 2 mm" in n for n in prior.notes)


def test_a_given_sigma_holds_the_truth_95_percent_of_the_time() -> None:
    # Monte-Carlo: the configured table height is off by N(0, 2 mm) in every run, the plan cannot see it
    sigma = 0.002
    rng = np.random.default_rng(5)
    inside = []
    for _ in range(40):
        scenario = cone_scenario(float(rng.normal(0.0, sigma)))
        est = estimate_mount(observations(scenario, rng), scenario.nominal_mount, scenario.nominal_plane,
                             given=("plane_offset",), given_sigma={"plane_offset": sigma})
        error = est.mount.translation - scenario.true_mount.translation
        inside.append(np.abs(error) <= est.z * est.translation_sigma_m)
    assert 0.85 <= float(np.mean(inside)) <= 1.0  # 120 intervals: 95 % - 3.5 sigma


def test_a_15_mm_wrong_given_offset_is_covered_with_a_sigma_and_refused_without() -> None:
    scenario = sim_scenario()
    wrong = Plane(scenario.true_plane.normal, scenario.true_plane.offset_m + 0.015)
    views = observations(scenario, np.random.default_rng(8))
    with pytest.raises(CalibrationQualityError, match="'noise_model'"):  # absorbed into the mount: chi2/dof ~190
        estimate_mount(views, scenario.nominal_mount, wrong, given=("plane_offset",))
    est = estimate_mount(views, scenario.nominal_mount, wrong, given=("plane_offset",),
                         given_sigma={"plane_offset": 0.01})
    error = est.mount.translation - scenario.true_mount.translation
    assert np.all(np.abs(error) <= est.z * est.translation_sigma_m)  # the data pull the table back
    assert abs(est.plane.offset_m - scenario.true_plane.offset_m) < 1e-3
    # where the plan cannot see the height, the mount follows the wrong table, and the interval says so
    cone = cone_scenario(0.015)
    est = estimate_mount(observations(cone, np.random.default_rng(8)), cone.nominal_mount, cone.nominal_plane,
                         given=("plane_offset",), given_sigma={"plane_offset": 0.01})
    error = est.mount.translation - cone.true_mount.translation
    assert abs(error[2]) > 0.01 and np.all(np.abs(error) <= est.z * est.translation_sigma_m)


def test_a_camera_looking_down_from_a_mount_rolled_180_deg() -> None:
    nominal = Pose.from_xyz_rpy([0.0, 0.04, -0.06], np.radians([180.0, 0.0, 90.0]))
    truth = Pose.from_xyz_rpy([0.002, 0.037, -0.063], np.radians([179.4, 0.4, 90.5]))
    scenario = sim_scenario(true_mount=truth, nominal_mount=nominal)
    assert all(f.rotation.apply([0.0, 0.0, 1.0])[2] > 0.3 for f in scenario.flanges)  # the tool axis points up
    exact = estimate_mount(observations(scenario, None), nominal, scenario.nominal_plane)
    assert np.linalg.norm(exact.mount.translation - truth.translation) < 1e-9
    rpy, rpy_sigma = exact.rpy_and_sigma_deg()
    wrapped = np.remainder(rpy - np.degrees(truth.as_xyz_rpy()[3:]) + 180.0, 360.0) - 180.0
    assert np.all(np.abs(wrapped) < 1e-7) and np.all(rpy_sigma < 0.05)
    result = coverage(scenario.with_arm_noise(ARM_T, ARM_R), 30, seed=180)
    assert result.refused == 0 and float(result.inside.mean()) >= 0.85  # 180 intervals


def test_the_document_and_report_say_what_the_intervals_rest_on() -> None:
    scenario = sim_scenario().with_arm_noise(ARM_T, ARM_R)
    est = estimate_mount(observations(scenario, np.random.default_rng(1)), scenario.nominal_mount,
                         scenario.nominal_plane, given=("plane_tilt_a",))
    doc = handeye_document(est.mount, est.covariance[:6, :6], est.confidence, scenario.nominal_mount,
                           header={"method": "plane"}, sections=plane_sections(est, list(scenario.flanges)),
                           z=est.z, interval_scale=est.interval_scale)
    assert doc["mount"]["interval_scale"] == est.interval_scale > 2.0
    assert doc["mount"]["interval_z"] == pytest.approx(float(student_t.ppf(0.975, est.dof)))
    assert doc["fit"]["noise_model"]["verdict"] == "scaled" and doc["fit"]["covariance_absolute"]
    sigma_t = np.array(doc["mount"]["translation_sigma_m"])
    np.testing.assert_allclose(sigma_t, est.interval_scale * np.sqrt(np.diag(est.absolute_covariance)[3:6]))
    report = format_report(doc)
    assert f"95 % intervals, scaled by {est.interval_scale:.2f}" in report
    assert "note: chi2/dof" in report and "note: given plane_tilt_a held exact" in report


def config_with(handeye: dict) -> dict:
    document = tomllib.loads(CONFIG.read_text())
    document["handeye"].update(handeye)
    return document


@pytest.mark.parametrize(("table", "words"), [
    ({"given_sigma": {"plane_offset": 0.002}}, "key 'handeye.given_sigma.plane_offset': not in handeye.given"),
    ({"given": ["plane_offset"], "given_sigma": {"plane_offset": 0}},
     "given_sigma.plane_offset': expected a number > 0"),
    ({"given": ["plane_offset"], "given_sigma": {"plane_offset": "2 mm"}}, "given_sigma.plane_offset': expected"),
    ({"given": ["plane_offset"], "given_sigma": {"plane_offset": True}}, "given_sigma.plane_offset': expected"),
    ({"given": ["plane_offset"], "given_sigma": {"plane_offset": math.nan}}, "given_sigma.plane_offset': expected"),
    ({"given_sigma": 0.002}, "key 'handeye.given_sigma': expected"),
    ({"max_interval_scale": 0.5}, "key 'handeye.max_interval_scale'"),
    ({"noise_test_level": 0.0}, "key 'handeye.noise_test_level'"),
])
def test_bad_noise_settings_are_one_line_errors_naming_the_key(table: dict, words: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_config(config_with(table), "cell.toml")
    message = str(err.value)
    assert words in message and message.startswith("cell.toml: ") and "\n" not in message


def test_the_noise_settings_are_read() -> None:
    config = parse_config(config_with({"given": ["plane_offset"], "given_sigma": {"plane_offset": 0.002},
                                       "noise_test_level": 0.05, "max_interval_scale": 4.0}), "cell.toml")
    assert config.handeye.given_sigma == {"plane_offset": 0.002}
    assert config.handeye.noise_test_level == 0.05 and config.handeye.max_interval_scale == 4.0
