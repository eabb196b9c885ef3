"""``pixel_to_base`` benchmark: a 100 000-pixel batch and single-pixel requests to ``cellcal serve`` (issue #41).

Targets: a batch of 100 000 pixels mapped (points and their 1-sigma) in <= 50 ms, and >= 500
single-pixel requests a second on one core.

* **batch**: :func:`cellcal.core.service.planepoint.pixel_to_base` on 100 000 pixels spread over the
  image of the sim camera (its calibration from a ``calibrate`` run of the packaged sim cell),
  ``--reps`` times after a warm-up; the median process CPU time on one pinned core, BLAS on one
  thread. The same batch over HTTP (JSON both ways) is timed too, for information: JSON's text
  costs more than the mapping.
* **single**: ``cellcal serve`` in a child process pinned to one core (BLAS on one thread), asked
  ``--requests`` single-pixel ``pixel_to_base`` requests one after the other over one keep-alive
  connection (httpx, from this process on another core when there is one); the rate is requests
  per second of the server's CPU time (its user + system time from /proc), and the wall-clock
  rate is printed beside it.

Figures measured while other jobs share the machine are noisy (CPU time less so): re-measure on a
quiet machine. Prints each figure with PASS / FAIL; exit status 1 if any fails.

Run: ``python benchmarks/service_pixel_to_base.py [--reps N] [--requests N]``.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):  # one core
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from tests.support.serve_process import start_serve  # noqa: E402

BATCH = 100_000
BATCH_TARGET_S = 0.050
RATE_TARGET_PER_S = 500.0


def _cores() -> tuple[int | None, int | None]:
    """A core for the server (and the batch) and another for the client, when the machine has them."""
    if not hasattr(os, "sched_getaffinity"):
        return None, None
    cores = sorted(os.sched_getaffinity(0))
    return cores[0], (cores[1] if len(cores) > 1 else None)


def _calibrated(out: Path) -> tuple[Any, Any]:
    """A calibrate run of the packaged sim cell into ``out``; (the service, the first pose's flange pose)."""
    from cellcal.core.service import Service
    from cellcal.devices.pose import Pose

    service = Service([None], out)
    run = service.start_run("paper-sim", "calibrate", "camera", {"report": False})
    run.done.wait(600)
    if run.state != "ok":
        raise SystemExit(f"the calibrate run did not end ok: {run.error}")
    assert run.result is not None
    return service, Pose.from_dict(run.result["poses"][0]["reported_flange_pose"])


def _batch(service: Any, flange: Any, reps: int) -> float:
    """Median process CPU time of mapping :data:`BATCH` pixels, seconds."""
    cell = service.cells["paper-sim"]
    intr = cell.calibration("camera").model.intrinsics
    uv = np.random.default_rng(0).uniform([0, 0], [intr.width - 1, intr.height - 1], (BATCH, 2))
    flange_pose = flange.to_dict()
    cell.pixel_to_base("camera", uv, flange_pose)  # warm-up (the lens table)
    times = []
    for _ in range(reps):
        t0 = time.process_time()
        cell.pixel_to_base("camera", uv, flange_pose)
        times.append(time.process_time() - t0)
    return statistics.median(times)


def _cpu_s(pid: int) -> float | None:
    """User + system CPU time of process ``pid`` so far, seconds (None off Linux)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _serve(out: Path, core: int | None) -> tuple[subprocess.Popen[str], str]:
    prefix = ("taskset", "-c", str(core)) if core is not None and _has_taskset() else ()
    return start_serve("--port", "0", "--out", str(out), "--rate", "1e6", prefix=prefix)


def _has_taskset() -> bool:
    from shutil import which

    return which("taskset") is not None


def _single(out: Path, flange: Any, requests: int, cores: tuple[int | None, int | None]) -> tuple[float, float, float]:
    """(requests per server CPU second, per wall second, the 100 000-pixel batch over HTTP in wall seconds)."""
    import httpx

    proc, base = _serve(out, cores[0])
    if cores[1] is not None:
        os.sched_setaffinity(0, {cores[1]})
    url = f"{base}/cells/paper-sim/cameras/camera/pixel_to_base"
    body = {"pixels": [100.5, 80.25], "flange_pose": flange.to_dict()}
    try:
        with httpx.Client(timeout=60) as client:
            for _ in range(50):  # warm-up
                client.post(url, json=body).raise_for_status()
            cpu0, t0 = _cpu_s(proc.pid), time.perf_counter()
            for i in range(requests):
                body["pixels"] = [100.5 + (i % 50), 80.25]
                client.post(url, json=body).raise_for_status()
            wall, cpu1 = time.perf_counter() - t0, _cpu_s(proc.pid)
            uv = np.random.default_rng(1).uniform([0, 0], [223, 171], (BATCH, 2)).tolist()
            t1 = time.perf_counter()
            client.post(url, json={"pixels": uv, "flange_pose": flange.to_dict()}).raise_for_status()
            batch_http = time.perf_counter() - t1
    finally:
        proc.terminate()
        proc.communicate(timeout=60)
    cpu = (cpu1 - cpu0) if cpu0 is not None and cpu1 is not None else wall
    return requests / max(cpu, 1e-9), requests / wall, batch_http


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reps", type=int, default=20, help="batches timed (default: %(default)s)")
    parser.add_argument("--requests", type=int, default=2000, help="single requests timed (default: %(default)s)")
    args = parser.parse_args()
    cores = _cores()
    if cores[0] is not None:
        os.sched_setaffinity(0, {cores[0]})
    with tempfile.TemporaryDirectory(prefix="cellcal-bench-") as tmp:
        service, flange = _calibrated(Path(tmp))
        batch_s = _batch(service, flange, args.reps)
        service.close()
        rate_cpu, rate_wall, batch_http = _single(Path(tmp), flange, args.requests, cores)
    ok_batch, ok_rate = batch_s <= BATCH_TARGET_S, rate_cpu >= RATE_TARGET_PER_S
    print(f"batch of {BATCH} pixels: {batch_s * 1e3:.1f} ms CPU (median of {args.reps}; target <= "
          f"{BATCH_TARGET_S * 1e3:.0f} ms) {'PASS' if ok_batch else 'FAIL'}")
    print(f"single-pixel requests: {rate_cpu:.0f} per server CPU second ({rate_wall:.0f}/s wall clock, "
          f"{args.requests} requests; target >= {RATE_TARGET_PER_S:.0f}/s) {'PASS' if ok_rate else 'FAIL'}")
    print(f"for information: the same batch over HTTP, JSON both ways: {batch_http * 1e3:.0f} ms wall clock")
    return 0 if ok_batch and ok_rate else 1


if __name__ == "__main__":
    sys.exit(main())
