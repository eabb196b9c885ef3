"""Depth calibration benchmark (issue #39 targets): ``fit_depthcal`` on the sims with known systematic errors.

For the stereo sim (OAK-like 640x400) and the ToF sim (O3R-like 224x172, artefacts off: the data-sheet
noise law), over several seeds, with systematic errors unlike the sims' defaults injected into ideal
frames (``tests/support/depthcal_views.py``), on a default-like plan (12 views at heights 0.45-0.65 m,
inclinations 90, 80 and 70 deg, the tilt's azimuth and the image position varying):

* **coverage**: the share of the correction's parameters whose 95 % interval holds the truth
  (target 90-98 %);
* **held-out**: the held-out views' residual RMS after the correction over the noise-only RMS
  (target <= 1.10);
* **scale and offset**: the 95 % half-width of the scale (target <= 0.1 %) and of the offset in depth
  at the working distance 0.55 m (target <= 1 mm), each from the arm's motion alone;
* **after calibrating**: a full-frame fit (``fit_full_frame``) of fresh views corrected with the fitted
  correction (``devices.correction.correct_frame``): its tilt and height errors over their Cramér-Rao
  bounds for the noise alone (the Fisher information of the frame's native values), RMS over the views
  (target <= 1.5); the uncorrected fit's for comparison;
* **the floor** of that check: the height error a perfect (noise-free) fit of ONE corrected frame would
  still have, the fitted correction's covariance propagated through the frame's fit, in micrometres beside
  the noise-alone bound. A single frame's noise bound is tiny (thousands of pixels) and the correction's
  leftover dominates it, so the issue's "<= 1.5x the noise-alone bound" cannot be met by any correction
  fitted from a plan of a dozen views; what a corrected fit can meet is <= 1.5x the two in quadrature,
  printed beside it. The floor shrinks with the points the depth calibration uses (``--points``);
* **the arm's share** of the scale and offset intervals: seed 0 refitted with the sim arm's stated accuracy
  (0.48 mm, 0.049 deg RMS, ``[sim.arm_errors]``'s defaults) in the intervals, as ``cellcal depthcal`` does. The
  scale is learnt from the arm's motion, so its interval cannot be narrower than what the arm's error does to
  that motion: the line prints the half-widths with it, the arm's part alone, and the arm accuracy the
  ``<= 0.1 %`` target would need (the arm's part is linear in it);
* **time** of the fit (median; wall clock, shared machine: re-measure on a quiet one).

Run: ``.venv/bin/python benchmarks/depthcal.py [--seeds 5] [--points 16000]`` (``--points``: the fit's
``max_points_per_view``, default its default).
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):  # one core: a shared machine
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import math  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from cellcal.core.depthcal import DepthcalResult, fit_depthcal  # noqa: E402
from cellcal.core.depthcal.fit import DEFAULT_POINTS_PER_VIEW  # noqa: E402
from cellcal.core.geometry.planes import Plane  # noqa: E402
from cellcal.core.handeye.estimator import ArmAccuracy  # noqa: E402
from cellcal.core.methods.fullframe import fit_full_frame  # noqa: E402
from cellcal.devices.correction import correct_frame  # noqa: E402
from cellcal.devices.pose import Pose  # noqa: E402
from cellcal.devices.systematic import SystematicError, normalised_pixels  # noqa: E402
from cellcal.devices.types import Frame  # noqa: E402
from tests.support.depthcal_views import MOUNT, bow_error, plan, stereo_views, tof_views  # noqa: E402

WORKING_DISTANCE_M = 0.55
#: Truths unlike the sims' defaults (stereo 0.5 %, 0.05 px, +0.5 px bow; ToF 3 mm, 0.1 %, 1 mm wiggle).
STEREO_TRUTH = bow_error("stereo", -0.4, 640, 400, fb_error=-0.007, disparity_offset_px=-0.12)
TOF_TRUTH = SystematicError("tof", offset_m=-0.0025, scale_error=-0.0025, wiggle_cos_m=-0.0008,
                            wiggle_sin_m=0.0009, wiggle_period_m=0.6246)
#: Camera poses of the check after calibrating (not in the plan).
CHECK_POSES = [Pose.from_xyz_rpy([0.02, -0.01, 0.5], np.radians([180.0 + 8.0, 0.0, 30.0])),
               Pose.from_xyz_rpy([-0.03, 0.02, 0.6], np.radians([180.0, -12.0, 100.0]))]


def crb_sigmas(exact: Frame, truth: Plane, native_sigma: np.ndarray | float, stereo: bool, fb: float,
               correction: SystematicError) -> tuple[float, float, float, float, float, float]:
    """Cramér-Rao 1-sigmas of a plane's tilt (RMS angle, rad) and height (m) from a frame's native values.

    Every valid pixel of the noise-free frame measures ``f·B/Z`` (stereo) or the range (ToF) of its ray's
    meeting with the plane, with the noise alone; the Fisher information of (two tilts, distance) inverts
    to the smallest covariance an unbiased fit can reach. Also the same with the correction's leftover
    (its covariance propagated through the weighted fit), and the leftover's part alone, the floor: what a
    perfect (noise-free) frame corrected with this correction would still err by:
    ``(tilt, height, tilt_with, height_with, tilt_floor, height_floor)``.
    """
    xyz = exact.xyz[exact.valid].astype(np.float64)
    rays = xyz / np.linalg.norm(xyz, axis=1)[:, None]
    n = np.asarray(truth.normal, dtype=np.float64)
    dist = float(truth.offset_m)
    t1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n, t1)

    def native(p: np.ndarray) -> np.ndarray:
        nn = n + p[0] * t1 + p[1] * t2
        nn = nn / np.linalg.norm(nn)
        rho = (dist + p[2]) / -(rays @ nn)
        return fb / (rho * rays[:, 2]) if stereo else rho

    jac = np.empty((rays.shape[0], 3))
    for k, h in enumerate((1e-6, 1e-6, 1e-7)):
        e = np.zeros(3)
        e[k] = h
        jac[:, k] = (native(e) - native(-e)) / (2 * h)
    sig = np.broadcast_to(np.asarray(native_sigma, dtype=np.float64), (rays.shape[0],))
    jw = jac / sig[:, None]
    cov = np.linalg.inv(jw.T @ jw)
    intr = exact.intrinsics
    u, v = normalised_pixels(intr.width, intr.height, intr.cx, intr.cy)
    design = correction.jacobian(native(np.zeros(3)), u[exact.valid], v[exact.valid])
    gain = cov @ (jw.T @ (design / sig[:, None]))          # plane parameters per correction term
    floor = gain @ np.asarray(correction.covariance) @ gain.T
    both = cov + floor
    return (math.sqrt(cov[0, 0] + cov[1, 1]), math.sqrt(cov[2, 2]),
            math.sqrt(both[0, 0] + both[1, 1]), math.sqrt(both[2, 2]),
            math.sqrt(floor[0, 0] + floor[1, 1]), math.sqrt(floor[2, 2]))


def check_after(result: DepthcalResult, kind: str, seed: int
                ) -> tuple[list[float], list[float], list[float], list[tuple[float, float, float]]]:
    """Full-frame fits of fresh views, corrected and not: (tilt, height) errors over their CRB sigmas.

    Returns the corrected fit's errors over the noise-alone bound, over the bound with the correction's
    leftover, the uncorrected fit's over the noise-alone bound (tilt, height pairs), and per view the
    height's figures in metres: (the corrected fit's error, the noise-alone bound, the correction's floor).
    """
    truth_err = STEREO_TRUTH if kind == "stereo" else TOF_TRUTH
    make = stereo_views if kind == "stereo" else tof_views
    views, _ = make(truth_err, CHECK_POSES, seed=seed + 1000)
    exact_views, _ = make(SystematicError(truth_err.kind), CHECK_POSES, seed=seed + 1000, noise=False)
    ratios_after, ratios_before, ratios_with = [], [], []
    heights: list[tuple[float, float, float]] = []
    for view, exact, pose in zip(views, exact_views, CHECK_POSES, strict=True):
        plane = Plane.from_point_normal(np.zeros(3), [0.0, 0.0, 1.0]).transformed(pose.inv()).oriented_toward_origin()
        model = view.frame.measurement
        if kind == "stereo":
            sig: np.ndarray | float = model.disparity_noise_px
            fb = model.fb_px_m
        else:
            xyz = exact.frame.xyz[exact.frame.valid].astype(np.float64)
            rho = np.linalg.norm(xyz, axis=1)
            cos = np.abs(xyz @ plane.normal) / rho
            sig = np.asarray(model.range_sigma_m(rho, cos))
            fb = 1.0
        s_tilt, s_height, w_tilt, w_height, _, f_height = crb_sigmas(exact.frame, plane, sig, kind == "stereo",
                                                                     fb, result.correction)
        for frame, out in ((correct_frame(view.frame, result.correction), ratios_after), (view.frame, ratios_before)):
            fit = fit_full_frame(frame)
            tilt = math.acos(min(1.0, abs(float(fit.plane.normal @ plane.normal))))
            height = float(fit.plane.offset_m) - float(plane.offset_m)
            out.extend([tilt / s_tilt, height / s_height])
            if out is ratios_after:
                ratios_with.extend([tilt / w_tilt, height / w_height])
                heights.append((height, s_height, f_height))
    return ratios_after, ratios_with, ratios_before, heights


#: The sim arm's stated accuracy (``[sim.arm_errors]``'s defaults over the plans: ADR 0055).
SIM_ARM = ArmAccuracy(0.48e-3, math.radians(0.049), "sim")


def arm_share(res: DepthcalResult, views: list, model: object, kind: str, points: int, seed: int) -> None:
    """Print the scale / offset 95 % half-widths with the sim arm's accuracy in the intervals, and its part alone."""
    truth = STEREO_TRUTH if kind == "stereo" else TOF_TRUTH
    told = fit_depthcal(views, mount=MOUNT, model=model, max_points_per_view=points, seed=seed,  # type: ignore[arg-type]
                        wiggle_period_m=None if kind == "stereo" else truth.wiggle_period_m, arm_accuracy=SIM_ARM)
    data = res.correction.leftover_sigma(res.correction.names)[:2]
    both = told.correction.leftover_sigma(told.correction.names)[:2]
    arm = np.sqrt(np.maximum(both**2 - data**2, 0.0))     # the arm's part: the two add in quadrature
    to_m = WORKING_DISTANCE_M ** 2 / model.fb_px_m if kind == "stereo" else 1.0  # type: ignore[attr-defined]
    need = 1000 * SIM_ARM.position_m * max(0.0, 0.001 / 1.96 - data[0]) / arm[0] if arm[0] > 0 else math.inf
    print(f"  with the arm's stated accuracy ({1000 * SIM_ARM.position_m:.2f} mm, "
          f"{math.degrees(SIM_ARM.rotation_rad):.3f} deg): scale ±{100 * 1.96 * both[0]:.3f} %, offset "
          f"±{1000 * 1.96 * both[1] * to_m:.3f} mm; the arm's part alone ±{100 * 1.96 * arm[0]:.3f} %, "
          f"±{1000 * 1.96 * arm[1] * to_m:.3f} mm: scale <= 0.1 % needs an arm accurate to about {need:.2f} mm "
          f"(target holds from the data alone; with this arm the honest target is the arm's part)")


def run(kind: str, seeds: int, points: int) -> dict[str, float]:
    truth = STEREO_TRUTH if kind == "stereo" else TOF_TRUTH
    true = dict(zip(truth.names, truth.vector, strict=True))
    inside = total = 0
    held, half_scale, half_offset, times, after, before, orders = [], [], [], [], [], [], []
    cpu: list[float] = []
    with_leftover: list[float] = []
    heights: list[tuple[float, float, float]] = []
    for seed in range(seeds):
        views, _ = (stereo_views(truth, plan(seed=seed), seed=seed) if kind == "stereo"
                    else tof_views(truth, plan(seed=seed), seed=seed))
        model = views[0].frame.measurement
        t0, c0 = time.perf_counter(), time.process_time()
        res = fit_depthcal(views, mount=MOUNT, model=model, max_points_per_view=points, seed=seed,
                           wiggle_period_m=None if kind == "stereo" else truth.wiggle_period_m)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        c = res.correction
        sig = c.leftover_sigma(c.names)
        for name, value, s in zip(c.names, c.vector, sig, strict=True):
            if s > 0:
                total += 1
                inside += abs(value - true.get(name, 0.0)) <= 1.96 * s
        held.append(res.holdout_rms_after / res.noise_only_rms)
        orders.append(res.field_order)
        half_scale.append(1.96 * sig[0])
        to_m = WORKING_DISTANCE_M ** 2 / model.fb_px_m if kind == "stereo" else 1.0
        half_offset.append(1.96 * sig[1] * to_m)
        a, w, b, hs = check_after(res, kind, seed)
        heights.extend(hs)
        after.extend(a)
        with_leftover.extend(w)
        before.extend(b)
        print(f"  {kind} seed {seed}: order {res.field_order}, held-out {held[-1]:.3f}x noise "
              f"(before {res.holdout_rms_before / res.noise_only_rms:.3f}x), scale ±{100 * half_scale[-1]:.3f} %, "
              f"offset ±{1000 * half_offset[-1]:.3f} mm, fit {times[-1]:.1f} s", flush=True)
        if seed == 0:
            arm_share(res, views, model, kind, points, seed)
    rms = lambda xs: math.sqrt(statistics.fmean(np.square(xs)))  # noqa: E731
    after_t, after_h = rms(after[0::2]), rms(after[1::2])
    before_t, before_h = rms(before[0::2]), rms(before[1::2])
    with_t, with_h = rms(with_leftover[0::2]), rms(with_leftover[1::2])
    cov_share = inside / total
    err_h = rms([h[0] for h in heights])
    crb_h = rms([h[1] for h in heights])
    floor_h = rms([h[2] for h in heights])
    out = {"coverage": cov_share, "held": max(held), "scale": max(half_scale), "offset": max(half_offset),
           "time": statistics.median(times), "tilt": after_t, "height": after_h, "floor_m": floor_h}

    def verdict(ok: bool) -> str:
        return "PASS" if ok else "FAIL"
    print(f"{kind}: {seeds} seeds, {points} points per view, field orders chosen {orders}")
    print(f"  95 % intervals hold the truth: {inside}/{total} = {100 * cov_share:.1f} % (target 90-98 %) "
          f"{verdict(0.90 <= cov_share <= 0.98)}")
    print(f"  held-out RMS after / noise-only: worst {max(held):.3f} (target <= 1.10) {verdict(max(held) <= 1.10)}")
    print(f"  scale 95 % half-width: worst {100 * max(half_scale):.3f} % (target <= 0.1 %) "
          f"{verdict(max(half_scale) <= 0.001)}")
    print(f"  offset 95 % half-width in depth at {WORKING_DISTANCE_M} m: worst {1000 * max(half_offset):.3f} mm "
          f"(target <= 1 mm) {verdict(max(half_offset) <= 0.001)}")
    print(f"  full-frame fit after the correction, RMS error / CRB: tilt {after_t:.2f}, height {after_h:.2f} "
          f"(target <= 1.5) {verdict(max(after_t, after_h) <= 1.5)}; uncorrected: tilt {before_t:.2f}, "
          f"height {before_h:.2f}")
    print(f"  the same over the bound with the correction's leftover (its covariance through the fit): "
          f"tilt {with_t:.2f}, height {with_h:.2f} {verdict(max(with_t, with_h) <= 1.5)}")
    print(f"  height floor of ONE corrected frame: the noise-alone CRB {1e6 * crb_h:.1f} um, the correction's own "
          f"leftover (a perfect fit of the frame, the correction's covariance) {1e6 * floor_h:.1f} um = "
          f"{floor_h / crb_h:.0f}x the CRB; the corrected fit's RMS error {1e6 * err_h:.1f} um = "
          f"{err_h / math.hypot(crb_h, floor_h):.2f}x their sum in quadrature (meetable target <= 1.5)")
    print(f"  fit time: median {statistics.median(times):.2f} s wall, {statistics.median(cpu):.2f} s CPU "
          f"(shared machine: re-measure on a quiet one)")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--points", type=int, default=DEFAULT_POINTS_PER_VIEW, help="max_points_per_view")
    parser.add_argument("--kind", choices=("stereo", "tof", "both"), default="both")
    args = parser.parse_args()
    for kind in ("stereo", "tof") if args.kind == "both" else (args.kind,):
        run(kind, args.seeds, args.points)


if __name__ == "__main__":
    main()
