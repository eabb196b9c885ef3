"""What ``cellcal depthcal`` costs on its default plan, as a ratio to the default ``cellcal calibrate`` (target: <= 3x).

Runs ``cellcal depthcal --config CONFIG --no-report --quiet`` and ``cellcal calibrate --config
CONFIG --no-report --quiet`` as whole processes, interleaved (so both share the machine's load;
the order alternates within a pair), each in a fresh output directory. The figure judged is the
median over ``--runs`` pairs of depthcal's wall time over calibrate's (at least 3). Also printed:
the medians of each, the CPU time (user + system) and its ratio, and the fit's own time as
``DIR/depthcal.json`` states it. Bytecode is cached in a temporary ``PYTHONPYCACHEPREFIX`` warmed
by one untimed run of each. Timing on a loaded machine is noisy: the figures that count are a
quiet machine's.

Usage: python benchmarks/depthcal_run.py [--runs N] [--config configs/sim.toml]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: The issue's limit: depthcal on its default plan at most this many times the default calibrate.
TARGET_RATIO = 3.0
#: Fewest interleaved pairs the median is taken over.
MIN_RUNS = 3
ROOT = Path(__file__).resolve().parents[1]


def _cellcal() -> list[str]:
    """The ``cellcal`` console script beside this interpreter, else ``python -m cellcal.core.cli``."""
    script = Path(sys.executable).with_name("cellcal")
    return [str(script)] if script.exists() else [sys.executable, "-m", "cellcal.core.cli"]


def _timed(cmd: list[str], env: dict[str, str]) -> tuple[float, float]:
    """(wall s, CPU s of the child) of one run; the command must succeed."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=600)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def measure(runs: int, config: str) -> dict[str, list[float]]:
    """``runs`` interleaved pairs: wall and CPU seconds of each command, and the fit's own seconds."""
    cellcal = _cellcal()
    out: dict[str, list[float]] = {k: [] for k in ("calibrate", "calibrate_cpu", "depthcal", "depthcal_cpu", "fit")}
    with tempfile.TemporaryDirectory() as tmp:
        env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
        env["PYTHONPYCACHEPREFIX"] = str(Path(tmp) / "pycache")
        for i in range(-1, runs):  # run -1 warms the bytecode cache, untimed
            order = ("calibrate", "depthcal") if i % 2 else ("depthcal", "calibrate")
            timed = {kind: _timed([*cellcal, kind, "--config", config, "--no-report", "--quiet", "--out",
                                   f"{tmp}/{kind}{i}"], env) for kind in order}
            if i < 0:
                continue
            for kind in order:
                out[kind].append(timed[kind][0])
                out[f"{kind}_cpu"].append(timed[kind][1])
            doc = json.loads((Path(tmp) / f"depthcal{i}" / "depthcal.json").read_text())
            out["fit"].append(float((doc.get("timings_s") or {}).get("fit", float("nan"))))
    return out


def main() -> int:
    """Measure and print; exit status 1 when the median ratio is over the target."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3, help=f"interleaved pairs (default %(default)s, "
                                                            f"at least {MIN_RUNS})")
    parser.add_argument("--config", default=str(ROOT / "configs" / "sim.toml"), help="the cell (default: %(default)s)")
    args = parser.parse_args()
    if args.runs < MIN_RUNS:
        parser.error(f"--runs {args.runs}: at least {MIN_RUNS} pairs")
    m = measure(args.runs, args.config)
    med = statistics.median
    ratios = [d / c for d, c in zip(m["depthcal"], m["calibrate"], strict=True)]
    cpu = [d / c for d, c in zip(m["depthcal_cpu"], m["calibrate_cpu"], strict=True)]
    ratio = med(ratios)
    verdict = "PASS" if ratio <= TARGET_RATIO else "FAIL"
    print(f"{Path(args.config).name}, medians of {args.runs} interleaved pairs (whole processes, --no-report):")
    print(f"  cellcal calibrate: {med(m['calibrate']):.2f} s wall, {med(m['calibrate_cpu']):.2f} s CPU")
    print(f"  cellcal depthcal:  {med(m['depthcal']):.2f} s wall, {med(m['depthcal_cpu']):.2f} s CPU "
          f"(the fit {med(m['fit']):.2f} s)")
    print(f"  depthcal / calibrate: {ratio:.2f}x wall (pairs {min(ratios):.2f}x-{max(ratios):.2f}x), "
          f"{med(cpu):.2f}x CPU; target <= {TARGET_RATIO:.0f}x: {verdict}")
    return 0 if verdict == "PASS" else 1


if __name__ == "__main__":
    sys.exit(main())
