"""The conformance kit catches broken backends, names the rule and the backend, and needs no pytest.

A tiny correct camera and arm (pure numpy, defined here) pass every rule; each
mutant breaks one promise the way real backends do (millimetres, depth instead of
radial distance, y up, degrees, stale frames, ignored timeouts, leaked threads,
bypassed life cycle) and must fail exactly the rules that promise belongs to.
"""

from __future__ import annotations

import dataclasses
import math
import re
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cellcal.devices import (
    ArmStatus,
    BackendContext,
    Camera3D,
    CellcalError,
    DeviceInfo,
    Frame,
    Intrinsics,
    Pose,
    RobotArm,
    VendorError,
)
from cellcal.devices.errors import ConformanceError
from cellcal.devices.measurement import MeasurementModel
from cellcal.testing import ARM_RULES, CAMERA_RULES, ArmOptions, CameraOptions, ScenePlane, check_arm, check_camera

_release_leaks = threading.Event()
#: Fast timing for the timeout mutants: a call may take its timeout + 0.1 s.
FAST = {"short_timeout_s": 0.05, "timing_slack_s": 0.1}


@pytest.fixture(autouse=True)
def _stop_leaked_threads() -> Any:
    _release_leaks.clear()
    yield
    _release_leaks.set()


def _leak_thread() -> None:
    threading.Thread(target=_release_leaks.wait, args=(10.0,), name="toy leak", daemon=True).start()


# ---------------------------------------------------------------- a correct camera, and mutants
class ToyCamera(Camera3D):
    """160 x 120 px pinhole ToF camera facing a wall 1.5 m ahead on its axis, tilted 20 deg about the camera's x axis;
    a 4 x 4 px corner is invalid. It draws the range noise it states (4 mm at 1 m, x range^1.5), from a seed per
    frame."""

    backend_name = "toy-cam"
    mutation: ClassVar[str] = ""

    @dataclass(frozen=True)
    class Config:
        wall_m: float = 1.5

    def __init__(self, config: Any = None, context: BackendContext | None = None):
        super().__init__()
        self.config = config or self.Config()
        self._seq = 0

    def _connect(self, timeout: float) -> None:
        if self.mutation == "leaks-thread":
            _leak_thread()

    def _close(self) -> None:
        pass

    def _info(self) -> DeviceInfo:
        return DeviceInfo(backend="toy-cam", vendor="" if self.mutation == "no-vendor" else "Toy", model="T1")

    def _intrinsics(self) -> Intrinsics:
        if self.mutation == "tiny-image":
            return Intrinsics(64, 48, 60.0, 60.0, 31.5, 23.5)
        f = 0.004 if self.mutation == "focal-in-metres" else 150.0
        return Intrinsics(160, 120, f, f, 79.5, 59.5)

    def _configured_intrinsics(self) -> Intrinsics | None:
        if self.mutation == "configured-wrong-size":      # what its config says differs from what it sends
            return Intrinsics(224, 172, 150.0, 150.0, 111.5, 85.5)
        return None

    def _measurement_model(self) -> MeasurementModel:
        m = self.mutation
        if m == "states-no-model":
            return super()._measurement_model()
        if m == "returns-a-dict":
            return {"kind": "tof"}  # type: ignore[return-value]
        source = "unstated" if m == "model-without-source" else "backend"
        settings: dict[str, Any] = {"mode": "near"} if m != "settings-not-json" else {"mode": {"near"}}
        sigma = 0.0004 if m == "states-a-tenth-of-its-noise" else TOY_SIGMA_AT_1M_M
        return MeasurementModel(kind="tof", sigma_at_1m_m=sigma, source=source, settings=settings)

    def _capture(self, timeout: float) -> Frame:
        m = self.mutation
        if m == "ignores-timeout" and timeout < 1.0:
            time.sleep(0.5)
        if m == "builtin-timeout-error" and timeout < 1.0:
            raise TimeoutError("no frame")
        intr = self._intrinsics()
        v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
        rays = np.dstack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)])
        rays /= np.linalg.norm(rays, axis=2, keepdims=True)                  # unit rays
        normal = np.asarray(TOY_SCENE.normal)                                 # the tilted wall
        distance = (normal @ [0.0, 0.0, self.config.wall_m]) / (rays @ normal)
        if m != "noise-free":
            rng = np.random.default_rng(self._seq)
            distance = distance + TOY_SIGMA_AT_1M_M * np.abs(distance)**1.5 * rng.standard_normal(distance.shape)
        if m == "rows-bottom-up":                           # read out from the last row, not flipped back
            distance = distance[::-1].copy()
        xyz = rays * distance[..., None]
        if m == "millimetres":
            xyz, distance = xyz * 1000.0, distance * 1000.0
        if m == "depth-not-radial":
            distance = xyz[..., 2].copy()
        if m == "y-up":
            xyz[..., 1] *= -1.0
        valid = np.ones(intr.shape, bool)
        valid[:4, :4] = False
        if m != "invalid-not-nan":
            xyz[~valid], distance[~valid] = np.nan, np.nan
        if m != "stale-frames":
            self._seq += 1
        frame_intr = dataclasses.replace(intr, fx=151.0, fy=151.0) if m == "frame-intrinsics-differ" else intr
        # a frame stamped with another model than the camera states (e.g. a stale one)
        model = FRAME_MODEL_DIFFERS if m == "frame-model-differs" else MeasurementModel()
        return Frame(distance.astype(np.float32), xyz.astype(np.float32), np.ones(intr.shape, np.float32), valid,
                     frame_intr, 1.7e9 + 0.05 * self._seq, self._seq, measurement=model)


#: The range noise the toy camera draws and states, 1-sigma at 1 m (times range^1.5), metres.
TOY_SIGMA_AT_1M_M = 0.004
#: The toy camera's test scene: the wall 1.5 m ahead, its normal tilted 20 deg about the camera's x axis.
TOY_SCENE = ScenePlane(normal=(0.0, math.sin(math.radians(20.0)), -math.cos(math.radians(20.0))),
                       axis_distance_m=1.5)
FRAME_MODEL_DIFFERS = MeasurementModel(kind="tof", sigma_at_1m_m=0.008, source="backend")


class BypassingCamera(ToyCamera):
    """Overrides the public capture() and skips the life-cycle check the base class does."""

    def capture(self, timeout: float | None = None) -> Frame:
        return self._capture(5.0 if timeout is None else timeout)


def camera_mutant(mutation: str) -> type[ToyCamera]:
    return type(f"ToyCamera_{mutation}", (ToyCamera,), {"mutation": mutation})


TOY_CAMERA_OPTIONS = CameraOptions(distance_range_m=(0.1, 5.0), scene_plane=TOY_SCENE, **FAST)


def test_correct_toy_camera_passes_every_rule() -> None:
    report = check_camera(ToyCamera, TOY_CAMERA_OPTIONS)
    assert report.ok and report.backend == "toy-cam"
    assert [r.rule for r in report.results] == list(CAMERA_RULES) and len(CAMERA_RULES) == 17
    assert str(report).startswith("camera backend toy-cam: 17/17 contract checks passed")


CAMERA_MUTANTS = {
    # calibrate's fit refuses what it cannot measure: millimetres by name, ranges off the rays as no plane
    "millimetres": {"camera.frame-units", "camera.calibrate-frames"},
    "depth-not-radial": {"camera.frame-units", "camera.calibrate-frames"},
    "y-up": {"camera.frame-geometry", "camera.calibrate-frames"},      # the wall is mirrored: 40 deg off
    "invalid-not-nan": {"camera.frame-units"},
    "stale-frames": {"camera.sequence"},
    # its rays reach 4 km at 1.5 m depth (most miss the tilted wall: behind the camera), and lie along a line
    "focal-in-metres": {"camera.intrinsics", "camera.frame-units", "camera.calibrate-frames"},
    "frame-intrinsics-differ": {"camera.frame-layout", "camera.frame-geometry"},
    "no-vendor": {"camera.info"},
    "ignores-timeout": {"camera.timeout-bounded"},
    "builtin-timeout-error": {"camera.timeout-bounded"},
    "leaks-thread": {"camera.releases-resources"},
    "states-no-model": {"camera.measurement-model"},
    "model-without-source": {"camera.measurement-model"},
    "settings-not-json": {"camera.measurement-model"},
    "frame-model-differs": {"camera.measurement-model"},
    # what only calibrate minded before (issue #37): each passed the other 16 rules
    "tiny-image": {"camera.calibrate-image"},
    "configured-wrong-size": {"camera.calibrate-image"},
    "noise-free": {"camera.calibrate-frames"},
    "states-a-tenth-of-its-noise": {"camera.calibrate-frames"},
    "rows-bottom-up": {"camera.calibrate-frames"},                    # consistent rays, a mirrored wall
}


def test_failure_messages_say_what_was_wrong() -> None:
    def detail(mutation: str, rule: str) -> str:
        report = check_camera(camera_mutant(mutation), TOY_CAMERA_OPTIONS, only=[rule], raise_on_failure=False)
        (failure,) = report.failures
        return failure.detail

    assert "outside the declared 0.1..5 m" in detail("millimetres", "camera.frame-units")
    # the wall's nearest and farthest pixels in millimetres, within 6 sigma of the range noise there (12 mm at
    # 2.1 m): every pixel's ray x = ((u - 79.5) / 150, (v - 59.5) / 150, 1) meets n . x = 1.5 n_z at z = 1.5 n_z / n . x
    n = np.asarray(TOY_SCENE.normal)
    u, v = np.meshgrid((np.arange(160) - 79.5) / 150.0, (np.arange(120) - 59.5) / 150.0)
    rays = np.stack([u, v, np.ones_like(u)], axis=-1)
    d = 1.5 * n[2] / (rays @ n) * np.linalg.norm(rays, axis=-1)
    d[:4, :4] = np.nan                                                       # the invalid corner
    found = re.search(r"\(min ([0-9.]+), max ([0-9.]+); metres expected\)", detail("millimetres", "camera.frame-units"))
    assert found is not None
    assert float(found[1]) == pytest.approx(1000.0 * np.nanmin(d), abs=75.0)
    assert float(found[2]) == pytest.approx(1000.0 * np.nanmax(d), abs=75.0) and 1000.0 * np.nanmax(d) > 2000.0
    assert "|xyz| differs from distance" in detail("depth-not-radial", "camera.frame-units")
    assert "OpenCV camera frame" in detail("y-up", "camera.frame-geometry")
    assert "must increase" in detail("stale-frames", "camera.sequence")
    assert "thread 'toy leak'" in detail("leaks-thread", "camera.releases-resources")
    assert "raised TimeoutError" in detail("builtin-timeout-error", "camera.timeout-bounded")


def test_a_camera_stating_no_model_is_told_how_to_state_one_or_to_opt_out() -> None:
    def detail(mutation: str, options: CameraOptions = TOY_CAMERA_OPTIONS) -> str:
        report = check_camera(camera_mutant(mutation), options, only=["camera.measurement-model"],
                              raise_on_failure=False, quiet=True)
        return report.failures[0].detail if report.failures else ""

    unknown = detail("states-no-model")
    assert unknown.startswith("the camera states no measurement model (kind 'unknown'); override "
                              "Camera3D._measurement_model() to return a MeasurementModel")
    assert "docs/extending.md" in unknown and "CameraOptions(model_unknown_reason='why')" in unknown
    opted_out = CameraOptions(model_unknown_reason="the Z1 cannot report its noise; users state [camera.model]",
                              distance_range_m=(0.1, 5.0))
    assert detail("states-no-model", opted_out) == ""          # the opt-out, with its reason, passes
    assert detail("frame-model-differs", opted_out) != ""      # but frames must still carry the camera's model
    with pytest.raises(CellcalError, match="model_unknown_reason must say why"):
        CameraOptions(model_unknown_reason=" ")
    assert "returned dict, not a MeasurementModel" in detail("returns-a-dict")
    assert "names no source; set source='device'" in detail("model-without-source")
    assert "does not survive a recording" in detail("settings-not-json")
    assert detail("frame-model-differs") == ("frame #0 carries the model 'tof: range sigma 8 mm at 1 m, exponent 1.5, "
                                             "multipath allowance 0 mm (backend)', the camera states 'tof: range "
                                             "sigma 4 mm at 1 m, exponent 1.5, multipath allowance 0 mm (backend)'; "
                                             "a frame must carry the camera's model")


def _detail(mutation: str, rule: str, options: CameraOptions = TOY_CAMERA_OPTIONS) -> str:
    """The failure detail of one rule for a toy mutant ("" when the rule passes)."""
    report = check_camera(camera_mutant(mutation), options, only=[rule], raise_on_failure=False, quiet=True)
    return report.failures[0].detail if report.failures else ""


def test_a_camera_too_small_for_the_default_plan_is_refused_as_calibrate_refuses_it() -> None:
    """The user's 64x48 camera: 15 of 15 rules passed, `cellcal calibrate` refused it (issue #37)."""
    assert _detail("tiny-image", "camera.calibrate-image") == (
        "`cellcal calibrate` with [plan] perimeters_px = [20, 30, 40, 50], window_px = 3 refuses this camera before "
        "the arm moves: perimeters 30, 40, 50 px put the P1-P9 grid with its 3 px sampling windows outside the 64x48 "
        "image (at most 22.5 px from the principal point (31.5, 23.5) px); use perimeters_px of at most 22 px")
    # a camera whose cells use smaller perimeters says so, and passes; 23 px is past the 22.5 px it can hold
    assert _detail("tiny-image", "camera.calibrate-image",
                   dataclasses.replace(TOY_CAMERA_OPTIONS, perimeters_px=(10, 22))) == ""
    assert "perimeter 23 px puts the P1-P9 grid" in _detail(
        "tiny-image", "camera.calibrate-image", dataclasses.replace(TOY_CAMERA_OPTIONS, perimeters_px=(10, 23)))
    assert _detail("configured-wrong-size", "camera.calibrate-image") == (
        "configured_intrinsics() before connect() says a 224x172 image centred at (111.5, 85.5) px, the connected "
        "camera a 160x120 image centred at (79.5, 59.5) px; `calibrate --check` would judge the plan on the wrong "
        "image")


FRAME_REFUSAL = "`cellcal calibrate` with the default [full_frame] gates refuses frame #0 of the test scene: "


def test_frames_calibrate_would_refuse_fail_the_kit_with_calibrates_words() -> None:
    """The noise gates against the stated model, and the plane where the vendor says it is (issue #37)."""
    noise_free = _detail("noise-free", "camera.calibrate-frames")
    assert noise_free.startswith(FRAME_REFUSAL + "quality gate 'residual_floor' failed: ")
    assert "x the 7.61 mm the sensor can deliver for these pixels (quantisation floor 0 mm), below the minimum of " \
           "0.25 x" in noise_free
    assert noise_free.endswith("the frames are less noisy than the camera's measurement model says: state the noise "
                               "it has (docs/extending.md, 'Stating how the camera measures')")
    loud = _detail("states-a-tenth-of-its-noise", "camera.calibrate-frames")
    assert loud.startswith(FRAME_REFUSAL + "quality gate 'residual_rms_m' failed: ")
    assert "the frames are noisier than the camera's measurement model says" in loud
    # rows read out bottom-up: every xyz lies on its pixel's ray (camera.frame-geometry passes), but the wall
    # tilted +20 deg is seen at -20 deg: 40 deg from the declared plane, past the default 15 deg
    mirrored = _detail("rows-bottom-up", "camera.calibrate-frames")
    assert mirrored.startswith(FRAME_REFUSAL + "quality gate 'expected_plane' failed: 40.0")
    assert " deg vs threshold 15 deg; the fitted plane is 40 deg from the expected one, 25 deg beyond the tolerance " \
           "of 15 deg (its offset, " in mirrored
    assert "an image read out upside down mirrors every plane" in mirrored
    assert _detail("millimetres", "camera.calibrate-frames").startswith(
        FRAME_REFUSAL + "the median range of the valid pixels is 15")


def test_the_frames_rule_needs_the_scene_declared_or_a_reason() -> None:
    undeclared = CameraOptions(distance_range_m=(0.1, 5.0), **FAST)
    assert _detail("", "camera.calibrate-frames", undeclared).startswith(
        "the kit cannot run calibrate's full-frame fit on this camera's frames without knowing its test scene: point "
        "the camera at a flat surface filling the image and declare it, e.g. CameraOptions(scene_plane=ScenePlane(")
    reason = dataclasses.replace(undeclared, scene_reason="the mocked SDK sends one depth for every pixel")
    assert _detail("noise-free", "camera.calibrate-frames", reason) == ""        # not run, with its reason
    # a plane declared 20 deg off the wall the toy sees: within 15 deg of it? no, of the declared one: refused
    off = ScenePlane(normal=(0.0, 0.0, 1.0), axis_distance_m=1.5)
    assert "quality gate 'expected_plane' failed: 20" in _detail(
        "", "camera.calibrate-frames", dataclasses.replace(undeclared, scene_plane=off))
    with pytest.raises(CellcalError, match="scene_reason must say why"):
        CameraOptions(scene_reason="")
    with pytest.raises(CellcalError, match="scene_plane must be a ScenePlane"):
        CameraOptions(scene_plane=((0.0, 0.0, 1.0), 1.5))  # type: ignore[arg-type]
    with pytest.raises(CellcalError, match="perimeters_px must be positive"):
        CameraOptions(perimeters_px=(20, 0))
    with pytest.raises(CellcalError, match="axis_distance_m must be a positive number of metres"):
        ScenePlane(normal=(0.0, 0.0, 1.0), axis_distance_m=-1.0)
    with pytest.raises(CellcalError, match="the axis never meets the plane"):
        ScenePlane(normal=(1.0, 0.0, 0.0), axis_distance_m=1.0)
    with pytest.raises(CellcalError, match="finite, non-zero 3-vector"):
        ScenePlane(normal=(0.0, 0.0, 0.0), axis_distance_m=1.0)


def test_bypassed_life_cycle_is_caught() -> None:
    report = check_camera(BypassingCamera, TOY_CAMERA_OPTIONS, raise_on_failure=False)
    # ... and the frames it hands out skip the stamping of the camera's model
    assert {r.rule for r in report.failures} == {"camera.not-connected", "camera.use-after-close",
                                                 "camera.timeout-validation", "camera.measurement-model"}
    (nc,) = [r for r in report.failures if r.rule == "camera.not-connected"]
    assert nc.detail == "capture() before connect() did not raise NotConnectedError"


def test_conformance_error_lists_every_failed_rule() -> None:
    with pytest.raises(ConformanceError) as err:
        check_camera(camera_mutant("frame-intrinsics-differ"), TOY_CAMERA_OPTIONS)
    lines = str(err.value).splitlines()
    assert lines[0] == "toy-cam: 2 of 17 camera contract checks failed"
    assert [line.split(" contract rule ")[1].split()[0] for line in lines[1:]] == ["camera.frame-layout",
                                                                                    "camera.frame-geometry"]
    assert isinstance(err.value, AssertionError) and isinstance(err.value, CellcalError)
    assert len(err.value.failures) == 2


# ---------------------------------------------------------------- a correct arm, and mutants
class ToyArm(RobotArm):
    """A 5-joint arm that arrives instantly wherever it is sent."""

    backend_name = "toy-arm"
    mutation: ClassVar[str] = ""

    @dataclass(frozen=True)
    class Config:
        speed_limit_m_s: float = 1.0

    def __init__(self, config: Any = None, context: BackendContext | None = None):
        super().__init__()
        self.config = config or self.Config()
        self._pose = Pose.from_xyz_rpy([0.3, 0.0, 0.4], [math.pi, 0.0, 0.0])
        self._stopped = False
        self.moves: list[Pose] = []
        self.stops = 0

    def _connect(self, timeout: float) -> None:
        if self.mutation == "leaks-thread":
            _leak_thread()

    def _close(self) -> None:
        pass

    def _info(self) -> DeviceInfo:
        return DeviceInfo(backend="toy-arm", vendor="Toy", model="A5")

    def _get_pose(self, timeout: float) -> Pose:
        if self.mutation == "ignores-timeout" and timeout < 1.0:
            time.sleep(0.5)
        p = self._pose
        if self.mutation == "millimetres":
            return Pose(p.rotation, p.translation * 1000.0)
        if self.mutation == "degrees":  # converted to degrees for the wire, never back
            return Pose(Rotation.from_euler("xyz", np.degrees(p.rotation.as_euler("xyz"))), p.translation)
        return p

    def _move_linear(self, pose: Pose, speed: float, acceleration: float, timeout: float) -> None:
        if self.mutation == "stops-short":  # 70 mm before the target along the path, and says it is done
            step = pose.translation - self._pose.translation
            pose = Pose(pose.rotation, pose.translation - SHORTFALL_M * step / max(np.linalg.norm(step), 1e-12))
        self._pose = pose
        self._stopped = False
        self.moves.append(pose)

    def _stop(self, timeout: float) -> None:
        if self.mutation == "stop-twice-fails" and self._stopped:
            raise VendorError("toy", 9, "already stopped")
        self._stopped = True
        self.stops += 1

    def _joint_positions(self, timeout: float) -> NDArray[np.float64]:
        q = np.array([0.0, -1.0, 1.2, 0.3, 2.0])
        return np.degrees(q) if self.mutation == "joints-in-degrees" else q

    def _status(self, timeout: float) -> ArmStatus:
        if self.mutation == "stuck-in-error":
            return ArmStatus(error_code=3, message="protective stop", can_move=False)
        return ArmStatus()

    def _clear_errors(self, timeout: float) -> None:
        pass


class UncheckedMoveArm(ToyArm):
    """Overrides the public move_linear() and skips every check the base class does."""

    def move_linear(self, pose: Pose, *, speed: float, acceleration: float, timeout: float | None = None) -> None:
        if isinstance(pose, Pose):
            self._move_linear(pose, speed, acceleration, 1.0)


class UncheckedShortArm(UncheckedMoveArm):
    """Stops 70 mm short and, skipping the base class's arrival check, says nothing."""

    mutation = "stops-short"


def arm_mutant(mutation: str) -> type[ToyArm]:
    return type(f"ToyArm_{mutation}", (ToyArm,), {"mutation": mutation})


TOY_ARM_OPTIONS = ArmOptions(joint_count=5, **FAST)
SHORTFALL_M = 0.07


def test_correct_toy_arm_passes_every_rule() -> None:
    report = check_arm(ToyArm, TOY_ARM_OPTIONS)
    assert report.ok and report.backend == "toy-arm"
    assert [r.rule for r in report.results] == list(ARM_RULES) and len(ARM_RULES) == 16


ARM_MUTANTS = {
    "millimetres": {"arm.pose-units", "arm.pose-round-trip", "arm.arrival"},  # reads back 1000x off the target
    "degrees": {"arm.pose-round-trip", "arm.arrival"},
    "stops-short": {"arm.pose-round-trip", "arm.arrival"},
    "joints-in-degrees": {"arm.joint-positions"},
    "stop-twice-fails": {"arm.stop-idempotent"},
    "stuck-in-error": {"arm.status", "arm.stop-idempotent"},
    "ignores-timeout": {"arm.timeout-bounded"},
    "leaks-thread": {"arm.releases-resources"},
}


MUTANTS = [("camera", m, rules) for m, rules in CAMERA_MUTANTS.items()] + [
    ("arm", m, rules) for m, rules in ARM_MUTANTS.items()]


@pytest.mark.parametrize(("kind", "mutation", "failing"), MUTANTS, ids=[f"{k}-{m}" for k, m, _ in MUTANTS])
def test_mutant_fails_exactly_its_rules(kind: str, mutation: str, failing: set[str]) -> None:
    if kind == "camera":
        report = check_camera(camera_mutant(mutation), TOY_CAMERA_OPTIONS, raise_on_failure=False)
    else:
        report = check_arm(arm_mutant(mutation), TOY_ARM_OPTIONS, raise_on_failure=False)
    assert {r.rule for r in report.failures} == failing
    for r in report.failures:
        assert r.message.startswith(f"toy-{kind[:3]}: contract rule {r.rule} (")


def test_arm_in_degrees_fails_the_round_trip_by_the_right_amount() -> None:
    report = check_arm(arm_mutant("degrees"), TOY_ARM_OPTIONS, only=["arm.pose-round-trip"], raise_on_failure=False)
    (failure,) = report.failures
    # the base class's arrival check reads the pose back in "radians" that are degrees: off by 57.3x
    assert failure.detail.startswith("unexpected MotionError: toy-arm: move to ") and "reported done" in failure.detail
    assert "is 0.000 mm and" in failure.detail and "the arm was told to stop" in failure.detail


def test_arm_that_stops_short_fails_the_arrival_rule() -> None:
    report = check_arm(arm_mutant("stops-short"), TOY_ARM_OPTIONS, only=["arm.arrival"], raise_on_failure=False)
    (failure,) = report.failures
    assert failure.detail.startswith("move_linear to a reachable target raised MotionError: toy-arm: move to ")
    assert "is 70.000 mm and 0.0000 deg from the target (tolerance 1 mm / 0.1 deg)" in failure.detail
    # bypassing the base class's check does not help: the kit reads the pose back itself
    report = check_arm(UncheckedShortArm, TOY_ARM_OPTIONS, only=["arm.arrival"], raise_on_failure=False)
    (failure,) = report.failures
    assert failure.detail == ("move_linear returned, but pose read 1 is 70 mm and 0 deg from the target: "
                              "it reported an arrival that did not happen")


def test_arrival_rule_fakes_a_short_move_and_wants_a_stop() -> None:
    arms: list[ToyArm] = []

    def factory() -> ToyArm:
        arms.append(ToyArm())
        return arms[-1]

    assert check_arm(factory, TOY_ARM_OPTIONS, only=["arm.arrival"]).ok
    (arm,) = arms
    step = np.linalg.norm(TOY_ARM_OPTIONS.step_m)
    # there, back, there again (read back 70 mm off: MotionError, stopped), back: every move at most one step
    assert len(arm.moves) == 4 and arm.stops == 1
    assert [round(float(np.linalg.norm(b.translation - a.translation)), 9) for a, b in
            zip(arm.moves, arm.moves[1:], strict=False)] == [step] * 3
    assert "_get_pose" not in vars(arm) and "_stop" not in vars(arm)  # the arm's own hooks are back


def test_unchecked_move_is_caught() -> None:
    report = check_arm(UncheckedMoveArm, TOY_ARM_OPTIONS, raise_on_failure=False)
    assert {r.rule for r in report.failures} == {"arm.not-connected", "arm.use-after-close",
                                                 "arm.argument-validation", "arm.timeout-validation", "arm.arrival"}
    (arrival,) = [r for r in report.failures if r.rule == "arm.arrival"]
    assert arrival.detail == "move_linear whose pose reads back 70 mm off the target did not raise MotionError"


def test_joint_count_is_checked_when_declared() -> None:
    report = check_arm(ToyArm, ArmOptions(joint_count=6, **FAST), only=["arm.joint-positions"],
                       raise_on_failure=False)
    assert report.failures[0].detail == "joint_positions() has 5 values, the arm has 6 joints"


# ---------------------------------------------------------------- API edges
def test_bad_arguments_to_the_kit() -> None:
    with pytest.raises(CellcalError, match="needs a factory"):
        check_camera(ToyCamera(), TOY_CAMERA_OPTIONS)  # type: ignore[arg-type]
    with pytest.raises(CellcalError, match=r"unknown camera contract rule.*camera\.nope"):
        check_camera(ToyCamera, only=["camera.nope"])
    with pytest.raises(CellcalError, match="distance_range_m"):
        CameraOptions(distance_range_m=(2.0, 1.0))
    with pytest.raises(CellcalError, match=r"ArmOptions\.speed_m_s"):
        ArmOptions(speed_m_s=0.0)
    with pytest.raises(CellcalError, match=r"CameraOptions\.short_timeout_s"):
        CameraOptions(short_timeout_s=math.nan)
    report = check_arm(arm_mutant("millimetres"), TOY_ARM_OPTIONS, raise_on_failure=False)
    assert {r.rule for r in check_arm(ToyArm, TOY_ARM_OPTIONS, only=["arm.pose-units"]).results} == {"arm.pose-units"}
    assert "FAIL arm.pose-units: flange at 500 from the base origin" in str(report)


def test_a_factory_returning_the_wrong_thing_fails_every_rule() -> None:
    report = check_camera(lambda: ToyArm(), raise_on_failure=False)  # type: ignore[arg-type, return-value]
    assert not report.results[0].passed
    assert all("the factory returned ToyArm, not a Camera3D subclass" in r.detail for r in report.failures)
    assert len(report.failures) == len(CAMERA_RULES)


def test_function_api_works_without_pytest() -> None:
    code = (
        "import sys; sys.modules['pytest'] = None\n"
        "import cellcal.testing as kit\n"
        "assert 'pytest' not in [m for m in sys.modules if sys.modules[m] is not None]\n"
        "import tomllib; from importlib import resources\n"
        "from cellcal.devices import default_registry, BackendContext\n"
        "doc = tomllib.loads(resources.files('cellcal.configs').joinpath('sim.toml').read_text())\n"
        "r = kit.check_camera(lambda: default_registry().create_camera({'backend': 'sim'},"
        " BackendContext(section='camera', document=doc)), kit.CameraOptions(distance_range_m=(0.1, 4.0),"
        " scene_plane=kit.ScenePlane(normal=(0.0, 0.0, 1.0), axis_distance_m=0.44)))\n"
        "print(r.backend, len(r.results), r.ok)\n"
        "try:\n    kit.CameraConformance\nexcept ImportError as e:\n    print('classes need pytest')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split("\n")[:2] == ["sim 17 True", "classes need pytest"]
