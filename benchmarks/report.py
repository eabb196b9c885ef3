"""What the run report costs on ``cellcal calibrate`` on the default sim, as a ratio to the run (target: <= 1.0x).

Runs ``cellcal calibrate --quiet --out DIR`` as whole processes with and without
``--no-report``, interleaved (so both share the machine's load; the order alternates within
a pair), each in a fresh output directory. A pair's cost ratio is (wall with the report - wall
without) / wall without; the figure judged is the median over ``--runs`` pairs (at least 5).
Also printed: the medians of each, the CPU time (user + system, children included) and its
ratio, and the time of ``cellcal report DIR --out FILE`` (re-rendering the page from the JSON
alone). Bytecode is cached in a temporary ``PYTHONPYCACHEPREFIX`` warmed by one untimed run
of each, as for an installed package. Timing on a loaded machine is noisy: the figures that
count are a quiet machine's.

Usage: python benchmarks/report.py [--runs N]
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

#: The issue's limit on the report's cost: at most the run's own time.
TARGET_RATIO = 1.0
#: Fewest interleaved pairs the median is taken over.
MIN_RUNS = 5


def _cellcal() -> list[str]:
    """The ``cellcal`` console script beside this interpreter, else ``python -m cellcal.core.cli``."""
    script = Path(sys.executable).with_name("cellcal")
    return [str(script)] if script.exists() else [sys.executable, "-m", "cellcal.core.cli"]


def _timed(cmd: list[str], env: dict[str, str]) -> tuple[float, float]:
    """(wall s, CPU s of the child and its children) of one run; the command must succeed."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=300)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def measure(runs: int) -> dict[str, list[float]]:
    """``runs`` interleaved pairs (and the re-rendering after each): wall and CPU seconds, page sizes (bytes)."""
    cellcal = _cellcal()
    out: dict[str, list[float]] = {k: [] for k in ("plain", "plain_cpu", "full", "full_cpu", "again", "html",
                                                   "data", "pngs")}
    with tempfile.TemporaryDirectory() as tmp:
        env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
        env["PYTHONPYCACHEPREFIX"] = str(Path(tmp) / "pycache")
        for i in range(-1, runs):  # run -1 warms the bytecode cache, untimed
            # the order within a pair alternates, so neither side always runs first after a re-rendering
            order = ("plain", "full") if i % 2 else ("full", "plain")
            timed = {}
            for kind in order:
                extra = ["--no-report"] if kind == "plain" else []
                timed[kind] = _timed([*cellcal, "calibrate", "--quiet", *extra, "--out", f"{tmp}/{kind}{i}"], env)
            again = _timed([*cellcal, "report", f"{tmp}/full{i}", "--out", f"{tmp}/again{i}.html"], env)
            if i < 0:
                continue
            for kind in ("plain", "full"):
                out[kind].append(timed[kind][0])
                out[f"{kind}_cpu"].append(timed[kind][1])
            out["again"].append(again[0])
            page = Path(tmp) / f"full{i}"
            out["html"].append((page / "report.html").stat().st_size)
            out["data"].append((page / "report-data.json").stat().st_size)
            out["pngs"].append(len(list(page.glob("*.png"))))
    return out


def main() -> int:
    """Measure and print; exit status 1 when the median cost ratio is over the target."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=7, help=f"interleaved pairs (default %(default)s, "
                                                            f"at least {MIN_RUNS})")
    args = parser.parse_args()
    if args.runs < MIN_RUNS:
        parser.error(f"--runs {args.runs}: at least {MIN_RUNS} pairs")
    m = measure(args.runs)
    med = statistics.median
    ratios = [(f - p) / p for f, p in zip(m["full"], m["plain"], strict=True)]
    cpu_ratios = [(f - p) / p for f, p in zip(m["full_cpu"], m["plain_cpu"], strict=True)]
    ratio = med(ratios)
    verdict = "PASS" if ratio <= TARGET_RATIO else "FAIL"
    print(f"cellcal calibrate on the default sim, medians of {args.runs} interleaved pairs (whole processes):")
    print(f"  without report: {med(m['plain']):.2f} s wall, {med(m['plain_cpu']):.2f} s CPU")
    print(f"  with report:    {med(m['full']):.2f} s wall, {med(m['full_cpu']):.2f} s CPU")
    print(f"  report cost / run: {ratio:.2f}x wall (pairs {min(ratios):.2f}x-{max(ratios):.2f}x), "
          f"target <= {TARGET_RATIO:.1f}x: {verdict}")
    print(f"  report cost / run: {med(cpu_ratios):.2f}x CPU")
    print(f"  cellcal report DIR --out FILE (from the JSON alone): {med(m['again']):.2f} s wall")
    print(f"  report.html {med(m['html']) / 1e6:.2f} MB, report-data.json {med(m['data']) / 1e6:.2f} MB, "
          f"{int(med(m['pngs']))} PNGs")
    return 0 if verdict == "PASS" else 1


if __name__ == "__main__":
    sys.exit(main())
