"""What the run report adds to ``cellcal calibrate`` on the default sim (target: at most 2 s).

Runs ``cellcal calibrate --quiet --out DIR`` with and without ``--no-report``, interleaved
(so both share the machine's load), each in a fresh output directory, and prints the median
wall time of each and of the difference over ``--runs`` pairs, plus the CPU time (user +
system, the drawing child included) and the time of ``cellcal report DIR --out FILE``
(re-rendering the page from the JSON alone). Bytecode is cached in a temporary
``PYTHONPYCACHEPREFIX`` warmed by one untimed run of each, as for an installed package.

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

#: The issue's limit on what the report may add to the default sim calibrate, s.
TARGET_ADDED_S = 2.0


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


def main() -> int:
    """Measure and print; exit status 1 when the median added time is over the target."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=7, help="interleaved pairs (default %(default)s)")
    args = parser.parse_args()
    cellcal = _cellcal()
    with tempfile.TemporaryDirectory() as tmp:
        env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
        env["PYTHONPYCACHEPREFIX"] = str(Path(tmp) / "pycache")
        with_report: list[tuple[float, float]] = []
        without: list[tuple[float, float]] = []
        rerender: list[float] = []
        for i in range(-1, args.runs):  # run -1 warms the bytecode cache, untimed
            plain = _timed([*cellcal, "calibrate", "--quiet", "--no-report", "--out", f"{tmp}/plain{i}"], env)
            full = _timed([*cellcal, "calibrate", "--quiet", "--out", f"{tmp}/full{i}"], env)
            again = _timed([*cellcal, "report", f"{tmp}/full{i}", "--out", f"{tmp}/again{i}.html"], env)
            if i >= 0:
                without.append(plain)
                with_report.append(full)
                rerender.append(again[0])
        added = [w[0] - p[0] for w, p in zip(with_report, without, strict=True)]
        page = Path(tmp) / f"full{args.runs - 1}"
        sizes = {p.name: p.stat().st_size for p in page.iterdir()}
    med = statistics.median
    print(f"cellcal calibrate on the default sim, medians of {args.runs} interleaved runs:")
    print(f"  without report: {med(w for w, _ in without):.2f} s wall, {med(c for _, c in without):.2f} s CPU")
    print(f"  with report:    {med(w for w, _ in with_report):.2f} s wall, {med(c for _, c in with_report):.2f} s CPU")
    print(f"  added by the report: {med(added):.2f} s wall (min {min(added):.2f}, max {max(added):.2f}); "
          f"target <= {TARGET_ADDED_S:g} s: {'met' if med(added) <= TARGET_ADDED_S else 'NOT met'}")
    print(f"  cellcal report DIR --out FILE (from the JSON alone): {med(rerender):.2f} s wall")
    print(f"  report.html {sizes.get('report.html', 0) / 1e6:.2f} MB, report-data.json "
          f"{sizes.get('report-data.json', 0) / 1e6:.2f} MB, {sum(n.endswith('.png') for n in sizes)} PNGs")
    return 0 if med(added) <= TARGET_ADDED_S else 1


if __name__ == "__main__":
    sys.exit(main())
