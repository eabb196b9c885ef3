"""Safety properties of the calibrator over random plans, configurations and arm states.

The code under test is the calibrator with its :class:`SafeArm`; the backend is a
recording arm that moves instantly and keeps every command it receives. Each
example draws a workspace box, speed/acceleration limits, a standoff, a reference
plane of any tilt, an explicit plan, the commanded speed/acceleration, the arm's
start pose and its error state, and checks:

* nothing reaches the backend from an arm in an error state (VendorError first);
* every command that reaches the backend is inside the envelope, re-checked here
  independently along a dense sampling of the path (flange and camera in the box,
  camera at least the standoff above the plane, speed and acceleration within their
  maxima);
* a plan whose moves would leave the envelope is rejected before the first command,
  with a SafetyError naming an offending plan pose (1-based).

Paths whose closest approach to a limit is within ``MARGIN_M`` are skipped (the
envelope samples the path at >= 16 points, so the camera's arc between samples may
lie up to ~3e-5 m beyond them); commands are only accepted by the independent check
with the same tolerance.
"""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np
from fault_cells import cell_document
from hypothesis import HealthCheck, Phase, assume, event, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation, Slerp
from test_safety import RecordingArm

from cellcal.core.calibration.calibrator import Calibrator
from cellcal.core.calibration.config import CellConfig, parse_config, plan_flange_poses
from cellcal.devices import Pose
from cellcal.devices.base import BackendContext
from cellcal.devices.errors import CellcalError, SafetyError, VendorError
from cellcal.devices.safety import SafeArm
from cellcal.sims.camera import SimCamera, SimCameraConfig

MARGIN_M = 1e-4
SAMPLES = 401


def margin(config: CellConfig, start: Pose | None, target: Pose, speed: float, acc: float) -> float:
    """Independent check of one move: the smallest slack to any limit, metres (< 0: violated).

    Speed and acceleration violations count as -1 (no tolerance applies to them).
    """
    s = config.safety
    if speed > s.max_speed_m_s or acc > s.max_acceleration_m_s2:
        return -1.0
    mount = config.mount.pose()
    t = np.linspace(0.0, 1.0, SAMPLES if start is not None else 1)
    if start is None:
        rots = Rotation.concatenate([target.rotation])
        flange = target.translation[None, :]
    else:
        rots = Slerp([0.0, 1.0], Rotation.concatenate([start.rotation, target.rotation]))(t)
        flange = start.translation + t[:, None] * (target.translation - start.translation)
    camera = flange + rots.apply(np.array(mount.translation))  # scipy rejects read-only input
    lo, hi = np.asarray(s.workspace_min_m), np.asarray(s.workspace_max_m)
    slack = min(float(np.min(p - lo)) for p in (flange, camera))
    slack = min(slack, min(float(np.min(hi - p)) for p in (flange, camera)))
    if config.reference is not None:
        n = np.asarray(config.reference.plane_normal, float)
        d = (camera - np.asarray(config.reference.plane_point_m)) @ (n / np.linalg.norm(n))
        slack = min(slack, float(np.min(d)) - s.min_standoff_m)
    return slack


vec = st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1))


@st.composite
def scenarios(draw: st.DrawFn) -> tuple[dict[str, Any], Pose, int]:
    """A cell, a start pose and an error code; about half the plans are meant to be safe."""
    wild = draw(st.booleans())  # False: poses well inside the box, speeds within the limits
    centre = np.array([draw(st.floats(0.1, 0.5)), draw(st.floats(-0.3, 0.3)), draw(st.floats(0.45, 0.7))])
    half = np.array([draw(st.floats(0.15, 0.5)) for _ in range(3)])
    tilt_axis = np.array(draw(vec)) + 1e-3
    tilt = Rotation.from_rotvec(tilt_axis / np.linalg.norm(tilt_axis)
                                * math.radians(draw(st.floats(0, 40 if wild else 15))))
    normal = tilt.apply([0.0, 0.0, 1.0])
    reach = half + 0.15 if wild else half - 0.12  # the camera hangs up to ~0.11 m off the flange

    def pose(d: st.DrawFn) -> Pose:
        xyz = centre + np.array(d(vec)) * reach
        rv = np.array(d(vec)) * (0.5 if wild else 0.3)
        return Pose(Rotation.from_rotvec(rv) * Rotation.from_euler("x", math.pi), xyz)

    plan = [pose(draw) for _ in range(draw(st.integers(1, 4)))]
    start = pose(draw)
    max_speed, max_acc = draw(st.floats(0.05, 1.0)), draw(st.floats(0.2, 5.0))
    speed = draw(st.floats(0.01, 1.2)) if wild else max_speed * draw(st.floats(0.1, 1.0))
    acc = draw(st.floats(0.1, 6.0)) if wild else max_acc * draw(st.floats(0.1, 1.0))
    doc = cell_document(
        safety={"workspace_min_m": (centre - half).tolist(), "workspace_max_m": (centre + half).tolist(),
                "max_speed_m_s": max_speed, "max_acceleration_m_s2": max_acc,
                "min_standoff_m": draw(st.floats(0.0, 0.4 if wild else 0.15))},
        reference={"plane_point_m": [0.0, 0.0, draw(st.floats(-0.1, 0.1))], "plane_normal": normal.tolist()},
        plan={"speed_m_s": speed, "acceleration_m_s2": acc,
              "poses": [{"xyz_m": p.translation.tolist(),
                         "rpy_deg": np.degrees(p.rotation.as_euler("xyz")).tolist()} for p in plan]},
        mount={"translation_m": [0.0, draw(st.floats(-0.05, 0.05)), draw(st.floats(0.0, 0.1))],
               "rpy_deg": [0.0, 0.0, draw(st.floats(-180, 180))]},
    )
    error = draw(st.sampled_from([0, 31]))
    return doc, start, error


#: No "explain" phase: it re-runs a failure thousands of times (minutes) to annotate it.
PHASES = (Phase.explicit, Phase.reuse, Phase.generate, Phase.target, Phase.shrink)
CAMERA_CONFIG = SimCameraConfig(noise=False, distortion=False, width=64, height=48)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow], phases=PHASES)
@given(scenario=scenarios())
def test_nothing_outside_the_envelope_reaches_the_backend(scenario: tuple[dict[str, Any], Pose, int]) -> None:
    doc, start, error = scenario
    config = parse_config(copy.deepcopy(doc), "<hypothesis>")
    poses = plan_flange_poses(config)
    plan = config.plan
    slack = [margin(config, start if i == 0 else poses[i - 1], p, plan.speed_m_s, plan.acceleration_m_s2)
             for i, p in enumerate(poses)]
    assume(all(abs(m) > MARGIN_M for m in slack))  # no borderline path
    offending = {i + 1 for i, m in enumerate(slack) if m < 0}

    inner = RecordingArm(start, error)
    camera = SimCamera(CAMERA_CONFIG, BackendContext(document={"sim": {}}))
    # the camera rides on the recording arm (one that stays put is refused, gate view_follows_arm)
    camera.fault_hook = lambda _event, _n: camera.world.arm.set_flange_pose(inner.pose)
    calibrator = Calibrator(config, camera, SafeArm(inner, config.safety_limits()))
    try:
        calibrator.run()
        outcome: CellcalError | None = None
    except CellcalError as exc:
        outcome = exc

    event("rejected plan" if offending else "arm in error" if error else "safe plan")
    previous = start
    for pose, speed, acc in inner.commands:  # whatever happened, every command was inside
        assert margin(config, previous, pose, speed, acc) > -MARGIN_M, f"unsafe command reached the backend: {pose}"
        previous = pose
    if error and isinstance(outcome, VendorError):  # the arm's error is reported before the path check
        assert outcome.code == error and inner.commands == []
    elif offending:
        assert isinstance(outcome, SafetyError), outcome
        assert inner.commands == []  # rejected before the first move
        named = int(str(outcome).split("plan pose ")[1].split(" ")[0])
        assert named in offending, (str(outcome), offending)
    elif error:
        raise AssertionError(f"an arm in error state was not refused: {outcome!r}")
    else:
        assert not isinstance(outcome, SafetyError), outcome
        assert len(inner.commands) == len(poses)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow], phases=PHASES)
@given(scenario=scenarios())
def test_every_violating_plan_names_its_pose_in_one_line(scenario: tuple[dict[str, Any], Pose, int]) -> None:
    doc, start, _error = scenario
    config = parse_config(copy.deepcopy(doc), "<hypothesis>")
    poses = plan_flange_poses(config)
    plan = config.plan
    target_only = [margin(config, None, p, plan.speed_m_s, plan.acceleration_m_s2) for p in poses]
    assume(all(abs(m) > MARGIN_M for m in target_only))
    calibrator = Calibrator(config, SimCamera(CAMERA_CONFIG), SafeArm(RecordingArm(start), config.safety_limits()))
    bad = [i + 1 for i, m in enumerate(target_only) if m < 0]
    if not bad:
        calibrator.check_plan(None)
        return
    try:
        calibrator.check_plan(None)
    except SafetyError as exc:
        text = str(exc)
        assert "\n" not in text and text.startswith(f"plan pose {bad[0]} (xyz=(")
    else:
        raise AssertionError(f"plan with offending poses {bad} was accepted")
