"""What running ur_rtde in a worker process costs a pose: ``isolate = true`` against in-process.

Against the UR emulator (a child process on a free 127.0.0.N, motion at ``--time-scale``),
the same ``ur`` driver runs the same cycle with ur_rtde in its worker process and in this
process: a short ``move_linear`` (with its arrival check), ``get_pose``, ``status``, as a
calibration pose does. Prints the median cycle time of each, the difference, the cost of
one call into the worker (a round trip on ``get_pose``'s ``getTimestamp``) and how many
calls a cycle makes. Target (issue #31): the worker adds at most 5 ms to a pose; exit 1 if
the measured median difference is above it.

Usage: python benchmarks/ur_worker.py [--cycles N] [--time-scale S]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np

from cellcal.devices.pose import Pose
from cellcal.drivers.ur.arm import URArm
from cellcal.sims.ur.process import UREmulatorProcess

TARGET_MS = 5.0
HOME = Pose.from_xyz_rpy([0.40, 0.0, 0.45], [np.pi, 0.0, 0.0])


def _cycle_times(host: str, *, isolate: bool, cycles: int) -> tuple[list[float], int, list[float]]:
    """Seconds per move+read+status cycle, calls into the worker per cycle, seconds per get_pose."""
    arm = URArm.from_config({"host": host, "timeout_s": 5.0, "poll_interval_s": 0.002, "isolate": isolate})
    with arm.connect(timeout=20.0):
        start = arm.get_pose()
        times: list[float] = []
        calls0 = getattr(arm._host, "calls", 0)
        for i in range(cycles):
            offset = np.array([0.0, 0.01 if i % 2 == 0 else 0.0, 0.0])
            target = Pose(start.rotation, start.translation + offset)
            t0 = time.perf_counter()
            arm.move_linear(target, speed=0.25, acceleration=1.2, timeout=10.0)
            arm.get_pose()
            arm.status()
            times.append(time.perf_counter() - t0)
        calls = (getattr(arm._host, "calls", 0) - calls0) // cycles
        reads: list[float] = []
        for _ in range(200):
            t0 = time.perf_counter()
            arm.get_pose()
            reads.append(time.perf_counter() - t0)
    return times, calls, reads


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=40, help="move cycles per mode (default: %(default)s)")
    parser.add_argument("--time-scale", type=float, default=0.02,
                        help="emulator wall seconds per simulated second (default: %(default)s)")
    args = parser.parse_args(argv)
    with UREmulatorProcess("auto", arm_config={"time_scale": args.time_scale}, unlock_delay_s=0.0) as emu:
        results: dict[bool, tuple[list[float], list[float], int]] = {}
        for isolate in (False, True, False, True):           # interleaved: drift of the machine hits both
            emu.call("reset")
            times, calls, reads = _cycle_times(emu.host, isolate=isolate, cycles=args.cycles)
            results.setdefault(isolate, ([], [], calls))
            results[isolate][0].extend(times)
            results[isolate][1].extend(reads)
    inline, worker = results[False], results[True]
    med = {k: statistics.median(v[0]) * 1000 for k, v in results.items()}
    read = {k: statistics.median(v[1]) * 1000 for k, v in results.items()}
    extra = med[True] - med[False]
    print(f"pose cycle (move_linear + get_pose + status), median of {len(inline[0])}:")
    print(f"  in-process      {med[False]:8.2f} ms")
    print(f"  worker process  {med[True]:8.2f} ms   ({worker[2]} calls into the worker per cycle)")
    print(f"  difference      {extra:+8.2f} ms   target <= {TARGET_MS:g} ms")
    print(f"get_pose, median of {len(inline[1])}: in-process {read[False]:.3f} ms, worker {read[True]:.3f} ms "
          f"({read[True] - read[False]:+.3f} ms)")
    if extra > TARGET_MS:
        print(f"FAIL: the worker adds {extra:.2f} ms to a pose (> {TARGET_MS:g} ms)")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
