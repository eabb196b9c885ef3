"""Run the O3R emulator standalone: ``python -m cellcal.sims.o3r [--pcic-base-port 50010] [--xmlrpc-port 80]``.

Serves simulated O3R222 heads (by default one, 3D on ``port2`` and 2D on port0; ``--heads
port2,port3`` serves two, their 2D on port0 and port1), the IMU on port6 and an application
instance ``app0``, numbered as a VPU numbers them (50010 + N, 51010), on 127.0.0.1 (the
shared simulated world's default scene, seen from the simulated arm's initial pose; a
further head stands where ``--head-pose`` puts it relative to the first), and prints one line
containing ``ready`` once every port listens. ``--frames per_pose`` renders once per arm pose
and adds fresh noise per frame, which serves load rates (``--frame-rate 1000 --max-frame-rate
5000``). Stop it with Ctrl-C / SIGTERM.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import re
import signal
import sys
import threading
from typing import Any

#: Where the k-th further head stands by default, in the first head's optical frame: k x this shift (m) along x,
#: turned by k x this angle (deg) about y, so that every head sees the scene from its own place.
DEFAULT_HEAD_SHIFT_M = 0.1
DEFAULT_HEAD_TURN_DEG = 10.0


def _heads(text: str) -> list[str]:
    """``port2,port3``: VPU ports of the 3D heads, each once."""
    names = [t.strip() for t in text.split(",") if t.strip()]
    bad = [n for n in names if not re.fullmatch(r"port[0-5]", n)]
    if not names or bad or len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(f"expected distinct ports port0..port5 separated by commas, got {text!r}")
    return names


def _head_pose(text: str) -> tuple[str, tuple[float, ...]]:
    """``PORT=X,Y,Z,ROLL,PITCH,YAW`` (m, deg)."""
    port, _, values = text.partition("=")
    try:
        numbers = tuple(float(v) for v in values.split(","))
    except ValueError:
        numbers = ()
    if not re.fullmatch(r"port[0-5]", port.strip()) or len(numbers) != 6 or not all(map(math.isfinite, numbers)):
        raise argparse.ArgumentTypeError(f"expected PORT=X,Y,Z,ROLL,PITCH,YAW (m, deg), got {text!r}")
    return port.strip(), numbers


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m cellcal.sims.o3r", description=__doc__.splitlines()[0])
    ap.add_argument("--xmlrpc-port", type=int, default=80, help="XML-RPC port (default 80; 0 = ephemeral)")
    ap.add_argument("--pcic-base-port", type=int, default=50010,
                    help="PCIC port of port0 (default 50010); portN = base + N, port6 = base + 6, app0 = base + 1000")
    ap.add_argument("--pcic-port", type=int, default=None,
                    help="PCIC port of the first 3D head alone (0 = ephemeral); the other ports are then ephemeral")
    ap.add_argument("--port-name", default="port2", help="VPU port of the 3D head (one head; see --heads)")
    ap.add_argument("--heads", type=_heads, default=None, metavar="PORT,PORT...",
                    help="VPU ports with a 3D head, e.g. port2,port3 (default: --port-name); the first is 'pcic='")
    ap.add_argument("--head-pose", type=_head_pose, action="append", default=[], metavar="PORT=X,Y,Z,R,P,Y",
                    help="a further head's pose in the first head's optical frame (m, deg; roll, pitch, yaw about "
                         f"fixed x, y, z); default: the k-th further head {DEFAULT_HEAD_SHIFT_M:g} m x k along x, "
                         f"turned {DEFAULT_HEAD_TURN_DEG:g} deg x k about y")
    ap.add_argument("--state", choices=("RUN", "IDLE", "CONF"), default="RUN", help="initial port state")
    ap.add_argument("--frame-rate", type=float, default=20.0, help="frames per second in RUN")
    ap.add_argument("--max-frame-rate", type=float, default=30.0, help="largest frame rate the VPU accepts")
    ap.add_argument("--mode", default="standard_range4m", help="mode of the 3D heads, e.g. cyclic_4m_2m_4m_2m")
    ap.add_argument("--confidence-bits", type=int, choices=(8, 16), default=16, help="confidence image depth")
    ap.add_argument("--header-version", type=int, choices=(1, 2, 3), default=None,
                    help="one chunk header version for all chunks (default: the mix a real VPU sends)")
    ap.add_argument("--tof-info-version", type=int, choices=(1, 2, 3, 4), default=4, help="TOF_INFO version")
    ap.add_argument("--clock", choices=("boot", "unix"), default="boot", help="device clock (default: since boot)")
    ap.add_argument("--state-change-s", type=float, default=0.3, help="how long a state change takes, s")
    ap.add_argument("--frames", choices=("per_frame", "per_pose"), default="per_frame",
                    help="render every frame, or once per arm pose with fresh noise per frame")
    ap.add_argument("--seed", type=int, default=0, help="seed of the simulated world (head k's noise: seed + k)")
    ap.add_argument("--no-noise", action="store_true", help="render noise-free frames")
    ap.add_argument("--no-distortion", action="store_true", help="pinhole lens")
    ap.add_argument("--no-systematic", action="store_true",
                    help="an ideal camera: no systematic depth error ([sim.systematic] enabled = false, ADR 0054)")
    return ap


def head_offsets(heads: list[str], given: list[tuple[str, tuple[float, ...]]]) -> dict[str, tuple[float, ...]]:
    """Each further head's pose in the first head's optical frame (x, y, z m; roll, pitch, yaw deg)."""
    poses = {p: v for p, v in given}
    unknown = sorted(set(poses) - set(heads[1:]))
    if unknown:
        raise SystemExit(f"error: --head-pose for {', '.join(unknown)}, which is not a further head of --heads")
    return {name: poses.get(name, (DEFAULT_HEAD_SHIFT_M * k, 0.0, 0.0, 0.0, DEFAULT_HEAD_TURN_DEG * k, 0.0))
            for k, name in enumerate(heads) if k > 0}


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit status."""
    args = _parser().parse_args(argv)
    heads: list[str] = args.heads or [args.port_name]
    offsets = head_offsets(heads, args.head_pose)

    from cellcal.devices.base import BackendContext
    from cellcal.devices.pose import Pose
    from cellcal.sims.camera import SimCamera, SimCameraConfig

    from .emulator import O3REmulator
    from .frames import OffsetView

    per_pose = args.frames == "per_pose"
    cfg = SimCameraConfig(noise=not (args.no_noise or per_pose), distortion=not args.no_distortion,
                          frame_rate_hz=min(args.frame_rate, 1000.0))  # the sim's own clock step
    document: dict[str, Any] = {"sim": {"systematic": {"enabled": False}}} if args.no_systematic else {}
    cam = SimCamera(cfg, BackendContext(seed=args.seed, document=document)).connect()
    further: dict[str, Any] = {}
    for k, name in enumerate(heads[1:], start=1):
        x, y, z, roll, pitch, yaw = offsets[name]
        other = SimCamera(dataclasses.replace(cfg, seed=args.seed + k), world=cam.world).connect()
        further[name] = OffsetView(other, Pose.from_xyz_rpy([x, y, z], [math.radians(a) for a in (roll, pitch, yaw)]))
    base = None if args.pcic_port is not None else args.pcic_base_port
    emu = O3REmulator(cam, xmlrpc_port=args.xmlrpc_port, pcic_port=args.pcic_port or 0, pcic_base_port=base,
                      heads=further, port_name=heads[0], state=args.state, frame_rate_hz=args.frame_rate,
                      max_frame_rate_hz=max(args.max_frame_rate, args.frame_rate), mode=args.mode,
                      confidence_bits=args.confidence_bits, header_version=args.header_version,
                      tof_info_version=args.tof_info_version, clock=args.clock, state_change_s=args.state_change_s,
                      frames=args.frames, noise_scale=0.0 if args.no_noise else 1.0)
    try:
        emu.start()
    except OSError as exc:
        print(f"error: cannot listen: {exc}", file=sys.stderr)
        return 2
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    ports = " ".join(f"{name}={p.port}" for name, p in sorted(emu.ports.items()))
    print(f"O3R emulator ready: xmlrpc=127.0.0.1:{emu.xmlrpc_port} pcic=127.0.0.1:{emu.pcic_port} "
          f"port={heads[0]} heads={','.join(heads)} state={args.state} ports: {ports}", flush=True)
    try:
        while not done.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        emu.close()
        for view in further.values():
            view.camera.close()
        cam.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
