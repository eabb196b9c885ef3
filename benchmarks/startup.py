"""Start-up cost of the ``cellcal`` command, measured against a bare interpreter in the same run.

Prints, as medians over ``--runs`` interleaved runs (so the three commands share the
machine's load):

* ``cellcal --help`` against ``python -c pass``: the ratio (target, issue #38: <= 3.5x),
  with PASS or FAIL;
* ``cellcal calibrate --out DIR`` on the default sim (README, Quick start): wall time
  end to end (target: under 0.4 s, PASS or FAIL), also as a ratio to the bare interpreter;
* the CPU time (user + system) of each, which a loaded machine disturbs less;
* with ``--imports``, the ten most expensive imports of each ``cellcal`` command
  (``python -X importtime``, cumulative).

The children run with compiled bytecode cached in a temporary ``PYTHONPYCACHEPREFIX``
(warmed by one untimed run each), as an installed package would; the source tree is
not written to.

Usage: python benchmarks/startup.py [--runs N] [--imports]
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

HELP_TARGET_RATIO = 3.5
CALIBRATE_TARGET_S = 0.4


def _cellcal() -> list[str]:
    """The ``cellcal`` console script beside this interpreter, else ``python -m cellcal.core.cli``."""
    script = Path(sys.executable).with_name("cellcal")
    return [str(script)] if script.exists() else [sys.executable, "-m", "cellcal.core.cli"]


def _env(cache: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPYCACHEPREFIX"] = cache
    return env


def _timed(cmd: list[str], env: dict[str, str]) -> tuple[float, float]:
    """(wall s, CPU s of the child) of one run; the command must succeed."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def _top_imports(cmd: list[str], env: dict[str, str], n: int = 10) -> list[tuple[float, str]]:
    """The ``n`` imports with the largest cumulative time (ms) in one ``-X importtime`` run."""
    full = [sys.executable, "-X", "importtime", *(cmd[1:] if cmd[0] == sys.executable else cmd)]
    err = subprocess.run(full, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True).stderr
    rows = []
    for line in err.splitlines():
        if line.startswith("import time:") and "|" in line:
            _, cumulative, name = (part.strip() for part in line[len("import time:"):].split("|"))
            if cumulative.isdigit() and "." not in name.strip():  # top-level packages only
                rows.append((int(cumulative) / 1000.0, name.strip()))
    return sorted(rows, reverse=True)[:n]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=15, help="timed runs of each command (default 15)")
    parser.add_argument("--imports", action="store_true", help="also list the most expensive imports")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryDirectory() as out:
        env = _env(cache)
        commands = {
            "python -c pass": [sys.executable, "-c", "pass"],
            # the floor of calibrate: the two compiled libraries it cannot run without
            "import numpy, cv2": [sys.executable, "-c", "import numpy, cv2"],
            "cellcal --help": [*_cellcal(), "--help"],
            "cellcal calibrate": [*_cellcal(), "calibrate", "--out", out],
        }
        for cmd in commands.values():  # warm the bytecode cache and the disk cache
            _timed(cmd, env)
        walls: dict[str, list[float]] = {k: [] for k in commands}
        cpus: dict[str, list[float]] = {k: [] for k in commands}
        for _ in range(args.runs):
            for name, cmd in commands.items():
                wall, cpu = _timed(cmd, env)
                walls[name].append(wall)
                cpus[name].append(cpu)
        med = {k: statistics.median(v) for k, v in walls.items()}
        cpu = {k: statistics.median(v) for k, v in cpus.items()}
        bare = med["python -c pass"]
        print(f"median over {args.runs} interleaved runs (wall / CPU):")
        for name in commands:
            print(f"  {name:<18} {med[name] * 1000:7.1f} ms / {cpu[name] * 1000:6.1f} ms   "
                  f"(min wall {min(walls[name]) * 1000:.1f} ms; {med[name] / bare:.2f}x the bare interpreter)")
        ratio = med["cellcal --help"] / bare
        print(f"cellcal --help: {ratio:.2f}x a bare interpreter start measured in the same run "
              f"(target <= {HELP_TARGET_RATIO:g}x: {'PASS' if ratio <= HELP_TARGET_RATIO else 'FAIL'}); CPU ratio "
              f"{cpu['cellcal --help'] / cpu['python -c pass']:.2f}x")
        cal = med["cellcal calibrate"]
        print(f"cellcal calibrate (default sim, end to end): {cal:.3f} s (target < {CALIBRATE_TARGET_S} s: "
              f"{'PASS' if cal < CALIBRATE_TARGET_S else 'FAIL'}); CPU {cpu['cellcal calibrate']:.3f} s")
        floor = med["import numpy, cv2"]
        print(f"  of which the floor (interpreter + numpy + OpenCV import): {floor:.3f} s; cellcal's own "
              f"imports and the 3-pose run: {cal - floor:.3f} s")
        if args.imports:
            for name in ("cellcal --help", "cellcal calibrate"):
                top = ", ".join(f"{mod} {ms:.0f}" for ms, mod in _top_imports(commands[name], env))
                print(f"top imports of {name} (cumulative ms): {top}")


if __name__ == "__main__":
    main()
