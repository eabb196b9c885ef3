"""Figures of the drift monitor on the simulated cell (and the O3R emulator).

Prints, for the packaged ``sim.toml`` (camera 0.44 m above the table, looking straight
down) with the default ``[monitor]`` thresholds (``period_s`` set to 0 so it runs flat out):

* **noise**: frames of plain sim noise through the real monitor (full-frame fit per
  frame), the number of false drift flags (target: 0), the per-frame noise of tilt and
  height, the largest deviation seen and its margin to the effective threshold;
* **bumps**: 0.5 deg about the camera's x and y axes and 5 mm along the optical axis,
  injected through ``SimWorld.bump_mount``: the detection latency in frames and in
  seconds of frame time (target: within 1 s);
* the median time per monitored frame (capture + fit + detector), ms.

Usage: python benchmarks/monitor_drift.py [--frames N] [--o3r-frames N]
"""

from __future__ import annotations

import argparse
import itertools
import math
import statistics
import time
from dataclasses import replace
from importlib import resources
from pathlib import Path
from typing import Any

from cellcal.core.calibration.config import CellConfig, load_config
from cellcal.core.monitor import Monitor, MonitoredCamera, MonitorStatus
from cellcal.devices.base import BackendContext
from cellcal.devices.camera import Camera3D
from cellcal.devices.pose import Pose
from cellcal.devices.registry import default_registry
from cellcal.sims.world import SHARED_KEY, SimWorld

CONFIGS = Path(str(resources.files("cellcal.configs")))


def make_camera(config: CellConfig) -> tuple[Camera3D, SimWorld]:
    shared: dict[str, Any] = {}
    ctx = BackendContext(source=config.source, section="camera", document=config.document, shared=shared,
                         seed=config.cell.seed)
    camera = default_registry().create_camera(config.camera_section, ctx)
    return camera, shared[SHARED_KEY]


def noise_run(config_name: str, frames: int) -> None:
    config = load_config(CONFIGS / config_name)
    settings = replace(config.monitor, period_s=0.0)
    camera, _ = make_camera(config)
    stamps: list[float] = []
    summary = Monitor([MonitoredCamera("cam", camera, settings, config.full_frame)],
                      lambda s: stamps.append(time.perf_counter())).run(max_frames=frames)
    c = summary.cameras[0]
    assert c.baseline is not None and c.tilt_threshold_rad and c.height_threshold_m
    assert c.baseline.tilt_noise_rad is not None and c.baseline.height_noise_m is not None
    per_frame_ms = 1000 * statistics.median(b - a for a, b in itertools.pairwise(stamps))
    print(f"{config_name}: {c.frames} noise frames, {c.errors} failed, "
          f"{sum(e.kind == 'drift_started' for e in c.events)} false drift flag(s); {per_frame_ms:.1f} ms/frame")
    tilt_thr_deg = math.degrees(c.tilt_threshold_rad)
    print(f"  noise (1 sigma, from {settings.baseline_frames} frames): "
          f"tilt {math.degrees(c.baseline.tilt_noise_rad):.4f} deg per axis, "
          f"height {c.baseline.height_noise_m * 1e6:.1f} um")
    print(f"  largest deviation: tilt {math.degrees(c.max_tilt_deviation_rad):.4f} deg "
          f"({c.tilt_threshold_rad / c.max_tilt_deviation_rad:.0f}x below {tilt_thr_deg:.3f} deg),"
          f" height {c.max_height_deviation_m * 1e6:.1f} um "
          f"({c.height_threshold_m / c.max_height_deviation_m:.0f}x below {c.height_threshold_m * 1000:.2f} mm)")


def bump_run(name: str, delta: Pose, bump_after: int = 40, frames: int = 60) -> None:
    config = load_config(None)
    settings = replace(config.monitor, period_s=0.0)
    camera, world = make_camera(config)
    statuses: list[MonitorStatus] = []

    def on_status(status: MonitorStatus) -> None:
        statuses.append(status)
        if status.index == bump_after:
            world.bump_mount(delta)

    Monitor([MonitoredCamera("sim", camera, settings, config.full_frame)], on_status).run(max_frames=frames)
    first = statuses[bump_after + 1]
    flagged = [s for s in statuses if s.event is not None and s.event.kind == "drift_started"]
    if not flagged or first.detector is None:
        print(f"  bump {name}: NOT flagged")
        return
    ev = flagged[0].event
    assert ev is not None
    early = flagged[0].index <= bump_after
    print(f"  bump {name}: flagged {flagged[0].index - bump_after} frame(s) / "
          f"{ev.timestamp - first.detector.sample.timestamp:.3f} s after the first bumped frame"
          f"{' (EARLY!)' if early else ''}; causes {', '.join(ev.causes)}; "
          f"tilt {math.degrees(ev.tilt_deviation_rad):.3f} deg, height {ev.height_deviation_m * 1000:.2f} mm")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=3000, help="sim noise frames (default %(default)s)")
    parser.add_argument("--o3r-frames", type=int, default=500, help="O3R emulator noise frames (default %(default)s)")
    args = parser.parse_args()
    noise_run("sim.toml", args.frames)
    if args.o3r_frames:
        noise_run("o3r_emulated.toml", args.o3r_frames)
    d = math.radians(0.5)
    print("sim.toml, default [monitor] (window 5 frames, camera at 20 Hz):")
    bump_run("0.5 deg about x", Pose.from_xyz_rpy((0, 0, 0), (d, 0, 0)))
    bump_run("0.5 deg about y", Pose.from_xyz_rpy((0, 0, 0), (0, d, 0)))
    bump_run("5 mm along z", Pose.from_xyz_rpy((0, 0, 0.005), (0, 0, 0)))
    bump_run("5 mm along x (in the plane: invisible)", Pose.from_xyz_rpy((0.005, 0, 0), (0, 0, 0)))


if __name__ == "__main__":
    main()
