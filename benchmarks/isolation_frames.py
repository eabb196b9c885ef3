"""What running a camera's SDK in a worker process costs a frame: ``isolate = true`` against in-process.

A synthetic SDK stand-in (:class:`SyntheticCamera`, no device) hands out 640 x 400 frames as
the OAK backend builds them (distance, xyz, amplitude float32, valid bool: 5.4 MB a frame);
the same class runs in this process and, with ``isolate = true``, in a worker process behind
the real transport (``cellcal.devices.isolation``: the pipe for the call, the shared-memory
ring for the arrays, the parent's views of its slot, one frame held at a time as a consumer
holds it while it works). Frames are asked for at 30 fps. Prints the
median and 90th-percentile time of ``capture`` in each mode, the difference (the isolation's
cost) as a share of the 33.3 ms frame period, and the CPU both processes spend per frame.
Target (issue #41): the median cost <= 10 % of the period; exit 1 above it.

Usage: python benchmarks/isolation_frames.py [--frames N] [--width W] [--height H] [--fps F]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cellcal.devices.base import BackendContext
from cellcal.devices.isolation.camera import IsolatableCamera
from cellcal.devices.types import DeviceInfo, Frame, Intrinsics

TARGET_SHARE = 0.10


@dataclass(frozen=True)
class SyntheticConfig:
    """The stand-in's config: the stream's size and rate, and where it runs."""

    width: int = field(default=640, metadata={"ge": 16, "le": 4096})
    height: int = field(default=400, metadata={"ge": 16, "le": 4096})
    isolate: bool = True


class SyntheticCamera(IsolatableCamera):
    """An SDK stand-in: each capture hands out fresh arrays (copies of one scene), as an SDK's new buffer would."""

    backend_name = "synthetic"
    Config = SyntheticConfig
    native_library = "synthetic-sdk"
    #: Imported by name in the worker (this file runs as ``__main__`` here; the worker finds it on PYTHONPATH).
    worker_factory = "isolation_frames:SyntheticCamera"

    def __init__(self, config: SyntheticConfig, context: BackendContext | None = None) -> None:
        super().__init__()
        self.config = config
        self._seq = 0
        self._intr = Intrinsics(config.width, config.height, 450.0, 450.0, config.width / 2 - 0.5,
                                config.height / 2 - 0.5)
        self._scene: dict[str, Any] = {}

    def _connect(self, timeout: float) -> None:
        if self.config.isolate:
            self._start_worker("synthetic", timeout, 2.0)
            return
        h, w = self.config.height, self.config.width
        rng = np.random.default_rng(0)
        z = (0.8 + 0.01 * rng.standard_normal((h, w))).astype(np.float32)   # a plane 0.8 m away, 10 mm noise
        v, u = np.mgrid[0:h, 0:w].astype(np.float32)
        xyz = np.stack([(u - self._intr.cx) / self._intr.fx * z, (v - self._intr.cy) / self._intr.fy * z, z], axis=2)
        self._scene = {"xyz": xyz, "distance": np.linalg.norm(xyz, axis=2).astype(np.float32),
                       "amplitude": rng.uniform(0, 255, (h, w)).astype(np.float32), "valid": z > 0.79}

    def _close(self) -> None:
        self._stop_worker()

    def _info(self) -> DeviceInfo:
        if self._worker is not None:
            return self._worker.info()
        return DeviceInfo(backend="synthetic", vendor="none", model="stand-in")

    def _intrinsics(self) -> Intrinsics:
        return self._worker.intrinsics() if self._worker is not None else self._intr

    def _capture(self, timeout: float) -> Frame:
        if self._worker is not None:
            return self._worker.capture(timeout)
        self._seq += 1
        s = self._scene
        return Frame(distance=s["distance"].copy(), xyz=s["xyz"].copy(), amplitude=s["amplitude"].copy(),
                     valid=s["valid"].copy(), intrinsics=self._intr, timestamp=time.time(), sequence=self._seq)


def _cpu_s(pid: int | None) -> float:
    """CPU seconds (user + system) of this process, plus those of process ``pid`` (Linux: /proc)."""
    total = time.process_time()
    if pid is not None:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return total


def _run(config: Any, frames: int, fps: float) -> tuple[list[float], float]:
    """Seconds per capture at ``fps``, and CPU seconds per frame (both processes)."""
    from isolation_frames import SyntheticCamera as Camera  # type: ignore[import-not-found]

    cam = Camera(config)
    times: list[float] = []
    with cam.connect(timeout=20.0):
        for _ in range(5):  # warm: the ring is made at the first frame, pages touched
            cam.capture(1.0)
        cpu0 = _cpu_s(cam.worker_pid)
        tick = time.perf_counter()
        for _ in range(frames):
            t0 = time.perf_counter()
            frame = cam.capture(1.0)
            times.append(time.perf_counter() - t0)
            assert frame.xyz.shape == (config.height, config.width, 3)
            tick += 1.0 / fps
            time.sleep(max(0.0, tick - time.perf_counter()))
        cpu = (_cpu_s(cam.worker_pid) - cpu0) / frames
    return times, cpu


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=150, help="frames per mode (default: %(default)s)")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=400)
    parser.add_argument("--fps", type=float, default=30.0)
    args = parser.parse_args(argv)
    # the worker imports this file by name
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(Path(__file__).parent),
                                                             os.environ.get("PYTHONPATH", "")]))
    period_ms = 1000.0 / args.fps
    mb = args.width * args.height * (4 + 12 + 4 + 1) / 1e6
    print(f"{args.width} x {args.height} frames ({mb:.2f} MB: distance, xyz, amplitude float32, valid) at "
          f"{args.fps:g} fps, {args.frames} per mode; synthetic SDK stand-in, real transport")
    sys.path.insert(0, str(Path(__file__).parent))
    # the classes under their module's name, not __main__'s: the config is pickled to the worker
    from isolation_frames import SyntheticConfig as Config  # type: ignore[import-not-found]

    figures: dict[bool, tuple[float, float, float]] = {}
    for isolate in (False, True):
        times, cpu = _run(Config(args.width, args.height, isolate), args.frames, args.fps)
        ms = sorted(t * 1e3 for t in times)
        figures[isolate] = (statistics.median(ms), ms[int(0.9 * (len(ms) - 1))], cpu * 1e3)
        print(f"  {'worker process' if isolate else 'in-process    '}: capture median {figures[isolate][0]:6.2f} ms, "
              f"p90 {figures[isolate][1]:6.2f} ms, CPU {figures[isolate][2]:6.2f} ms a frame")
    cost = figures[True][0] - figures[False][0]
    cpu_cost = figures[True][2] - figures[False][2]
    share = cost / period_ms
    print(f"isolation costs {cost:.2f} ms a frame (median), {100 * share:.1f} % of the {period_ms:.1f} ms period; "
          f"CPU {cpu_cost:.2f} ms a frame ({100 * cpu_cost / period_ms:.1f} %); target <= {100 * TARGET_SHARE:.0f} %")
    ok = share <= TARGET_SHARE
    print("PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
