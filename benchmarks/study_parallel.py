"""``cellcal study --jobs N`` against ``--jobs 1``: speed-up, CPU/wall and identical tables, in one run.

Runs the same small study (``--quick`` design, ``--trials`` per condition, no plots) as
a ``cellcal study`` subprocess with ``--jobs 1`` and with ``--jobs N`` (default: every
core), alternating, ``--repeats`` times each, and prints:

* the median wall time of each and the speed-up (target: >= 1.8x on 2 cores);
* CPU/wall of the parallel run, children included (target: >= 1.6 on 2 cores);
* whether the two ``study.csv`` files are byte-identical (they must be);
* the CPU seconds of each (the pool's overhead) and the load average: on a shared
  machine the speed-up is bounded by the cores the other jobs leave free.

Usage: python benchmarks/study_parallel.py [--trials N] [--jobs N] [--repeats N]
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SPEEDUP_TARGET = 1.8
CPU_WALL_TARGET = 1.6


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def _study(out: Path, trials: int, jobs: int) -> tuple[float, float]:
    """(wall s, CPU s of the study and its workers) of one ``cellcal study`` run."""
    cmd = [sys.executable, "-m", "cellcal.core.cli", "study", "--quick", "--trials", str(trials), "--no-plots",
           "--quiet", "--jobs", str(jobs), "--out", str(out)]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)  # a waited-for child's own waited-for children count
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=4, help="trials per condition (default 4; 6 conditions)")
    parser.add_argument("--jobs", type=int, default=_cores(), help="workers of the parallel run (default: cores)")
    parser.add_argument("--repeats", type=int, default=3, help="runs of each (default 3)")
    args = parser.parse_args()
    runs: dict[int, list[tuple[float, float]]] = {1: [], args.jobs: []}
    with tempfile.TemporaryDirectory() as tmp:
        outs = {1: Path(tmp) / "one", args.jobs: Path(tmp) / "many"}
        for _ in range(args.repeats):
            for jobs in runs:
                runs[jobs].append(_study(outs[jobs], args.trials, jobs))
        same = (outs[1] / "study.csv").read_bytes() == (outs[args.jobs] / "study.csv").read_bytes()
    wall = {j: statistics.median(w for w, _ in r) for j, r in runs.items()}
    cpu_wall = statistics.median(c / w for w, c in runs[args.jobs])
    speedup = wall[1] / wall[args.jobs]
    print(f"cellcal study --quick --trials {args.trials} ({6 * args.trials} trials), {args.repeats} runs each, "
          f"{_cores()} cores:")
    cpu = {j: statistics.median(c for _, c in r) for j, r in runs.items()}
    print(f"  --jobs 1: median {wall[1]:.2f} s wall, {cpu[1]:.2f} s CPU; --jobs {args.jobs}: median "
          f"{wall[args.jobs]:.2f} s wall, {cpu[args.jobs]:.2f} s CPU (workers included)")
    print(f"  load average during the run: {os.getloadavg()[0]:.1f} on {_cores()} cores (other jobs share them)")
    verdict = "met" if speedup >= SPEEDUP_TARGET else "MISSED"
    print(f"  speed-up {speedup:.2f}x (target >= {SPEEDUP_TARGET}x: {verdict})")
    print(f"  CPU/wall of --jobs {args.jobs}: {cpu_wall:.2f} (target >= {CPU_WALL_TARGET}: "
          f"{'met' if cpu_wall >= CPU_WALL_TARGET else 'MISSED'}); of --jobs 1: "
          f"{statistics.median(c / w for w, c in runs[1]):.2f}")
    print(f"  study.csv identical: {'yes' if same else 'NO'}")


if __name__ == "__main__":
    main()
