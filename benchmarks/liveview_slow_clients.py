"""A minute of viewers that never read: the live view's memory and the run's end (issue #31).

``cellcal monitor --viz-port`` runs for ``--seconds`` (default 60) with four clients that subscribe
to every channel and then never read a byte, and 200 connections that never finish a handshake
(tests/support/hostile_viewer.py: raw WebSocket over a plain socket). The command's resident memory
is sampled every 0.25 s. Targets: at most 150 MB throughout, flat (the last half adds < 20 MB to
the first half's peak), and the run ends within 15 s of ``--duration``. Exit 1 if one is missed.

Usage: python benchmarks/liveview_slow_clients.py [--seconds S]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests" / "support"))

from hostile_viewer import monitor_with_slow_viewers
from ports import free_port

TARGET_MB = 150.0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    args = parser.parse_args(argv)
    run = monitor_with_slow_viewers(free_port(), args.seconds)
    early, late = run.peaks_mb(args.seconds)
    peak = max(mb for _, mb in run.samples)
    print(f"{args.seconds:g} s of monitor with 4 viewers that never read and 200 idle connections: resident "
          f"memory peak {peak:.1f} MB (target <= {TARGET_MB:g}), first half {early:.1f} MB, second half "
          f"{late:.1f} MB ({late - early:+.1f} MB); the run ended {run.ended_after_s - args.seconds:+.1f} s after "
          f"--duration (exit {run.returncode})")
    ok = peak <= TARGET_MB and late - early < 20.0 and run.ended_after_s < args.seconds + 15.0 and run.returncode == 0
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
