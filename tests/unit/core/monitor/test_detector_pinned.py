"""The drift detector on hand-made samples: thresholds and timers at their exact boundaries, every field read.

The samples are chosen so that what the detector must find is known without it:

* heights and thresholds are dyadic (0.5 m, 0.0625 m, 0.03125 m) and the tilt baseline is 0,
  so a deviation equals its threshold (or half of it, the clear level) exactly in floating
  point, and the next float up is over it;
* frame times step by 0.25 s, so ``clear_s = 1.0`` is exactly four frames;
* the warm-up frames have chosen sample variances (per-axis tilt variances 1e-8 and 49e-8
  rad², whose mean 25e-8 is the square of 5e-4 rad; heights 1 mm apart, standard deviation
  1 mm), so the noise figures and the thresholds they set are known in advance;
* a camera that is tilted (1 deg about x, -0.5 deg about y) and steady has deviations of
  zero from its own baseline: only differences of tilts may enter the deviation.
"""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
from test_monitor import run_detector

from cellcal.core.calibration.sections import MonitorSection
from cellcal.core.monitor import Baseline, DriftDetector, DriftEvent, PlaneSample
from cellcal.core.monitor.detector import DetectorStatus
from cellcal.devices.errors import CalibrationError

DEG = math.pi / 180.0
T0 = 1000.0
DT = 0.25  # frame period, s: a power of two, so frame times and clear_s = 1.0 add exactly
H0 = 0.5  # baseline height, m
H_THR = 0.0625  # height threshold, m (2**-4)
#: Thresholds taken from the configuration (a given baseline with zero noise), a one-frame window: the
#: window median is the frame's own deviation.
EXACT = MonitorSection(period_s=0.0, baseline_frames=2, tilt_threshold_deg=0.2, height_threshold_m=H_THR,
                       window_frames=1, hysteresis_ratio=0.5, clear_s=1.0)
T_THR = EXACT.tilt_threshold_rad  # 0.2 deg in rad
QUIET = Baseline(0.0, 0.0, H0, tilt_noise_rad=0.0, height_noise_m=0.0)


def at(i: int, tilt_x: float = 0.0, tilt_y: float = 0.0, height: float = H0) -> PlaneSample:
    """Frame ``i`` (time T0 + i * DT) seeing the plane at these tilts (rad) and height (m)."""
    return PlaneSample(T0 + i * DT, tilt_x, tilt_y, height)


def above(x: float) -> float:
    """The next float above ``x``."""
    return math.nextafter(x, math.inf)


#: Warm-up of three frames: tilt x 0, 1, 2 (x 1e-4 rad), tilt y 0, 7, 14 (x 1e-4 rad), heights 440, 441, 442 mm.
WARM_UP = [PlaneSample(T0 + i * DT, i * 1e-4, i * 7e-4, 0.440 + i * 0.001) for i in range(3)]
#: Their sample variances: tilt x 1e-8, tilt y 49e-8 rad² -> per-axis RMS sqrt(25e-8) = 5e-4 rad; height 1 mm.
WARM_UP_TILT_NOISE = 5e-4
WARM_UP_HEIGHT_NOISE = 0.001


# ---------------------------------------------------------------------- deviations
def test_a_steady_camera_tilted_1_deg_has_zero_deviation_and_never_alarms() -> None:
    tx, ty = 1.0 * DEG, -0.5 * DEG
    det = DriftDetector(MonitorSection(period_s=0.0, baseline_frames=4, window_frames=3),
                        Baseline(tx, ty, 0.44, tilt_noise_rad=1e-5, height_noise_m=1e-6))
    statuses = [det.update(PlaneSample(T0 + i * DT, tx, ty, 0.44)) for i in range(30)]
    assert all(s.tilt_deviation_rad == 0.0 and s.height_deviation_m == 0.0 for s in statuses)
    assert statuses[-1] == DetectorStatus(statuses[-1].sample, "ok", 0.0, 0.0, 0.0, 0.0, None)
    assert det.events == [] and det.phase == "ok"


def test_a_warm_up_on_a_tilted_camera_gives_its_own_tilt_as_baseline() -> None:
    """The same steady 1 deg camera, baseline from the warm-up: its frames deviate by the warm-up's spread only."""
    tx, ty = 1.0 * DEG, -0.5 * DEG
    warm = [PlaneSample(s.timestamp, tx + s.tilt_x_rad, ty + s.tilt_y_rad, s.height_m) for s in WARM_UP]
    det = DriftDetector(MonitorSection(period_s=0.0, baseline_frames=3, window_frames=3))
    assert run_detector(det, warm + [PlaneSample(T0 + i * DT, tx, ty, 0.441) for i in range(3, 40)]) == []
    assert det.baseline is not None
    assert det.baseline.tilt_x_rad == pytest.approx(tx + 1e-4, rel=1e-12)
    assert det.baseline.tilt_y_rad == pytest.approx(ty + 7e-4, rel=1e-12)
    status = det.update(PlaneSample(T0 + 40 * DT, tx, ty, 0.441))
    assert status.tilt_deviation_rad == pytest.approx(math.hypot(1e-4, 7e-4), rel=1e-9)
    assert status.height_deviation_m == pytest.approx(0.0, abs=1e-15)


def test_deviations_are_the_distances_from_a_tilted_baseline() -> None:
    """3e-4 and 4e-4 rad off a baseline tilted 1 deg / -0.5 deg: 5e-4 rad; 2 mm below it: 2 mm."""
    base = Baseline(1.0 * DEG, -0.5 * DEG, 0.44, tilt_noise_rad=0.0, height_noise_m=0.0)
    det = DriftDetector(MonitorSection(period_s=0.0, window_frames=2, height_threshold_m=0.01), base)
    first = det.update(PlaneSample(T0, 1.0 * DEG + 3e-4, -0.5 * DEG - 4e-4, 0.438))
    assert first.tilt_deviation_rad == pytest.approx(5e-4, rel=1e-9)
    assert first.height_deviation_m == pytest.approx(0.002, rel=1e-9)
    assert (first.tilt_median_rad, first.height_median_m, first.event) == (None, None, None)  # window not full
    second = det.update(PlaneSample(T0 + DT, 1.0 * DEG, -0.5 * DEG, 0.443))
    assert second.tilt_deviation_rad == 0.0
    assert second.height_deviation_m == pytest.approx(0.003, rel=1e-9)
    assert second.tilt_median_rad == pytest.approx(2.5e-4, rel=1e-9)  # median of two: their mean
    assert second.height_median_m == pytest.approx(0.0025, rel=1e-9)
    assert second.phase == "ok" and second.event is None


# ---------------------------------------------------------------------- warm-up and noise
def test_the_warm_up_noise_is_the_sample_variance_averaged_over_both_tilt_axes() -> None:
    det = DriftDetector(MonitorSection(period_s=0.0, baseline_frames=3, window_frames=2, tilt_threshold_deg=0.001,
                                       height_threshold_m=1e-5, noise_sigmas=6.0))
    assert (det.baseline, det.tilt_threshold_rad, det.height_threshold_m, det.phase) == (None, None, None, "baseline")
    statuses = [det.update(s) for s in WARM_UP]
    assert statuses == [DetectorStatus(s, "baseline") for s in WARM_UP]
    b = det.baseline
    assert b is not None
    assert (b.tilt_x_rad, b.tilt_y_rad, b.height_m) == pytest.approx((1e-4, 7e-4, 0.441), rel=1e-12)
    assert b.tilt_noise_rad == pytest.approx(WARM_UP_TILT_NOISE, rel=1e-9)
    assert b.height_noise_m == pytest.approx(WARM_UP_HEIGHT_NOISE, rel=1e-9)
    # the configured thresholds are tiny: six measured sigmas are the effective ones
    assert det.tilt_threshold_rad == pytest.approx(6 * WARM_UP_TILT_NOISE, rel=1e-9)
    assert det.height_threshold_m == pytest.approx(6 * WARM_UP_HEIGHT_NOISE, rel=1e-9)
    assert det.phase == "ok"


@pytest.mark.parametrize(("cfg", "tilt_thr", "height_thr"), [
    # 0.2 deg (3.49e-3 rad) > 6 x 5e-4 rad; 2 mm < 6 x 1 mm: the tilt threshold is the configured one
    ({"noise_sigmas": 6.0}, 0.2 * DEG, 0.006),
    # 8 x 5e-4 = 4e-3 rad > 0.2 deg; 10 mm > 8 x 1 mm: the height threshold is the configured one
    ({"noise_sigmas": 8.0, "height_threshold_m": 0.01}, 0.004, 0.01),
    # no noise floor: the configured values
    ({"noise_sigmas": 0.0}, 0.2 * DEG, 0.002),
])
def test_each_threshold_is_the_larger_of_the_configured_one_and_the_noise_floor(
        cfg: dict[str, float], tilt_thr: float, height_thr: float) -> None:
    det = DriftDetector(replace(MonitorSection(period_s=0.0, baseline_frames=3), **cfg))
    for s in WARM_UP:
        det.update(s)
    assert det.tilt_threshold_rad == pytest.approx(tilt_thr, rel=1e-9)
    assert det.height_threshold_m == pytest.approx(height_thr, rel=1e-9)


def test_a_given_plane_without_noise_is_kept_and_its_noise_measured() -> None:
    given = Baseline(0.01, -0.02, 0.45)
    det = DriftDetector(MonitorSection(period_s=0.0, baseline_frames=3, window_frames=1), given, label="cam")
    assert det.baseline is None and det.phase == "baseline"
    for s in WARM_UP:
        det.update(s)
    b = det.baseline
    assert b is not None and (b.tilt_x_rad, b.tilt_y_rad, b.height_m) == (0.01, -0.02, 0.45)
    assert b.tilt_noise_rad == pytest.approx(WARM_UP_TILT_NOISE, rel=1e-9)
    assert b.height_noise_m == pytest.approx(WARM_UP_HEIGHT_NOISE, rel=1e-9)


def test_a_given_baseline_with_noise_sets_the_thresholds_at_once() -> None:
    det = DriftDetector(replace(EXACT, noise_sigmas=4.0), Baseline(0.0, 0.0, H0, tilt_noise_rad=0.0005,
                                                                    height_noise_m=0.02))
    assert det.phase == "ok" and not det.drifting
    assert det.tilt_threshold_rad == T_THR  # 0.2 deg (3.5 mrad) > 4 x 0.5 mrad
    assert det.height_threshold_m == 0.08  # 4 x 20 mm > 62.5 mm


@pytest.mark.parametrize(("baseline_frames", "window", "first_median"), [(6, 5, 6), (3, 5, 4), (9, 5, 9), (2, 1, 2),
                                                                        (2, 3, 2)])
def test_the_window_holds_the_last_warm_up_frames_so_a_median_comes_as_soon_as_it_is_full(
        baseline_frames: int, window: int, first_median: int) -> None:
    """Warm-up heights 440, 441, ... mm: the window starts with the last ``window`` of them (or all, if fewer).

    With a warm-up of 6 frames, shorter than twice the window of 5, the first frame after the warm-up
    already has a median (its window: the last 4 warm-up frames and itself); after 3 frames, two more are needed.
    """
    heights = [0.440 + 0.001 * i for i in range(baseline_frames)]
    mean = sum(heights) / baseline_frames
    det = DriftDetector(MonitorSection(period_s=0.0, baseline_frames=baseline_frames, window_frames=window,
                                       height_threshold_m=1.0, noise_sigmas=0.0))
    for i, h in enumerate(heights):
        assert det.update(PlaneSample(T0 + i * DT, 0.0, 0.0, h)).phase == "baseline"
    assert det.baseline is not None and det.baseline.height_m == pytest.approx(mean, rel=1e-12)
    deviations = [abs(h - mean) for h in heights[-window:]]
    for i in range(baseline_frames, first_median + 1):
        status = det.update(PlaneSample(T0 + i * DT, 0.0, 0.0, mean))  # deviation 0
        deviations.append(0.0)
        if i < first_median:
            assert (status.tilt_median_rad, status.height_median_m) == (None, None)
    last = sorted(deviations[-window:])  # an odd window: the median is its middle value
    assert status.height_median_m == pytest.approx(last[window // 2], abs=1e-15)
    assert status.tilt_median_rad == 0.0


def test_the_first_frame_after_a_6_frame_warm_up_has_the_median_of_a_window_of_5() -> None:
    """Heights 440..445 mm (mean 442.5): the window keeps deviations 0.5, 0.5, 1.5, 2.5 mm, then 3.5 mm is added."""
    det = DriftDetector(MonitorSection(period_s=0.0, baseline_frames=6, window_frames=5, height_threshold_m=1.0,
                                       noise_sigmas=0.0))
    for i in range(6):
        det.update(PlaneSample(T0 + i * DT, 0.0, 0.0, 0.440 + 0.001 * i))
    status = det.update(PlaneSample(T0 + 6 * DT, 0.0, 0.0, 0.446))
    assert status.height_deviation_m == pytest.approx(0.0035, rel=1e-9)
    assert status.height_median_m == pytest.approx(0.0015, rel=1e-9)


# ---------------------------------------------------------------------- start at the threshold
def test_drift_starts_only_above_the_threshold_not_at_it() -> None:
    det = DriftDetector(EXACT, QUIET, label="cam-a")
    at_both = det.update(at(0, T_THR, 0.0, H0 + H_THR))
    assert (at_both.tilt_median_rad, at_both.height_median_m) == (T_THR, H_THR)
    assert at_both.event is None and at_both.phase == "ok"
    tilt = det.update(at(1, above(T_THR)))
    assert tilt.event == DriftEvent("drift_started", T0 + DT, above(T_THR), 0.0, T_THR, H_THR, ("tilt",), "cam-a")
    assert tilt.phase == "drift" and det.drifting is True and det.events == [tilt.event]


def test_height_alone_and_both_together_name_their_causes_in_order() -> None:
    det = DriftDetector(EXACT, QUIET)
    height = det.update(at(0, 0.0, T_THR, above(H0 + H_THR)))
    assert height.event is not None and height.event.causes == ("height",)
    assert height.event.height_deviation_m > H_THR and height.event.label == ""
    both = DriftDetector(EXACT, QUIET).update(at(0, 0.0, -above(T_THR), math.nextafter(H0 - H_THR, 0.0)))
    assert both.event is not None and both.event.causes == ("tilt", "height")
    assert both.event.to_dict() == {
        "kind": "drift_started", "timestamp": T0, "label": "", "causes": ["tilt", "height"],
        "tilt_deviation_rad": above(T_THR), "height_deviation_m": both.height_deviation_m,
        "tilt_threshold_rad": T_THR, "height_threshold_m": H_THR}
    assert both.height_deviation_m == pytest.approx(H_THR, rel=1e-15) and both.height_deviation_m > H_THR


# ---------------------------------------------------------------------- clearing at the hysteresis level
def _drifting(label: str = "") -> DriftDetector:
    """A detector (EXACT, quiet baseline) that flagged tilt drift on frame 0."""
    det = DriftDetector(EXACT, QUIET, label=label)
    assert det.update(at(0, 2 * T_THR)).event is not None
    return det


def test_drift_clears_after_exactly_clear_s_at_exactly_half_the_thresholds() -> None:
    """From frame 1 both deviations sit exactly on the clear level (half the thresholds): cleared at frame 5 (1 s)."""
    det = _drifting("cam-b")
    half_t, half_h = 0.5 * T_THR, 0.5 * H_THR  # exact: halving a float
    statuses = [det.update(at(i, half_t, 0.0, H0 + half_h)) for i in range(1, 7)]
    assert [s.event is not None for s in statuses] == [False, False, False, False, True, False]
    cleared = statuses[4].event
    assert cleared == DriftEvent("drift_cleared", T0 + 5 * DT, half_t, half_h, T_THR, H_THR, (), "cam-b")
    assert cleared.to_dict() == {
        "kind": "drift_cleared", "timestamp": 1001.25, "label": "cam-b", "causes": [],
        "tilt_deviation_rad": half_t, "height_deviation_m": 0.03125,
        "tilt_threshold_rad": T_THR, "height_threshold_m": 0.0625}
    assert [s.phase for s in statuses] == ["drift"] * 4 + ["ok"] * 2
    assert det.drifting is False and [e.kind for e in det.events] == ["drift_started", "drift_cleared"]


@pytest.mark.parametrize(("tilt", "height"), [(above(0.5 * T_THR), H0), (0.0, above(H0 + 0.5 * H_THR)),
                                              (above(0.5 * T_THR), H0 + 0.5 * H_THR)])
def test_a_hair_above_the_clear_level_on_either_quantity_never_clears(tilt: float, height: float) -> None:
    det = _drifting()
    for i in range(1, 20):
        assert det.update(at(i, tilt, 0.0, height)).event is None
    assert det.drifting and det.phase == "drift"


def test_clear_s_of_zero_clears_on_the_first_frame_below() -> None:
    det = DriftDetector(replace(EXACT, clear_s=0.0), QUIET)
    assert det.update(at(0, 0.0, 0.0, above(H0 + H_THR))).event is not None
    status = det.update(at(1))
    assert status.event == DriftEvent("drift_cleared", T0 + DT, 0.0, 0.0, T_THR, H_THR, (), "")
    assert status.phase == "ok"


def test_a_frame_above_the_clear_level_restarts_the_clear_timer() -> None:
    """Below from frame 1, above at frame 3, below again from frame 4: cleared at frame 8 (1 s after frame 4)."""
    det = _drifting()
    tilts = {3: 0.75 * T_THR}
    kinds = [getattr(det.update(at(i, tilts.get(i, 0.0))).event, "kind", None) for i in range(1, 10)]
    assert kinds == [None] * 7 + ["drift_cleared", None]


def test_drift_starts_again_after_clearing_and_the_timer_starts_afresh() -> None:
    det = _drifting()
    for i in range(1, 6):
        det.update(at(i))  # cleared at frame 5
    assert det.drifting is False
    assert det.update(at(6, 2 * T_THR)).event is not None  # drift again
    kinds = [getattr(det.update(at(i)).event, "kind", None) for i in range(7, 12)]
    assert kinds == [None, None, None, None, "drift_cleared"]  # a full clear_s again, from frame 7
    assert [e.kind for e in det.events] == ["drift_started", "drift_cleared"] * 2


# ---------------------------------------------------------------------- API
def test_a_bare_detector_uses_the_default_settings_and_rejects_other_samples_in_one_line() -> None:
    det = DriftDetector()
    assert det.settings == MonitorSection() and det.label == "" and det.events == []
    assert det.drifting is False and det.phase == "baseline"
    with pytest.raises(CalibrationError) as info:
        det.update((T0, 0.0, 0.0, 0.44))  # type: ignore[arg-type]
    assert str(info.value) == "DriftDetector.update needs a PlaneSample, got tuple"
