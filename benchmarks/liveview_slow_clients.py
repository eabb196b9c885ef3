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
import socket
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests" / "support"))

from hostile_viewer import WAIT_S, rss_mb, subscribe_all_and_stop_reading
from ports import free_port

TARGET_MB = 150.0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    args = parser.parse_args(argv)
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "cellcal.core.cli", "monitor", "--duration", str(args.seconds),
                             "--quiet", "--viz-port", str(port)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    sockets: list[socket.socket] = []
    samples: list[tuple[float, float]] = []
    try:
        assert proc.stderr is not None and "live view:" in proc.stderr.readline()
        started = time.monotonic()
        sockets += [subscribe_all_and_stop_reading(port) for _ in range(4)]
        sockets += [socket.create_connection(("127.0.0.1", port), timeout=WAIT_S) for _ in range(200)]
        while proc.poll() is None and time.monotonic() - started < args.seconds + WAIT_S:
            samples.append((time.monotonic() - started, rss_mb(proc.pid)))
            time.sleep(0.25)
        proc.communicate(timeout=WAIT_S)
        ended = time.monotonic() - started
    finally:
        for sock in sockets:
            sock.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    half = args.seconds / 2
    early = max(mb for t, mb in samples if 1.0 < t <= half)
    late = max(mb for t, mb in samples if t > half)
    peak = max(mb for _, mb in samples)
    print(f"{args.seconds:g} s of monitor with 4 viewers that never read and 200 idle connections: resident "
          f"memory peak {peak:.1f} MB (target <= {TARGET_MB:g}), first half {early:.1f} MB, second half "
          f"{late:.1f} MB ({late - early:+.1f} MB); the run ended {ended - args.seconds:+.1f} s after --duration "
          f"(exit {proc.returncode})")
    ok = peak <= TARGET_MB and late - early < 20.0 and ended < args.seconds + 15.0 and proc.returncode == 0
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
