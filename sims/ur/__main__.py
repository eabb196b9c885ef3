"""``python -m cellcal.sims.ur --host 127.0.0.N``: serve an emulated UR controller on a loopback address.

Prints one line ``ready <host> rtde=30004 script=30003 dashboard=29999`` once all three
ports listen, then serves until interrupted (Ctrl-C: exit 130; SIGTERM: exit 0). Point
any ur_rtde program at the host, e.g. ``rtde_receive.RTDEReceiveInterface("127.0.0.2")``.
With ``--control`` it also answers JSON commands on stdin (see :mod:`.process`) and
exits when stdin closes.
"""

from __future__ import annotations

import argparse
import json
import logging
import random
import signal
import sys
import threading
from types import FrameType
from typing import Any

from cellcal.devices.base import BackendContext
from cellcal.devices.errors import CellcalError
from cellcal.devices.geometry.vendor_poses import pose_from_ur
from cellcal.sims.arm import SimArm, SimArmConfig

from .emulator import UR_LIKE, UREmulator
from .process import serve_commands

#: Loopback addresses tried for ``--host auto``.
AUTO_HOSTS = [f"127.0.0.{n}" for n in range(2, 255)]


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m cellcal.sims.ur", description=__doc__.splitlines()[0])
    parser.add_argument("--host", default="127.0.0.1",
                        help="loopback address to serve on (default 127.0.0.1; 'auto' picks a free 127.0.0.N)")
    parser.add_argument("--time-scale", type=float, default=None,
                        help="wall seconds per simulated second of motion (default 1 = real time)")
    parser.add_argument("--powered-off", action="store_true", help="start powered off (a real arm does)")
    parser.add_argument("--unlock-delay", type=float, default=5.0,
                        help="seconds before a protective stop may be unlocked (default 5, as on a UR)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the arm's read-back noise")
    parser.add_argument("--arm-config", default="{}", help="JSON object of simulated-arm settings (SimArmConfig)")
    parser.add_argument("--flange-pose", type=float, nargs=6, metavar="V",
                        help="start flange pose x y z rx ry rz (m, rotation vector in rad)")
    parser.add_argument("--control", action="store_true", help="answer JSON commands on stdin (for tests)")
    parser.add_argument("--verbose", action="store_true", help="log every program start/stop and fault to stderr")
    return parser


def _arm(args: argparse.Namespace) -> SimArm:
    try:
        extra: dict[str, Any] = json.loads(args.arm_config)
        if not isinstance(extra, dict):
            raise ValueError("not a JSON object")
    except ValueError as exc:
        raise CellcalError(f"--arm-config must be a JSON object: {exc}") from None
    settings: dict[str, Any] = {**UR_LIKE, "time_scale": 1.0, **extra}
    if args.time_scale is not None:
        settings["time_scale"] = args.time_scale
    try:
        config = SimArmConfig(**settings)
    except TypeError as exc:
        raise CellcalError(f"--arm-config: {exc}") from None
    arm = SimArm(config, BackendContext(seed=args.seed)).connect()
    if args.flange_pose is not None:
        arm.world.arm.set_flange_pose(pose_from_ur(args.flange_pose))
    return arm


def _start(arm: SimArm, args: argparse.Namespace) -> UREmulator:
    hosts = [args.host]
    if args.host == "auto":
        hosts = random.sample(AUTO_HOSTS, len(AUTO_HOSTS))
    error: OSError | None = None
    for host in hosts[:64]:
        emulator = UREmulator(arm, host, powered=not args.powered_off, unlock_delay_s=args.unlock_delay)
        try:
            emulator.start()
        except OSError as exc:
            error = exc
            continue
        return emulator
    raise CellcalError(f"cannot listen on {args.host} (ports 30004, 30003, 29999): {error}")


def main(argv: list[str] | None = None) -> int:
    """Run the emulator until interrupted (or stdin closes with ``--control``); returns the exit status."""
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING, stream=sys.stderr,
                        format="ur-emulator: %(levelname)s %(message)s")
    try:
        arm = _arm(args)
    except CellcalError as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return 1
    try:
        emulator = _start(arm, args)
    except CellcalError as exc:
        arm.close()
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return 1
    done = threading.Event()
    status = {"code": 0}

    def _on_signal(signum: int, _frame: FrameType | None) -> None:
        status["code"] = 130 if signum == signal.SIGINT else 0
        done.set()

    previous = {sig: signal.signal(sig, _on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        print(f"ready {emulator.host} rtde=30004 script=30003 dashboard=29999", flush=True)
        if args.control:
            def control() -> None:
                serve_commands(emulator, sys.stdin, sys.stdout)
                done.set()  # stdin closed or "quit": the controlling process is gone

            threading.Thread(target=control, name="ur-emulator control", daemon=True).start()
        while not done.wait(0.5):
            pass
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        emulator.close()
        arm.close()
    return status["code"]


if __name__ == "__main__":
    sys.exit(main())
