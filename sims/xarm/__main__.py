"""``python -m cellcal.sims.xarm [--axes 5]``: serve an emulated xArm on a pty.

Prints the pty path as the first line of output, then serves until interrupted
(Ctrl-C / SIGTERM). Point any xArm serial client at the printed path, e.g.
``XArmAPI("/dev/pts/7")`` from ``xarm-python-sdk``.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from types import FrameType

from cellcal.sims.arm import SimArm, SimArmConfig

from .emulator import XArmEmulator


def main(argv: list[str] | None = None) -> int:
    """Run the emulator until SIGINT/SIGTERM; returns the exit status."""
    parser = argparse.ArgumentParser(prog="python -m cellcal.sims.xarm", description=__doc__.splitlines()[0])
    parser.add_argument("--axes", type=int, choices=(5, 6, 7), default=5, help="axis count reported (default 5)")
    parser.add_argument("--time-scale", type=float, default=1.0,
                        help="wall seconds per simulated second of motion (default 1 = real time)")
    parser.add_argument("--ready", action="store_true", help="start enabled and ready (a real arm starts stopped)")
    args = parser.parse_args(argv)
    if not 0.0 <= args.time_scale <= 10.0:
        parser.error("--time-scale must be within [0, 10]")

    done = threading.Event()

    def _on_signal(_signum: int, _frame: FrameType | None) -> None:
        done.set()

    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)
    arm = SimArm(SimArmConfig(time_scale=args.time_scale)).connect()
    emulator = XArmEmulator(arm, axes=args.axes, start_ready=args.ready)
    try:
        path = emulator.start()
        print(path, flush=True)
        start = arm.get_pose()
        print(f"xArm {args.axes} emulator serving; flange at "
              f"{[round(float(v), 4) for v in start.as_xyz_rpy()]} (m, rad); Ctrl-C to stop",
              file=sys.stderr, flush=True)
        while not done.wait(0.5):
            pass
    finally:
        emulator.close()
        arm.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
