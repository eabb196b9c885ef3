"""The kit never hangs, tests timeouts against a stalled device, and reports a malformed frame once.

A small camera is defined here over a fake "link" (a frame queue a fake device fills):
its capture can hang for ever, ignore its timeout, or build a Frame of the wrong shape;
and a small arm whose controller can stall.
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest
from numpy.typing import NDArray

from cellcal.devices import (
    ArmStatus,
    BackendContext,
    Camera3D,
    DeviceInfo,
    DeviceTimeoutError,
    Frame,
    Intrinsics,
    Pose,
    RobotArm,
)
from cellcal.devices.measurement import MeasurementModel
from cellcal.testing import CAMERA_RULES, ArmOptions, CameraOptions, check_arm, check_camera

pytest_plugins = ["pytester"]

#: Released at teardown, so a capture that "never returns" ends with the test.
_release = threading.Event()
INTR = Intrinsics(32, 24, 30.0, 30.0, 15.5, 11.5)


@pytest.fixture(autouse=True)
def _release_hung_calls() -> Any:
    _release.clear()
    yield
    _release.set()


class FakeLink:
    """A device's frame stream: ``stalled`` sends nothing; otherwise a frame is ready at once."""

    def __init__(self, stalled: bool = False):
        self.stalled = stalled

    def next_frame(self, wait_s: float) -> int:
        if self.stalled:
            time.sleep(wait_s)
            raise queue.Empty
        return 1


class LinkCamera(Camera3D):
    """A wall 1.5 m away, seen through a :class:`FakeLink`; ``behaviour`` breaks it one way."""

    backend_name = "link-cam"
    behaviour: ClassVar[str] = ""
    model: ClassVar[MeasurementModel] = MeasurementModel(kind="tof", sigma_at_1m_m=0.004, source="backend")

    @dataclass(frozen=True)
    class Config:
        stalled: bool = False

    def _measurement_model(self) -> MeasurementModel:
        return self.model

    def __init__(self, config: Any = None, context: BackendContext | None = None):
        super().__init__()
        self.config = config or self.Config()
        self._seq = 0
        self._link: FakeLink | None = None

    def _connect(self, timeout: float) -> None:
        self._link = FakeLink(self.config.stalled)

    def _close(self) -> None:
        self._link = None

    def _info(self) -> DeviceInfo:
        return DeviceInfo(backend=self.backend_name, vendor="Toy", model="L1")

    def _intrinsics(self) -> Intrinsics:
        return INTR

    def _capture(self, timeout: float) -> Frame:
        if self.behaviour == "hangs":
            _release.wait()                                   # a vendor call that never returns
        assert self._link is not None
        wait_s = 1.5 if self.behaviour == "ignores-timeout" else timeout  # its own fixed wait, not the caller's
        try:
            self._link.next_frame(wait_s)
        except queue.Empty:
            raise DeviceTimeoutError(f"link-cam: no frame within {wait_s:g} s") from None
        v, u = np.mgrid[0:INTR.height, 0:INTR.width].astype(np.float64)
        xyz = np.dstack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones_like(u)]) * 1.5
        distance = np.linalg.norm(xyz, axis=2)
        if self.behaviour == "transposed":
            distance = distance.T                             # rows and columns swapped
        self._seq += 1
        return Frame(distance.astype(np.float32), xyz.astype(np.float32), np.ones(INTR.shape, np.float32),
                     np.ones(INTR.shape, bool), INTR, 1.7e9 + 0.05 * self._seq, self._seq)


def camera(behaviour: str) -> type[LinkCamera]:
    return type(f"LinkCamera_{behaviour or 'ok'}", (LinkCamera,), {"behaviour": behaviour})


FAST = {"distance_range_m": (0.1, 5.0), "short_timeout_s": 0.05, "timing_slack_s": 0.3, "capture_timeout_s": 0.5,
        # its 32 x 24 image holds the grid up to 10.5 px; its noise-free wall is for the watchdog, not a calibration
        "perimeters_px": (10,), "scene_reason": "a noise-free wall: these tests are about the watchdog"}


def test_a_capture_that_never_returns_fails_one_rule_names_the_hook_and_the_kit_finishes(
        capsys: pytest.CaptureFixture[str]) -> None:
    cls = camera("hangs")
    t0 = time.monotonic()
    report = check_camera(cls, CameraOptions(watchdog_s=0.4, **FAST), raise_on_failure=False)
    took = time.monotonic() - t0
    # the first rule that captures hangs: capture(0.5 s) gets 0.5 + 0.4 s, then the kit moves on
    assert took < 5.0                                         # not the 15 x 0.9 s of a hang per rule
    verdicts = {r.rule: ("pass" if r.passed else "skip" if r.skipped else "fail") for r in report.results}
    assert verdicts["camera.factory"] == verdicts["camera.not-connected"] == "pass"
    hung = report.results[2]
    assert hung.rule == "camera.connect-idempotent" and verdicts[hung.rule] == "fail"
    assert f"hook {cls.__name__}._capture (called through capture())" in hung.detail
    elapsed = float(hung.detail.split("did not return after ")[1].split(" s")[0])
    assert 0.9 <= elapsed < 3.0                               # 0.5 s timeout + 0.4 s watchdog, late on a busy machine
    assert "allowed: its timeout 0.5 s + 0.4 s" in hung.detail
    assert [verdicts[r] for r in CAMERA_RULES[3:]] == ["skip"] * (len(CAMERA_RULES) - 3)
    assert "hung under camera.connect-idempotent" in report.results[-1].detail
    assert len(report.failures) == 1 and not report.ok
    # every rule is announced as it starts, the hung one included
    err = capsys.readouterr().err
    assert [line.split()[-2] for line in err.splitlines()] == list(CAMERA_RULES)


def test_an_ignored_timeout_passes_against_a_fast_device_and_fails_against_a_stalled_one() -> None:
    cls = camera("ignores-timeout")
    fast = check_camera(cls, CameraOptions(**FAST), only=["camera.timeout-bounded"], quiet=True)
    assert fast.ok                                            # the device answers at once: nothing to see
    stalled = CameraOptions(stalled_factory=lambda: cls.from_config({"stalled": True}), **FAST)
    report = check_camera(cls, stalled, only=["camera.timeout-bounded"], raise_on_failure=False, quiet=True)
    (result,) = report.results
    assert not result.passed
    assert "against a stalled device (it sends nothing), capture() #1 with timeout 0.05 s took" in result.detail
    took = float(result.detail.split(" took ")[1].split(" s")[0])
    assert 1.45 <= took < 3.0 and "the timeout is not honoured" in result.detail  # the 1.5 s stall, not 0.05 s


def test_a_correct_camera_passes_every_rule_with_a_stalled_device() -> None:
    cls = camera("")
    options = CameraOptions(stalled_factory=lambda: cls.from_config({"stalled": True}), **FAST)
    report = check_camera(cls, options, quiet=True)
    assert report.ok and len(report.results) == len(CAMERA_RULES) and not any(r.skipped for r in report.results)


def test_a_stalled_device_that_answers_is_a_violation() -> None:
    cls = camera("")
    options = CameraOptions(stalled_factory=cls, **FAST)     # not stalled: frames arrive
    report = check_camera(cls, options, only=["camera.timeout-bounded"], raise_on_failure=False, quiet=True)
    assert "returned Frame, expected DeviceTimeoutError" in report.results[0].detail


def test_a_malformed_frame_is_reported_once_under_frame_layout() -> None:
    report = check_camera(camera("transposed"), CameraOptions(**FAST), raise_on_failure=False, quiet=True)
    (failure,) = report.failures
    assert failure.rule == "camera.frame-layout"
    assert "could not build a Frame: Frame.distance must be float32 of shape (24, 32), got ((32, 24)" in failure.detail
    skipped = [r.rule for r in report.results if r.skipped]
    # every rule that captures is skipped, pointing at frame-layout; the others still pass
    assert set(skipped) == {"camera.connect-idempotent", "camera.use-after-close", "camera.frame-units",
                            "camera.frame-geometry", "camera.sequence", "camera.measurement-model",
                            "camera.timeout-validation", "camera.timeout-bounded", "camera.releases-resources"}
    assert all("reported under camera.frame-layout" in r.detail for r in report.results if r.skipped)
    assert "1/17" not in str(report) and "7/17 contract checks passed, 9 skipped" in str(report)


PYTEST_MODULE = '''
import pytest
from cellcal.testing import CameraConformance, CameraOptions
from test_kit_watchdog import FAST, camera


class TestTransposed(CameraConformance):
    options = CameraOptions(**FAST)

    def make_camera(self):
        return camera("transposed")()


class TestIgnoresTimeout(CameraConformance):
    options = CameraOptions(**FAST)

    def make_camera(self):
        return camera("ignores-timeout")()

    @pytest.fixture
    def stalled_camera_factory(self):
        return lambda: camera("ignores-timeout").from_config({"stalled": True})
'''


def test_under_pytest_a_malformed_frame_fails_one_test_and_skips_the_rest_and_the_stalled_fixture_is_used(
        pytester: pytest.Pytester) -> None:
    pytester.syspathinsert(str(Path(__file__).parent))
    pytester.makepyfile(test_vendor=PYTEST_MODULE)
    result = pytester.runpytest("-p", "no:cacheprovider", "-rs", "-q")
    # TestTransposed: frame-layout fails, 9 rules skip, 7 pass; TestIgnoresTimeout: only timeout-bounded fails
    result.assert_outcomes(passed=7 + 16, failed=2, skipped=9)
    out = result.stdout.str()
    assert "TestTransposed.test_contract[camera.frame-layout]" in out
    assert "TestIgnoresTimeout.test_contract[camera.timeout-bounded]" in out and "the timeout is not honoured" in out
    assert out.count("skipped: needs a well-formed frame") == 9


class LinkArm(RobotArm):
    """An arm whose controller answers reads at once, or (``stalled``) never; ``careless`` waits 1.5 s regardless."""

    backend_name = "link-arm"
    careless: ClassVar[bool] = False

    @dataclass(frozen=True)
    class Config:
        stalled: bool = False

    def __init__(self, config: Any = None, context: BackendContext | None = None):
        super().__init__()
        self.config = config or self.Config()

    def _read(self, timeout: float) -> None:
        if self.config.stalled:
            time.sleep(1.5 if self.careless else timeout)
            raise DeviceTimeoutError(f"link-arm: no reply within {timeout:g} s")

    def _connect(self, timeout: float) -> None:
        pass

    def _close(self) -> None:
        pass

    def _info(self) -> DeviceInfo:
        return DeviceInfo(backend=self.backend_name, vendor="Toy", model="A1")

    def _get_pose(self, timeout: float) -> Pose:
        self._read(timeout)
        return Pose.from_xyz_rpy(np.array([0.3, 0.0, 0.4]), np.array([np.pi, 0.0, 0.0]))

    def _move_linear(self, pose: Pose, speed: float, acceleration: float, timeout: float) -> None:
        raise AssertionError("not moved in these tests")

    def _stop(self, timeout: float) -> None:
        pass

    def _joint_positions(self, timeout: float) -> NDArray[np.float64]:
        self._read(timeout)
        return np.zeros(5)

    def _status(self, timeout: float) -> ArmStatus:
        self._read(timeout)
        return ArmStatus()

    def _clear_errors(self, timeout: float) -> None:
        pass


@pytest.mark.parametrize("careless", [False, True])
def test_arm_reads_against_a_stalled_controller(careless: bool) -> None:
    cls = type("CarelessArm" if careless else "CarefulArm", (LinkArm,), {"careless": careless})
    options = ArmOptions(short_timeout_s=0.05, timing_slack_s=0.3, stalled_factory=lambda: cls.from_config(
        {"stalled": True}))
    report = check_arm(cls, options, only=["arm.timeout-bounded"], raise_on_failure=False, quiet=True)
    (result,) = report.results
    assert result.passed is not careless
    if careless:
        assert result.detail.startswith("against a stalled device (it sends nothing), get_pose() with timeout 0.05 s "
                                        "took ")
        took = float(result.detail.split(" took ")[1].split(" s")[0])
        assert 1.45 <= took < 3.0                             # its own 1.5 s wait, not the 0.05 s asked for
