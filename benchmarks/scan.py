"""How long a network scan of a /24 takes: ``cellcal devices --scan --subnet 127.0.0.0/24``.

Every address of 127.0.0.0/24 is loopback and every port probed is closed, so nothing
outside this machine is touched. Prints, as medians over ``--runs`` runs:

* each network backend's ``scan_hosts`` on the 254 hosts in this process (the sweep and
  the identification, without a child process): target well under the scan's timeout;
* the whole command (every backend, each in its child process, OAK discovery included):
  target ``<= 5 s`` with the default ``--timeout 2``.

The worst case, every host silent, is bounded by design rather than measured here:
the sweep stops at half the timeout (508 connections, 256 at a time, each given at
most a quarter of the timeout), identification at the timeout, a child at the timeout
plus its start-up allowance (ADR 0036).

Usage: python benchmarks/scan.py [--runs N] [--timeout S]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path

SUBNET = "127.0.0.0/24"
TARGET_S = 5.0


def _cellcal() -> list[str]:
    """The ``cellcal`` console script beside this interpreter, else ``python -m cellcal.core.cli``."""
    script = Path(sys.executable).with_name("cellcal")
    return [str(script)] if script.exists() else [sys.executable, "-m", "cellcal.core.cli"]


def _in_process(timeout: float, runs: int) -> None:
    from cellcal.core.cli.scan_targets import parse_subnet
    from cellcal.devices.registry import default_registry

    hosts = parse_subnet(SUBNET)
    registry = default_registry()
    for kind, name in (("camera", "o3r"), ("arm", "xarm"), ("arm", "ur")):
        cls = registry.get(kind, name)  # type: ignore[arg-type]
        times, summary = [], ""
        for _ in range(runs):
            start = time.monotonic()
            report = cls.scan_hosts(hosts, timeout)  # type: ignore[attr-defined]
            times.append(time.monotonic() - start)
            summary = report.summary
        print(f"{name:>5} scan_hosts({SUBNET}): {statistics.median(times):.3f} s median of {runs}  ({summary})")


def _command(timeout: float, runs: int) -> float:
    times = []
    for _ in range(runs):
        start = time.monotonic()
        done = subprocess.run([*_cellcal(), "devices", "--scan", "--subnet", SUBNET, "--timeout", str(timeout)],
                              capture_output=True, text=True, timeout=120, check=False)
        times.append(time.monotonic() - start)
        if done.returncode != 0:
            raise SystemExit(f"cellcal devices --scan failed ({done.returncode}): {done.stderr.strip()}")
    found = [line.strip() for line in done.stdout.split("scan:\n", 1)[1].splitlines()
             if line.strip().split(":")[0] in ("camera o3r", "arm xarm", "arm ur")]
    for line in found:
        print(f"  {line}")
    return statistics.median(times)


def main() -> int:
    """Run both measurements; exit 1 if the command misses its target."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--timeout", type=float, default=2.0)
    args = parser.parse_args()
    _in_process(args.timeout, args.runs)
    median = _command(args.timeout, args.runs)
    verdict = "ok" if median <= TARGET_S else "MISSED"
    print(f"cellcal devices --scan --subnet {SUBNET} --timeout {args.timeout:g}: {median:.2f} s median of "
          f"{args.runs} (target <= {TARGET_S:g} s: {verdict})")
    return 0 if median <= TARGET_S else 1


if __name__ == "__main__":
    raise SystemExit(main())
