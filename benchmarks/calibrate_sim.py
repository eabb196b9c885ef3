"""End-to-end time of the default plan on the simulated cell.

Prints:
* the wall time of ``cellcal calibrate`` on the packaged sim.toml, interpreter start
  included (target: under 3 s), median of several runs;
* the time per pose spent outside simulated motion (capture + compute; target: under
  20 ms), from an in-process run.

Usage: python benchmarks/calibrate_sim.py [--runs N]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time


def end_to_end(runs: int) -> list[float]:
    times = []
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(runs):
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "cellcal.core.cli", "calibrate", "--quiet", "--out", tmp],
                           check=True, stdout=subprocess.DEVNULL)
            times.append(time.perf_counter() - t0)
    return times


def per_pose(runs: int) -> tuple[list[float], list[float], list[float]]:
    from cellcal.core.calibration.calibrator import Calibrator, build_devices
    from cellcal.core.calibration.config import load_config

    overhead, motion, full_frame = [], [], []
    for _ in range(runs):
        config = load_config(None)
        camera, arm = build_devices(config)
        doc = Calibrator(config, camera, arm).run()
        for t in doc["timings_s"]["per_pose"]:
            overhead.append(t["capture"] + t["compute"])
            motion.append(t["move"])
            full_frame.append(t.get("compute_full_frame", 0.0))
    return overhead, motion, full_frame


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    args = parser.parse_args()
    e2e = end_to_end(args.runs)
    overhead, motion, full_frame = per_pose(args.runs)
    med_e2e = statistics.median(e2e)
    med_over = statistics.median(overhead) * 1000
    print(f"cellcal calibrate (default sim plan, interpreter start included): median {med_e2e:.2f} s "
          f"over {args.runs} runs (min {min(e2e):.2f} s); target < 3 s -> {med_e2e / 3.0:.2f} of budget")
    print(f"per-pose overhead outside simulated motion (capture + compute): median {med_over:.2f} ms, "
          f"max {max(overhead) * 1000:.2f} ms over {len(overhead)} poses; target < 20 ms -> "
          f"{med_over / 20.0:.2f} of budget")
    print(f"  of which the full-frame fit (method full_frame): median {statistics.median(full_frame) * 1000:.2f} ms, "
          f"min {min(full_frame) * 1000:.2f} ms")
    print(f"per-pose simulated motion (wall, time_scale from the config): median "
          f"{statistics.median(motion) * 1000:.2f} ms")


if __name__ == "__main__":
    main()
