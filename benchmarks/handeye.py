"""Figures of ``cellcal handeye`` on the simulated xArm 5 cell (``configs/sim_handeye.toml``).

* **coverage**: ``--trials N`` complete simulated runs (auto plan, seeds 0..N-1; the true
  mount ``[sim.mount]`` is 5.8 mm / 0.98 deg off the nominal ``[mount]``): mean and
  largest error of the plane method per axis, and how often the 95 % intervals of
  ``translation_m`` and ``rpy_deg`` contain the truth (target 93-97 %).
* **compare**: ``--compare N`` runs with a ChArUco board in the scene, the same poses:
  the plane method against every OpenCV ``calibrateHandEye`` method on the board views
  (rotation error, deg; translation error per axis, mm; mean over the runs).

Usage: python benchmarks/handeye.py [--trials N] [--compare N]
"""

from __future__ import annotations

import argparse
import math
import time
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from cellcal.core.calibration.calibrator import build_devices
from cellcal.core.calibration.config import parse_config
from cellcal.core.handeye import auto_plan, estimate_from_document, plan_calibrator
from cellcal.devices.pose import Pose

CONFIG = Path(str(resources.files("cellcal.configs"))) / "sim_handeye.toml"


def cell(seed: int, board: bool = False) -> Any:
    """The hand-eye sim cell with ``[cell] seed`` set (and a ChArUco board on the table)."""
    document = tomllib.loads(CONFIG.read_text())
    document["cell"]["seed"] = seed
    if board:
        # the default board of [handeye] charuco_*, rendered finely (6x6 sub-rays, 160 texels per square)
        document["sim"]["charuco"] = {"center_m": [0.3, 0.0, 0.0], "supersample": 6, "texture_px_per_square": 160}
    return parse_config(document, f"{CONFIG} (seed {seed})")


def true_mount(config: Any) -> Pose:
    """The simulator's true mount, ``[sim.mount]``."""
    m = config.document["sim"]["mount"]
    return Pose.from_xyz_rpy(m["translation_m"], np.radians(m["rpy_deg"]))


def rotation_error_deg(estimate: Pose, truth: Pose) -> float:
    """Angle of ``truth^-1 estimate``, degrees."""
    return math.degrees(float(np.linalg.norm((truth.inv() @ estimate).rotation.as_rotvec())))


def one_trial(seed: int) -> dict[str, Any]:
    """One complete simulated run: errors of the plane method and whether each interval holds the truth."""
    config = cell(seed)
    poses = auto_plan(config)
    camera, arm = build_devices(config)
    measured = plan_calibrator(config, camera, arm, poses).run()
    est = estimate_from_document(config, measured)
    truth = true_mount(config)
    rpy, rpy_sigma = est.rpy_and_sigma_deg()
    true_rpy = np.degrees(truth.as_xyz_rpy()[3:])
    t_err = est.mount.translation - truth.translation
    rpy_err = rpy - true_rpy
    z = est.z
    return {"poses": len(poses), "t_err": t_err, "rpy_err": rpy_err, "rot_err": rotation_error_deg(est.mount, truth),
            "t_in": np.abs(t_err) <= z * est.translation_sigma_m, "rpy_in": np.abs(rpy_err) <= z * rpy_sigma,
            "t_sigma": est.translation_sigma_m, "rpy_sigma": rpy_sigma, "chi2": est.chi2, "dof": est.dof}


def coverage(trials: int) -> None:
    """Run ``trials`` seeds and print errors and interval coverage."""
    started = time.perf_counter()
    runs = [one_trial(seed) for seed in range(trials)]
    wall = time.perf_counter() - started
    t_err = np.array([r["t_err"] for r in runs]) * 1000
    rpy_err = np.array([r["rpy_err"] for r in runs])
    t_in = np.array([r["t_in"] for r in runs])
    rpy_in = np.array([r["rpy_in"] for r in runs])
    print(f"plane method, auto plan of {runs[0]['poses']} poses, {trials} simulated runs ({wall:.0f} s):")
    print("  translation |error| mean / max, mm: " + ", ".join(
        f"{a} {np.mean(np.abs(t_err[:, k])):.3f} / {np.max(np.abs(t_err[:, k])):.3f}" for k, a in enumerate("xyz")))
    print("  rpy |error| mean / max, deg: " + ", ".join(
        f"{a} {np.mean(np.abs(rpy_err[:, k])):.4f} / {np.max(np.abs(rpy_err[:, k])):.4f}"
        for k, a in enumerate(("roll", "pitch", "yaw"))))
    rot = np.array([r["rot_err"] for r in runs])
    print(f"  rotation error (angle) mean / max: {rot.mean():.4f} / {rot.max():.4f} deg")
    print("  95 % interval coverage: translation " + ", ".join(f"{a} {100 * t_in[:, k].mean():.1f} %"
                                                              for k, a in enumerate("xyz"))
          + "; rpy " + ", ".join(f"{a} {100 * rpy_in[:, k].mean():.1f} %" for k, a in enumerate(("r", "p", "y")))
          + f"; all six pooled {100 * np.concatenate([t_in, rpy_in], axis=1).mean():.1f} %")
    print("  error / sigma spread (should be ~1): translation " + ", ".join(
        f"{np.std(t_err[:, k] / 1000 / np.array([r['t_sigma'][k] for r in runs])):.2f}" for k in range(3))
          + "; rpy " + ", ".join(f"{np.std(rpy_err[:, k] / np.array([r['rpy_sigma'][k] for r in runs])):.2f}"
                                 for k in range(3)))
    chi2 = sum(r["chi2"] for r in runs) / sum(r["dof"] for r in runs)
    print(f"  pooled chi2 / dof {chi2:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=20, help="simulated runs for the coverage (default 20)")
    parser.add_argument("--compare", type=int, default=0, help="runs of plane vs OpenCV methods (default 0)")
    args = parser.parse_args()
    if args.trials:
        coverage(args.trials)
    if args.compare:
        from cellcal.core.handeye.charuco_run import compare_methods

        print(compare_methods([cell(seed, board=True) for seed in range(args.compare)], true_mount))


if __name__ == "__main__":
    main()
