"""Coverage of the hand-eye 95 % mount intervals on the sim with the arm's kinematic errors on (issue #39).

Complete simulated runs of ``configs/sim_handeye.toml`` (auto plan, one frame per pose): for every
seed a different arm, its joint zero offsets and link length errors drawn at the default
magnitude of ``[sim.arm_errors]`` (:func:`cellcal.sims.kinematics.random_arm_errors`: 0.025 deg and
0.3 mm per joint and link, 1-sigma), and the camera's systematic error off (``[sim.systematic]
enabled = false``) so that the arm is the only systematic error. The poses are measured once and
the mount estimated twice from the same planes:

* **with the arm term**: the arm's stated accuracy (the sim arm states the RMS of its errors over the
  workspace, :meth:`cellcal.sims.arm.SimArm.arm_model`) in the weights and intervals (ADR 0055):
  common to the poses, half of it in step with the pose (``ArmAccuracy.trend``), a quarter at random;
* **random only**: the same accuracy without the trend, half of it at random per pose (as before the
  trend);
* **without**: the read-back noise of ``[handeye]`` alone, as before issue #39.

It prints how often each ``[mount]`` value's 95 % interval holds the true mount ``[sim.mount]``,
pooled, and chi2/dof. Target (issue #39): 90-98 % with the arm term, every value.

It also prints where the sim arms' errors lie, per flange axis, over each run's poses, against
the stated per-axis accuracy (RMS / sqrt 3): the part common to the poses in the flange frame
(what the mount absorbs) and the part that varies. A stated accuracy is isotropic, as vendors
state it; the sim's five-axis chain errs in common only along and about the flange's z axis, so
the common part the intervals allow for tx, ty, roll and pitch is not there, and those values are
covered more often than 98 %: the bound of an isotropic statement, which only a kinematic model
of the arm (its joint zeros and link lengths as parameters) would lift.

``--camera`` puts the camera's systematic error on as well (ADR 0059 "Amended"): ``default``, the
sim's default errors (the same for every seed); ``drawn``, per seed a ToF range scale, offset and
radial bow drawn at the camera's stated allowance (1-sigma 0.2 %, 5 mm, 2 mm at the corner) and the
sim's wiggle at a random phase. The estimate is then made three ways from the same planes: as it
is (each pose weighed by its fit's noise, the allowance a common term), without the common term
(noise weights, the allowance left out), and as before the split (the allowance as per-pose noise).
The mean 95 % half-widths are printed.

``--wiggle-mm`` sets the ToF wiggle's amplitude (the sim's 1 mm at a period of 0.62 m is a local
range scale of up to 1 %, five times the scale allowance: outside what the intervals allow for);
``--ideal-arm`` turns the arm's kinematic errors off, leaving the camera's alone.

Usage: python benchmarks/handeye_arm_errors.py [--seeds N] [--first S] [--camera ideal|default|drawn]
[--wiggle-mm A] [--ideal-arm]
"""

from __future__ import annotations

import argparse
import copy
import tempfile
import time
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from cellcal.core.calibration.calibrator import build_devices
from cellcal.core.calibration.config import parse_config
from cellcal.core.handeye import auto_plan, estimate_from_document, plan_calibrator
from cellcal.core.handeye.estimator import HandEyeEstimate
from cellcal.devices.errors import CalibrationQualityError
from cellcal.devices.measurement import DEFAULT_ALLOWANCES
from cellcal.devices.pose import Pose
from cellcal.sims.kinematics import random_arm_errors

CONFIG = Path(str(resources.files("cellcal.configs"))) / "sim_handeye.toml"
VALUES = ("tx", "ty", "tz", "roll", "pitch", "yaw")
TARGET = (0.90, 0.98)


def camera_errors(camera: str, seed: int, wiggle_m: float | None = None) -> dict[str, Any]:
    """The ``[sim.systematic]`` table of ``camera`` (``ideal``, ``default`` or ``drawn``) for ``seed``.

    ``wiggle_m``: the ToF wiggle's amplitude (None: the sim's default, 1 mm).
    """
    if camera == "ideal":
        return {"enabled": False}
    wiggle = {} if wiggle_m is None else {"wiggle_amplitude_m": wiggle_m}
    if camera == "default":
        return {"enabled": True, **wiggle}
    rng = np.random.default_rng([59, seed])
    scale, offset, bow = DEFAULT_ALLOWANCES["tof"]
    return {"enabled": True, "range_scale_error": float(rng.normal(0.0, scale)),
            "range_offset_m": float(rng.normal(0.0, offset)), "range_bow_m": float(rng.normal(0.0, bow)),
            "wiggle_phase_deg": float(rng.uniform(-180.0, 180.0)), **wiggle}


def cell(seed: int, camera: str = "ideal", wiggle_m: float | None = None, arm: bool = True
         ) -> tuple[Any, dict[str, Any]]:
    """The hand-eye sim cell of ``seed``: its own arm errors, the camera's errors, one frame per pose."""
    document = tomllib.loads(CONFIG.read_text())
    document["cell"]["seed"] = seed
    document["plan"]["frames_per_pose"] = 1
    errors = random_arm_errors(np.random.default_rng([39, seed]))
    document["sim"]["arm_errors"] = {"enabled": True, "joint_offsets_deg": list(errors.joint_offsets_deg),
                                     "link_errors_mm": list(errors.link_errors_mm)} if arm else {"enabled": False}
    document["sim"]["systematic"] = camera_errors(camera, seed, wiggle_m)
    return parse_config(document, str(CONFIG)), document


def variant(measured: dict[str, Any], keep_split: bool, keep_shifts: bool) -> dict[str, Any]:
    """The measured document without the noise/systematic split or without the shifts."""
    out = copy.deepcopy(measured)
    for pose in out["poses"]:
        ff = pose.get("full_frame") or {}
        if not keep_shifts:
            ff.pop("systematic_shifts", None)
        if not keep_split:
            for key in ("noise_normal_covariance", "noise_offset_sigma_m", "noise_normal_offset_covariance"):
                ff.pop(key, None)
    return out


def half_widths(estimate: HandEyeEstimate) -> np.ndarray:
    """95 % half-widths of the six mount values (mm, mm, mm, deg, deg, deg)."""
    _, rpy_sigma = estimate.rpy_and_sigma_deg()
    return estimate.z * np.concatenate([1000 * estimate.translation_sigma_m, rpy_sigma])


def inside(estimate: HandEyeEstimate, truth: Pose) -> np.ndarray:
    """Whether each mount value's interval holds the truth (6,)."""
    t, t_sigma = estimate.mount.translation, estimate.translation_sigma_m
    rpy, rpy_sigma = estimate.rpy_and_sigma_deg()
    true_rpy = np.degrees(truth.as_xyz_rpy()[3:])
    d_rpy = (rpy - true_rpy + 180.0) % 360.0 - 180.0
    z = estimate.z
    return np.concatenate([np.abs(t - truth.translation) <= z * t_sigma, np.abs(d_rpy) <= z * rpy_sigma])


def percent(values: np.ndarray) -> str:
    return " ".join(f"{name} {100 * v:5.1f}" for name, v in zip(VALUES, values, strict=True))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=100, help="simulated runs, one arm each (default 100)")
    parser.add_argument("--first", type=int, default=0, help="first seed")
    parser.add_argument("--camera", choices=("ideal", "default", "drawn"), default="ideal",
                        help="the camera's systematic error: none (default), the sim's defaults, drawn per seed")
    parser.add_argument("--wiggle-mm", type=float, default=None,
                        help="with --camera: the ToF wiggle's amplitude, mm (default: the sim's 1 mm)")
    parser.add_argument("--ideal-arm", action="store_true", help="with --camera: the arm without kinematic errors")
    args = parser.parse_args()
    if args.camera != "ideal":
        camera_benchmark(args)
        return
    with_arm, random_only, without, chi2_with, chi2_without, arm_errors = [], [], [], [], [], []
    common_f, varying_f = [], []
    started = time.perf_counter()
    for seed in range(args.first, args.first + args.seeds):
        config, document = cell(seed)
        truth_table = document["sim"]["mount"]
        truth = Pose.from_xyz_rpy(np.asarray(truth_table["translation_m"]), np.radians(truth_table["rpy_deg"]))
        camera, arm = build_devices(config)
        with tempfile.TemporaryDirectory():
            measured = plan_calibrator(config, camera, arm, auto_plan(config)).run()
        model = arm.arm_model()
        arm_errors.append((model.accuracy_m, model.accuracy_rad))
        est = estimate_from_document(config, measured, model)
        before = estimate_from_document(config, measured, None)
        random_only.append(inside(estimate_with(config, measured, model, trend=0.0, varying=0.5), truth))
        common, varying = flange_error_parts(measured, arm.inner.world.arm_errors, model)
        common_f.append(common)
        varying_f.append(varying)
        with_arm.append(inside(est, truth))
        without.append(inside(before, truth))
        chi2_with.append(est.chi2 / est.dof)
        chi2_without.append(before.chi2 / before.dof)
    wall = time.perf_counter() - started
    w, wo = np.mean(with_arm, axis=0), np.mean(without, axis=0)
    acc = np.array(arm_errors)
    print(f"{args.seeds} seeds ({wall:.0f} s), one arm each: RMS kinematic error median "
          f"{1000 * np.median(acc[:, 0]):.2f} mm, {np.degrees(np.median(acc[:, 1])):.3f} deg "
          f"(range {1000 * acc[:, 0].min():.2f}-{1000 * acc[:, 0].max():.2f} mm)")
    ok = bool(np.all((w >= TARGET[0]) & (w <= TARGET[1])))
    print(f"  with the arm term:    {percent(w)} %  (pooled {100 * w.mean():.1f} %); chi2/dof median "
          f"{np.median(chi2_with):.2f}  target {100 * TARGET[0]:.0f}-{100 * TARGET[1]:.0f} %: "
          f"{'PASS' if ok else 'FAIL'}")
    ro = np.mean(random_only, axis=0)
    print(f"  random only (no trend): {percent(ro)} %  (pooled {100 * ro.mean():.1f} %)")
    print(f"  without (as before):  {percent(wo)} %  (pooled {100 * wo.mean():.1f} %); chi2/dof median "
          f"{np.median(chi2_without):.2f}")
    rms = lambda a: np.sqrt(np.mean(np.square(a), axis=0))  # noqa: E731
    axes = ("x", "y", "z", "rx", "ry", "rz")
    print("  the sim arms' flange errors over the poses, RMS over the seeds in units of the stated per-axis accuracy:")
    print("    common (flange frame): " + " ".join(f"{a} {v:.2f}" for a, v in zip(axes, rms(common_f), strict=True)))
    print("    varying:               " + " ".join(f"{a} {v:.2f}" for a, v in zip(axes, rms(varying_f), strict=True)))


def estimate_with(config: Any, measured: dict[str, Any], model: Any, *, trend: float, varying: float
                  ) -> HandEyeEstimate:
    """The plane estimate with the arm's accuracy split otherwise than the default (``ArmAccuracy``)."""
    import dataclasses
    import math

    from cellcal.core.handeye.estimator import estimate_mount
    from cellcal.core.handeye.model import observation_from_pose
    from cellcal.core.handeye.run import arm_accuracy, reference_plane

    he = config.handeye
    accuracy = arm_accuracy(model)
    accuracy = None if accuracy is None else dataclasses.replace(accuracy, trend=trend, varying=varying)
    return estimate_mount([observation_from_pose(p) for p in measured["poses"]], config.mount.pose(),
                          reference_plane(config), given=he.given, given_sigma=he.given_sigma,
                          arm_translation_sigma_m=he.arm_translation_sigma_m,
                          arm_rotation_sigma_rad=math.radians(he.arm_rotation_sigma_deg), confidence=he.confidence,
                          noise_test_level=he.noise_test_level, max_interval_scale=he.max_interval_scale,
                          arm_accuracy=accuracy)


def flange_error_parts(measured: dict[str, Any], errors: Any, model: Any) -> tuple[np.ndarray, np.ndarray]:
    """(6,) each: the flange-frame error's mean over the poses and its spread (x, y, z, rx, ry, rz), per-axis units.

    The unit is the stated accuracy per axis (``accuracy / sqrt 3``, position and rotation apart).
    """
    from scipy.spatial.transform import Rotation

    parts = []
    for pose in measured["poses"]:
        reported = Pose.from_dict(pose["reported_flange_pose"])
        d = reported.inv() @ errors.true_pose(reported)  # the true flange seen from the reported one
        parts.append(np.concatenate([np.asarray(d.translation), Rotation.from_matrix(d.rotation_matrix).as_rotvec()]))
    e = np.array(parts)
    unit = np.array([model.accuracy_m] * 3 + [model.accuracy_rad] * 3) / np.sqrt(3.0)
    return np.abs(e.mean(axis=0)) / unit, e.std(axis=0) / unit


def camera_benchmark(args: argparse.Namespace) -> None:
    """Coverage with the camera's systematic error on: the common term, without it, and as before the split."""
    ways = {"common term (as it is)": (True, True), "noise weights, no common term": (True, False),
            "allowance as per-pose noise (before)": (False, False)}
    inside_of: dict[str, list[np.ndarray]] = {k: [] for k in ways}
    chi2_of: dict[str, list[float]] = {k: [] for k in ways}
    width_of: dict[str, list[np.ndarray]] = {k: [] for k in ways}
    refused = dict.fromkeys(ways, 0)
    started = time.perf_counter()
    for seed in range(args.first, args.first + args.seeds):
        wiggle = None if args.wiggle_mm is None else args.wiggle_mm / 1000.0
        config, document = cell(seed, args.camera, wiggle, arm=not args.ideal_arm)
        truth_table = document["sim"]["mount"]
        truth = Pose.from_xyz_rpy(np.asarray(truth_table["translation_m"]), np.radians(truth_table["rpy_deg"]))
        camera, arm = build_devices(config)
        with tempfile.TemporaryDirectory():
            measured = plan_calibrator(config, camera, arm, auto_plan(config)).run()
        model = arm.arm_model()
        for name, (split, shifts) in ways.items():
            try:
                est = estimate_from_document(config, variant(measured, split, shifts), model)
            except CalibrationQualityError:  # refused (gate noise_model): a miss of every value
                inside_of[name].append(np.zeros(len(VALUES), dtype=bool))
                refused[name] += 1
                continue
            inside_of[name].append(inside(est, truth))
            chi2_of[name].append(est.chi2 / est.dof)
            width_of[name].append(half_widths(est))
    wall = time.perf_counter() - started
    wiggle = "the sim's" if args.wiggle_mm is None else f"{args.wiggle_mm:g} mm"
    arm_text = "an ideal arm" if args.ideal_arm else "one arm each"
    print(f"{args.seeds} seeds ({wall:.0f} s), {arm_text}, the camera's systematic error {args.camera} "
          f"(ToF allowance 0.2 %, 5 mm, 2 mm; wiggle {wiggle}):")
    for name in ways:
        w = np.mean(inside_of[name], axis=0)
        ok = bool(np.all((w >= TARGET[0]) & (w <= TARGET[1])))
        hw = np.mean(width_of[name], axis=0) if width_of[name] else np.full(len(VALUES), np.nan)
        chi = f"{np.median(chi2_of[name]):.2f}" if chi2_of[name] else "n/a"
        print(f"  {name}: {percent(w)} %  (pooled {100 * w.mean():.1f} %); refused {refused[name]}; chi2/dof median "
              f"{chi}; target {100 * TARGET[0]:.0f}-{100 * TARGET[1]:.0f} %: "
              f"{'PASS' if ok else 'FAIL'}")
        print("      mean 95 % half-widths: " + " ".join(
            f"{v} {x:.3g} {'mm' if i < 3 else 'deg'}" for i, (v, x) in enumerate(zip(VALUES, hw, strict=True))))


if __name__ == "__main__":
    main()
