"""``python -m cellcal.sims.xarm [--axes 5] [--tcp-port P --report-port Q]``: serve an emulated xArm.

Serial (default): prints the pty path as the first line of output. TCP (``--tcp-port``
and/or ``--report-port``; 0 = a free port): serves the control port and the rich report
stream on 127.0.0.1 and prints ``ready 127.0.0.1 tcp=P report=Q`` once both listen. Then
serves until interrupted (Ctrl-C / SIGTERM). Point any xArm client at it, e.g.
``XArmAPI("/dev/pts/7")`` from ``xarm-python-sdk``, or cellcal's ``xarm`` backend with
``host = "127.0.0.1"``, ``tcp_port = P``, ``report_port = Q``.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from types import FrameType

from cellcal.sims.arm import SimArm, SimArmConfig

from .emulator import XArmEmulator
from .tcp_server import XArmTcpServer


def main(argv: list[str] | None = None) -> int:
    """Run the emulator until SIGINT/SIGTERM; returns the exit status."""
    parser = argparse.ArgumentParser(prog="python -m cellcal.sims.xarm", description=__doc__.splitlines()[0])
    parser.add_argument("--axes", type=int, choices=(5, 6, 7), default=5, help="axis count reported (default 5)")
    parser.add_argument("--time-scale", type=float, default=1.0,
                        help="wall seconds per simulated second of motion (default 1 = real time)")
    parser.add_argument("--ready", action="store_true", help="start enabled and ready (a real arm starts stopped)")
    parser.add_argument("--tcp-port", type=int, default=None, help="serve TCP: control port (0 = free port)")
    parser.add_argument("--report-port", type=int, default=None, help="serve TCP: rich report port (0 = free port)")
    parser.add_argument("--report-hz", type=float, default=20.0, help="reports per second over TCP (default 20)")
    args = parser.parse_args(argv)
    if not 0.0 <= args.time_scale <= 10.0:
        parser.error("--time-scale must be within [0, 10]")
    for name in ("tcp_port", "report_port"):
        value = getattr(args, name)
        if value is not None and not 0 <= value <= 65535:
            parser.error(f"--{name.replace('_', '-')} must be within [0, 65535]")
    if not 0.5 <= args.report_hz <= 1000.0:
        parser.error("--report-hz must be within [0.5, 1000]")

    done = threading.Event()

    def _on_signal(_signum: int, _frame: FrameType | None) -> None:
        done.set()

    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)
    arm = SimArm(SimArmConfig(time_scale=args.time_scale)).connect()
    emulator = XArmEmulator(arm, axes=args.axes, start_ready=args.ready)
    tcp = args.tcp_port is not None or args.report_port is not None
    server = XArmTcpServer(emulator, tcp_port=args.tcp_port or 0, report_port=args.report_port or 0,
                           report_hz=args.report_hz) if tcp else None
    try:
        if server is not None:
            try:
                control, report = server.start()
            except OSError as exc:
                print(f"error: cannot listen on 127.0.0.1: {exc}", file=sys.stderr, flush=True)
                return 1
            print(f"ready {server.host} tcp={control} report={report}", flush=True)
        else:
            print(emulator.start(), flush=True)
        start = arm.get_pose()
        print(f"xArm {args.axes} emulator serving; flange at "
              f"{[round(float(v), 4) for v in start.as_xyz_rpy()]} (m, rad); Ctrl-C to stop",
              file=sys.stderr, flush=True)
        while not done.wait(0.5):
            pass
    finally:
        if server is not None:
            server.close()
        emulator.close()
        arm.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
