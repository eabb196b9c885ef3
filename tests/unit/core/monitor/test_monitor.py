"""Live drift monitor: the detector on numbers, the monitor on the sim and the O3R emulator, the CLI."""

from __future__ import annotations

import json
import math
import re
import signal
import subprocess
import sys
import threading
import tomllib
from dataclasses import replace
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from ideal_camera import IDEAL_CELL_TOML, ideal_config

from cellcal.core.calibration.config import CellConfig, load_config, parse_config
from cellcal.core.calibration.sections import MonitorSection
from cellcal.core.cli import main
from cellcal.core.geometry.planes import Plane
from cellcal.core.monitor import (
    Baseline,
    DriftDetector,
    DriftEvent,
    Monitor,
    MonitoredCamera,
    MonitorStatus,
    PlaneSample,
)
from cellcal.devices.base import BackendContext
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import CalibrationError, ConfigError, MonitorError
from cellcal.devices.pose import Pose
from cellcal.devices.registry import default_registry
from cellcal.sims.world import SHARED_KEY, SimWorld

CONFIGS = Path(str(resources.files("cellcal.configs")))
DEG = math.pi / 180.0
MM = 1e-3
FPS = 20.0  # the sim camera's frame rate: its timestamps step by 1/FPS per capture
#: Frame-to-frame noise of the full-frame fit on the default sim cell (camera 0.44 m above the
#: table, the sim's default noise measured on a real O3R), measured over 2000 frames of
#: ``plane_sample``: tilt 0.0074 / 0.0050 deg (x / y), height 13.7 um, 1 sigma.
SIM_TILT_SIGMA = 0.0074 * DEG
SIM_HEIGHT_SIGMA = 13.7e-6


# ---------------------------------------------------------------------- helpers
def synthetic(n: int, rng: np.random.Generator, *, tilt_sigma: float = SIM_TILT_SIGMA,
              height_sigma: float = SIM_HEIGHT_SIGMA, base: tuple[float, float, float] = (0.0, 0.0, 0.44),
              offsets: np.ndarray | None = None, t0: float = 1000.0) -> list[PlaneSample]:
    """``n`` samples at FPS around ``base`` with Gaussian noise plus per-frame ``offsets`` (n, 3)."""
    noise = rng.standard_normal((n, 3)) * np.array([tilt_sigma, tilt_sigma, height_sigma])
    values = np.asarray(base) + noise + (0.0 if offsets is None else offsets)
    return [PlaneSample(t0 + i / FPS, *map(float, v)) for i, v in enumerate(values)]


def step_offsets(n: int, at: int, step: tuple[float, float, float]) -> np.ndarray:
    out = np.zeros((n, 3))
    out[at:] = step
    return out


def run_detector(detector: DriftDetector, samples: list[PlaneSample]) -> list[tuple[int, DriftEvent]]:
    events = []
    for i, s in enumerate(samples):
        status = detector.update(s)
        if status.event is not None:
            events.append((i, status.event))
    return events


def make_camera(config: CellConfig) -> tuple[Camera3D, SimWorld]:
    """The configuration's camera from the registry, and the simulated world behind it."""
    shared: dict[str, Any] = {}
    ctx = BackendContext(source=config.source, section="camera", document=config.document, shared=shared,
                         seed=config.cell.seed)
    camera = default_registry().create_camera(config.camera_section, ctx)
    world = shared[SHARED_KEY]
    assert isinstance(world, SimWorld)
    return camera, world


FAST = MonitorSection(period_s=0.0, baseline_frames=20, window_frames=5)


# ---------------------------------------------------------------------- detector on numbers
def test_sim_noise_never_flags_over_thousands_of_frames() -> None:
    rng = np.random.default_rng(1)
    # three times the measured sim noise, 5000 frames (250 s at 20 Hz)
    det = DriftDetector(MonitorSection())
    samples = synthetic(5000, rng, tilt_sigma=3 * SIM_TILT_SIGMA, height_sigma=3 * SIM_HEIGHT_SIGMA)
    assert run_detector(det, samples) == []
    # the configured thresholds are far above this noise, so they are the effective ones
    assert det.tilt_threshold_rad == pytest.approx(0.2 * DEG)
    assert det.height_threshold_m == pytest.approx(2 * MM)
    assert det.baseline is not None and det.baseline.tilt_noise_rad == pytest.approx(3 * SIM_TILT_SIGMA, rel=0.4)


def test_thresholds_follow_the_measured_noise() -> None:
    # a noisy camera: 0.1 deg per axis, 1 mm, against configured 0.2 deg / 2 mm thresholds
    samples = synthetic(5000, np.random.default_rng(2), tilt_sigma=0.1 * DEG, height_sigma=1 * MM)
    fixed = DriftDetector(MonitorSection(noise_sigmas=0.0))
    false_flags = run_detector(fixed, samples)
    assert false_flags and false_flags[0][0] < 100  # configured thresholds alone flag plain noise at once
    det = DriftDetector(MonitorSection())  # noise_sigmas = 6
    assert run_detector(det, samples) == []
    assert det.tilt_threshold_rad is not None and det.height_threshold_m is not None
    assert 0.4 * DEG < det.tilt_threshold_rad < 0.9 * DEG
    assert 4 * MM < det.height_threshold_m < 9 * MM


@pytest.mark.parametrize(("step", "cause"), [((0.5 * DEG, 0.0, 0.0), "tilt"), ((0.0, -0.5 * DEG, 0.0), "tilt"),
                                             ((0.0, 0.0, 5 * MM), "height"), ((0.0, 0.0, -5 * MM), "height")])
def test_a_step_is_flagged_on_the_third_frame(step: tuple[float, float, float], cause: str) -> None:
    n, at = 600, 300
    samples = synthetic(n, np.random.default_rng(3), offsets=step_offsets(n, at, step))
    events = run_detector(DriftDetector(FAST), samples)
    assert [(i, e.kind, e.causes) for i, e in events] == [(at + 2, "drift_started", (cause,))]
    latency_s = events[0][1].timestamp - samples[at].timestamp
    assert latency_s == pytest.approx(2 / FPS)
    assert latency_s <= 1.0


def test_steps_below_the_thresholds_are_not_flagged() -> None:
    n = 2000
    samples = synthetic(n, np.random.default_rng(4), offsets=step_offsets(n, 100, (0.1 * DEG, 0.05 * DEG, 1 * MM)))
    det = DriftDetector(FAST)
    assert run_detector(det, samples) == []


def test_isolated_wild_frames_are_not_flagged_but_would_be_without_the_window() -> None:
    n = 1000
    spikes = np.zeros((n, 3))
    spikes[30::7] = (5 * DEG, 0.0, 20 * MM)  # one wild frame in seven (flying pixels, a hand in view)
    samples = synthetic(n, np.random.default_rng(5), offsets=spikes)
    assert run_detector(DriftDetector(FAST), samples) == []
    assert run_detector(DriftDetector(replace(FAST, window_frames=1)), samples) != []


def test_hysteresis_prevents_flapping_near_the_threshold_and_clears_after_clear_s() -> None:
    thr = 0.2 * DEG
    n_hover, n_back = 2000, 100
    hover = np.zeros((n_hover + n_back, 3))
    hover[:n_hover, 0] = thr  # sits right on the threshold; noise of 5 % of it pushes it across
    rng = np.random.default_rng(6)
    baseline = Baseline(0.0, 0.0, 0.44, tilt_noise_rad=SIM_TILT_SIGMA, height_noise_m=SIM_HEIGHT_SIGMA)
    samples = synthetic(n_hover + n_back, rng, tilt_sigma=0.05 * thr, offsets=hover)

    no_hysteresis = DriftDetector(replace(FAST, hysteresis_ratio=1.0, clear_s=0.0), baseline)
    assert len(run_detector(no_hysteresis, samples)) > 50

    det = DriftDetector(FAST, baseline)  # hysteresis_ratio 0.5, clear_s 1.0
    events = run_detector(det, samples)
    assert [e.kind for _, e in events] == ["drift_started", "drift_cleared"]
    i_clear, cleared = events[1]
    # back at the baseline from frame n_hover; the window median follows two frames later,
    # then the deviation must stay below half the threshold for 1.0 s of frame time
    assert i_clear == n_hover + 2 + round(1.0 * FPS)
    assert cleared.timestamp - samples[n_hover].timestamp == pytest.approx(2 / FPS + 1.0)
    assert not det.drifting


def test_an_interruption_above_the_clear_level_restarts_the_clear_timer() -> None:
    n = 400
    offsets = np.zeros((n, 3))
    offsets[100:200, 2] = 5 * MM  # drift
    offsets[215:225, 2] = 1.5 * MM  # back, then above the clear level (1 mm) for 0.5 s, then back
    samples = synthetic(n, np.random.default_rng(7), offsets=offsets)
    events = run_detector(DriftDetector(FAST), samples)
    assert [(i, e.kind) for i, e in events] == [(102, "drift_started"), (225 + 2 + 20, "drift_cleared")]


def test_a_given_baseline_with_noise_needs_no_warm_up() -> None:
    given = Baseline(0.0, 0.0, 0.445, tilt_noise_rad=SIM_TILT_SIGMA, height_noise_m=SIM_HEIGHT_SIGMA)
    det = DriftDetector(FAST, given)
    assert det.phase == "ok" and det.height_threshold_m == pytest.approx(2 * MM)
    events = run_detector(det, synthetic(50, np.random.default_rng(8)))  # 5 mm below the given height
    assert [(i, e.kind, e.causes) for i, e in events] == [(FAST.window_frames - 1, "drift_started", ("height",))]
    assert events[0][1].height_deviation_m == pytest.approx(5 * MM, abs=0.05 * MM)


def test_a_given_baseline_without_noise_measures_the_noise_on_the_first_frames() -> None:
    det = DriftDetector(FAST, Baseline(0.0, 0.3 * DEG, 0.44))
    events = run_detector(det, synthetic(60, np.random.default_rng(9)))
    assert [(i, e.causes) for i, e in events] == [(FAST.baseline_frames, ("tilt",))]  # first frame after warm-up
    assert det.baseline is not None and det.baseline.tilt_y_rad == pytest.approx(0.3 * DEG)
    assert det.baseline.tilt_noise_rad == pytest.approx(SIM_TILT_SIGMA, rel=0.4)


def test_bad_samples_and_baselines_are_rejected_in_one_line() -> None:
    with pytest.raises(CalibrationError, match="finite"):
        PlaneSample(0.0, math.nan, 0.0, 0.4)
    with pytest.raises(CalibrationError, match="PlaneSample"):
        DriftDetector().update((0.0, 0.0, 0.0, 0.4))  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="height_m"):
        Baseline.from_dict({"tilt_x_rad": 0.0, "tilt_y_rad": 0.0}, source="b.json")
    with pytest.raises(ConfigError, match="finite"):
        Baseline.from_dict({"tilt_x_rad": "x", "tilt_y_rad": 0.0, "height_m": 0.4}, source="b.json")
    b = Baseline(0.01, -0.02, 0.5, 1e-4, 2e-6)
    assert Baseline.from_dict(json.loads(json.dumps(b.to_dict()))) == b


# ---------------------------------------------------------------------- monitor on the sim
def collect(statuses: list[MonitorStatus]) -> Any:
    return statuses.append


def test_baseline_from_the_plane_in_the_base_frame_matches_the_measured_one() -> None:
    config = ideal_config(ideal_arm=True)  # the measured baseline against the planned geometry to 0.1 mm
    camera, world = make_camera(config)
    expected = Baseline.from_plane_in_base(Plane.from_point_normal((0, 0, 0), (0, 0, 1)), world.camera_pose())
    summary = Monitor([MonitoredCamera("sim", camera, FAST, config.full_frame)]).run(max_frames=25)
    measured = summary.cameras[0].baseline
    assert measured is not None
    assert expected.height_m == pytest.approx(0.44, abs=1e-9)
    assert abs(measured.height_m - expected.height_m) < 0.1 * MM
    assert abs(measured.tilt_x_rad - expected.tilt_x_rad) < 0.01 * DEG
    assert abs(measured.tilt_y_rad - expected.tilt_y_rad) < 0.01 * DEG


@pytest.mark.parametrize(("delta", "cause"), [
    (Pose.from_xyz_rpy((0.0, 0.0, 0.0), (0.5 * DEG, 0.0, 0.0)), "tilt"),    # 0.5 deg about the camera's x
    (Pose.from_xyz_rpy((0.0, 0.0, 0.0), (0.0, 0.5 * DEG, 0.0)), "tilt"),    # 0.5 deg about its y
    (Pose.from_xyz_rpy((0.0, 0.0, 5 * MM), (0.0, 0.0, 0.0)), "height"),     # 5 mm along the optical axis
])
def test_a_bump_on_the_sim_is_flagged_within_the_window_and_not_before(delta: Pose, cause: str) -> None:
    config = load_config(None)
    camera, world = make_camera(config)
    statuses: list[MonitorStatus] = []
    bump_after = 34

    def on_status(status: MonitorStatus) -> None:
        statuses.append(status)
        if status.index == bump_after:
            world.bump_mount(delta)

    summary = Monitor([MonitoredCamera("sim", camera, FAST, config.full_frame)], on_status).run(max_frames=50)
    assert not camera.connected
    assert all(s.error is None for s in statuses) and len(statuses) == 50
    assert all(s.phase != "drift" for s in statuses[:bump_after + 1])
    flagged = [s for s in statuses if s.event is not None]
    assert len(flagged) == 1 and flagged[0].event is not None
    first_bumped = bump_after + 1
    assert flagged[0].index == first_bumped + FAST.window_frames // 2  # the 3rd bumped frame
    assert flagged[0].event.kind == "drift_started" and cause in flagged[0].event.causes
    assert statuses[first_bumped].detector is not None
    latency_s = flagged[0].event.timestamp - statuses[first_bumped].detector.sample.timestamp
    assert latency_s == pytest.approx((FAST.window_frames // 2) / FPS, abs=1e-3)
    assert summary.drift_detected and summary.cameras[0].drifting


@pytest.mark.statistical
def test_sim_noise_does_not_flag_over_200_real_frames() -> None:
    config = load_config(None)
    camera, _ = make_camera(config)
    summary = Monitor([MonitoredCamera("sim", camera, FAST, config.full_frame)]).run(max_frames=200)
    cam = summary.cameras[0]
    assert cam.frames == 200 and cam.errors == 0 and cam.events == [] and not summary.drift_detected
    assert cam.tilt_threshold_rad is not None and cam.height_threshold_m is not None
    # far below the thresholds: the worst of 200 frames is what the fit's frame-to-frame noise gives
    # (measured 0.0248 deg of tilt, 3.4 sigma, 8x below 0.2 deg; 0.038 mm of height, 53x below 2 mm).
    # 5x leaves room for a 5.4 sigma tilt, which 200 frames of plain noise do not reach
    assert cam.max_tilt_deviation_rad < cam.tilt_threshold_rad / 5
    assert cam.max_tilt_deviation_rad < 5.4 * SIM_TILT_SIGMA
    assert cam.max_height_deviation_m < cam.height_threshold_m / 10


def test_o3r_emulator_stays_quiet_and_leaves_no_thread() -> None:
    before = set(threading.enumerate())
    config = ideal_config(CONFIGS / "o3r_emulated.toml", ideal_arm=True)  # the height to 0.1 mm of the plan's
    camera, _ = make_camera(config)
    assert camera.backend_name == "o3r-emulated"
    summary = Monitor([MonitoredCamera("o3r", camera, FAST, config.full_frame)]).run(max_frames=40)
    cam = summary.cameras[0]
    assert (cam.frames, cam.errors, cam.events) == (40, 0, [])
    assert cam.baseline is not None and cam.baseline.height_m == pytest.approx(0.44, abs=0.1 * MM)
    assert not camera.connected
    assert [t for t in threading.enumerate() if t not in before and t.is_alive()] == []


def test_a_bump_behind_the_o3r_emulator_is_flagged_too() -> None:
    config = load_config(CONFIGS / "o3r_emulated.toml")
    camera, world = make_camera(config)
    statuses: list[MonitorStatus] = []

    def on_status(status: MonitorStatus) -> None:
        statuses.append(status)
        if status.index == 25:
            world.bump_mount(Pose.from_xyz_rpy((0.0, 0.0, 5 * MM), (0.0, 0.0, 0.0)))

    Monitor([MonitoredCamera("o3r", camera, FAST, config.full_frame)], on_status).run(max_frames=35)
    assert [(s.index, s.event.kind) for s in statuses if s.event is not None] == [(28, "drift_started")]


def test_two_cameras_are_watched_independently() -> None:
    a_cfg, b_cfg = load_config(None), load_config(CONFIGS / "o3r_emulated.toml")
    (a, world_a), (b, _) = make_camera(a_cfg), make_camera(b_cfg)
    seen: list[tuple[str, int]] = []

    def on_status(status: MonitorStatus) -> None:
        seen.append((status.label, status.index))
        if status.label == "a" and status.index == 24:
            world_a.bump_mount(Pose.from_xyz_rpy((0.0, 0.0, 0.0), (1 * DEG, 0.0, 0.0)))

    summary = Monitor([MonitoredCamera("a", a, FAST), MonitoredCamera("b", b, FAST)], on_status).run(max_frames=30)
    assert seen[:4] == [("a", 0), ("b", 0), ("a", 1), ("b", 1)]
    by_label = {c.label: c for c in summary.cameras}
    assert [e.kind for e in by_label["a"].events] == ["drift_started"] and by_label["b"].events == []
    assert not a.connected and not b.connected


def test_background_run_stops_cleanly_and_joins_its_thread() -> None:
    before = set(threading.enumerate())
    config = load_config(CONFIGS / "o3r_emulated.toml")
    camera, _ = make_camera(config)
    got_ten = threading.Event()

    def on_status(status: MonitorStatus) -> None:
        if status.index >= 9:
            got_ten.set()

    monitor = Monitor([MonitoredCamera("o3r", camera, FAST)], on_status).start()
    assert got_ten.wait(60.0)
    summary = monitor.stop(timeout=30.0)
    assert summary.cameras[0].frames >= 10 and not summary.interrupted
    assert not camera.connected
    assert [t for t in threading.enumerate() if t not in before and t.is_alive()] == []


def test_ctrl_c_in_the_loop_returns_a_summary_and_closes_the_camera() -> None:
    camera, _ = make_camera(load_config(None))

    def on_status(status: MonitorStatus) -> None:
        if status.index == 5:
            raise KeyboardInterrupt

    summary = Monitor([MonitoredCamera("sim", camera, FAST)], on_status).run()
    assert summary.interrupted and summary.cameras[0].frames == 6
    assert not camera.connected


def test_a_camera_that_loses_the_plane_reports_failed_frames_then_stops_the_run() -> None:
    config = load_config(None)
    camera, world = make_camera(config)
    statuses: list[MonitorStatus] = []

    def on_status(status: MonitorStatus) -> None:
        statuses.append(status)
        if status.index == 3:
            world.bump_mount(Pose.from_xyz_rpy((0.0, 0.0, 0.0), (120 * DEG, 0.0, 0.0)))  # now looks up

    monitor = Monitor([MonitoredCamera("sim", camera, FAST)], on_status, max_consecutive_errors=4)
    with pytest.raises(MonitorError, match=r"sim: 4 failed frames in a row; last: .*valid"):
        monitor.run(max_frames=50)
    assert [s.error is None for s in statuses] == [True] * 4 + [False] * 3
    assert not camera.connected


def test_duplicate_labels_and_no_cameras_are_config_errors() -> None:
    camera, _ = make_camera(load_config(None))
    with pytest.raises(ConfigError, match="label 'x'"):
        Monitor([MonitoredCamera("x", camera), MonitoredCamera("x", camera)])
    with pytest.raises(ConfigError, match="at least one camera"):
        Monitor([])


def test_monitor_table_is_validated() -> None:
    text = (CONFIGS / "sim.toml").read_text() + "\n[monitor]\nwindow_frames = 0\n"
    with pytest.raises(ConfigError, match=r"monitor\.window_frames"):
        parse_config(tomllib.loads(text), "x.toml")
    assert load_config(None).monitor == MonitorSection()


# ---------------------------------------------------------------------- CLI
@pytest.fixture
def fast_config(tmp_path: Path) -> Path:
    """sim.toml with a fast [monitor] table and an ideal camera (baselines against the true geometry to 0.1 mm)."""
    path = tmp_path / "fast.toml"
    path.write_text((CONFIGS / "sim.toml").read_text()
                    + "\n[monitor]\nperiod_s = 0.0\nbaseline_frames = 10\nstatus_every_s = 0.01\n" + IDEAL_CELL_TOML)
    return path


def test_cli_frames_run_is_quiet_and_exits_0(fast_config: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["monitor", "--config", str(fast_config), "--frames", "30", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "fast: 30 frames, 0 failed, 0 drift event(s), now ok" in out
    assert "DRIFT" not in out and "baseline tilt_x" not in out


def test_cli_duration_run_prints_status_lines(fast_config: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["monitor", "--config", str(fast_config), "--duration", "1.5"]) == 0
    out = capsys.readouterr().out
    assert "monitoring fast (sim," in out and "monitor finished after" in out
    assert "[fast] baseline tilt_x" in out and "from baseline" in out


def test_cli_baseline_round_trip_and_drift_exit_status(fast_config: Path, tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    saved = tmp_path / "baseline.json"
    assert main(["monitor", "--config", str(fast_config), "--frames", "15", "--quiet",
                 "--save-baseline", str(saved)]) == 0
    doc = json.loads(saved.read_text())
    assert doc["cameras"]["fast"]["height_m"] == pytest.approx(0.44, abs=0.1 * MM)
    assert main(["monitor", "--config", str(fast_config), "--frames", "15", "--quiet",
                 "--baseline", str(saved)]) == 0
    doc["cameras"]["fast"]["height_m"] += 3 * MM  # the camera now sits 3 mm closer than it should
    saved.write_text(json.dumps(doc))
    capsys.readouterr()
    assert main(["monitor", "--config", str(fast_config), "--frames", "15", "--quiet",
                 "--baseline", str(saved)]) == 1
    out = capsys.readouterr().out
    assert "[fast] t=+0.20 s DRIFT STARTED (height): tilt" in out and "(threshold 2.00 mm)" in out
    # the 3 mm step, seen through the noise: a 5-frame median against the 10-frame baseline scatters by less
    # than one frame's height noise (SIM_HEIGHT_SIGMA, 13.7 um); 2.99 mm is printed, 0.02 mm allows ~1.5 of it
    shown = re.search(r"height (\d+\.\d\d) mm \(threshold", out)
    assert shown is not None and float(shown.group(1)) == pytest.approx(3.0, abs=0.02)
    assert "now DRIFTING" in out


def test_cli_missing_baseline_exits_2(fast_config: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["monitor", "--config", str(fast_config), "--baseline", "missing.json"]) == 2
    assert "baseline file not found" in capsys.readouterr().err


@pytest.mark.parametrize(("argv", "message"), [
    (["--duration", "-1"], "argument --duration: expected a finite number > 0, got '-1'"),
    (["--duration", "nan"], "argument --duration: expected a finite number > 0, got 'nan'"),
    (["--frames", "0"], "argument --frames: expected an integer >= 1, got '0'"),
    (["--frames", "2.5"], "argument --frames: expected an integer >= 1, got '2.5'"),
])
def test_cli_bad_duration_or_frames_is_a_usage_error(fast_config: Path, argv: list[str], message: str,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """Checked by the parser (cellcal.core.cli.argtypes): status 2, one line, before any device is built."""
    with pytest.raises(SystemExit) as info:
        main(["monitor", "--config", str(fast_config), *argv])
    assert info.value.code == 2
    assert capsys.readouterr().err == f"cellcal monitor: error: {message}\n"


def test_cli_rejects_a_baseline_file_of_another_kind(fast_config: Path, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"schema": "cellcal.study/1"}))
    assert main(["monitor", "--config", str(fast_config), "--baseline", str(other)]) == 2
    assert "not a monitor baseline file" in capsys.readouterr().err


def test_cli_watches_the_sim_and_the_o3r_emulator_together(fast_config: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    before = set(threading.enumerate())
    o3r = fast_config.with_name("o3r.toml")
    o3r.write_text(fast_config.read_text().replace('backend = "sim"', 'backend = "o3r-emulated"', 1))
    assert main(["monitor", "--config", str(fast_config), "--config", str(o3r), "--frames", "15", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "fast: 15 frames, 0 failed" in out and "o3r: 15 frames, 0 failed" in out
    assert [t for t in threading.enumerate() if t not in before and t.is_alive()] == []


def test_cli_ctrl_c_prints_the_summary_and_exits_130(fast_config: Path) -> None:
    proc = subprocess.Popen([sys.executable, "-m", "cellcal.core.cli", "monitor", "--config", str(fast_config)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            if "from baseline" in line:
                break
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, err
    assert "monitor interrupted after" in out and "fast:" in out and "Traceback" not in err


def result_with_plane(path: Path, normal: tuple[float, float, float], offset_m: float) -> Path:
    """A calibration result carrying only what the monitor reads: its plane in the base frame."""
    doc = {"schema": "cellcal.calibration/2",
           "summary": {"plane_consistency": {"consensus_plane_base": {"normal": list(normal), "offset_m": offset_m}}}}
    path.write_text(json.dumps(doc))
    return path


def test_cli_baseline_from_a_calibration_result_at_the_arms_pose(fast_config: Path, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    table = result_with_plane(tmp_path / "true.json", (0.0, 0.0, 1.0), 0.0)  # the sim's table, z = 0
    assert main(["monitor", "--config", str(fast_config), "--frames", "15", "--baseline", str(table)]) == 0
    line = re.search(r"\[fast\] baseline tilt_x (\S+) deg, tilt_y (\S+) deg, height (\S+) mm", capsys.readouterr().out)
    assert line is not None  # the table seen from the arm's reported pose (its reading error: tens of um)
    assert abs(float(line[1])) < 0.01 and abs(float(line[2])) < 0.01 and abs(float(line[3]) - 440.0) < 0.1
    a = 0.5 * DEG  # a calibration that found the plane tilted by 0.5 deg about the base x axis
    tilted = result_with_plane(tmp_path / "tilted.json", (0.0, -math.sin(a), math.cos(a)), 0.0)
    assert main(["monitor", "--config", str(fast_config), "--frames", "15", "--quiet",
                 "--baseline", str(tilted)]) == 1
    event = re.search(r"DRIFT STARTED \(tilt\): tilt (\S+) deg", capsys.readouterr().out)
    assert event is not None and abs(float(event[1]) - 0.5) < 0.01


def test_cli_calibration_result_without_a_base_plane_or_with_two_cameras_exits_2(
        fast_config: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bare = tmp_path / "bare.json"
    bare.write_text(json.dumps({"schema": "cellcal.calibration/1", "summary": {}}))
    assert main(["monitor", "--config", str(fast_config), "--baseline", str(bare)]) == 2
    assert "consensus_plane_base" in capsys.readouterr().err
    table = result_with_plane(tmp_path / "true.json", (0.0, 0.0, 1.0), 0.0)
    assert main(["monitor", "--config", str(fast_config), "--config", str(fast_config), "--baseline", str(table)]) == 2
    assert "baseline of one camera" in capsys.readouterr().err
