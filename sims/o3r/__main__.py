"""Run the O3R emulator standalone: ``python -m cellcal.sims.o3r --xmlrpc-port N --pcic-port M``.

Serves one simulated O3R222 3D head on ``port2`` (the shared simulated world's
default scene, seen from the simulated arm's initial pose) on 127.0.0.1 and prints
one line containing ``ready`` once both ports listen. Stop it with Ctrl-C / SIGTERM.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit status."""
    ap = argparse.ArgumentParser(prog="python -m cellcal.sims.o3r", description=__doc__.splitlines()[0])
    ap.add_argument("--xmlrpc-port", type=int, default=80, help="XML-RPC port (default 80; 0 = ephemeral)")
    ap.add_argument("--pcic-port", type=int, default=50012, help="PCIC port of port2 (default 50012; 0 = ephemeral)")
    ap.add_argument("--port-name", default="port2", help="VPU port of the 3D head")
    ap.add_argument("--state", choices=("RUN", "IDLE", "CONF"), default="RUN", help="initial port state")
    ap.add_argument("--frame-rate", type=float, default=20.0, help="frames per second in RUN")
    ap.add_argument("--seed", type=int, default=0, help="seed of the simulated world")
    ap.add_argument("--no-noise", action="store_true", help="render noise-free frames")
    ap.add_argument("--no-distortion", action="store_true", help="pinhole lens")
    args = ap.parse_args(argv)

    from cellcal.devices.base import BackendContext
    from cellcal.sims.camera import SimCamera, SimCameraConfig

    from .emulator import O3REmulator

    cfg = SimCameraConfig(noise=not args.no_noise, distortion=not args.no_distortion,
                            frame_rate_hz=args.frame_rate)
    cam = SimCamera(cfg, BackendContext(seed=args.seed)).connect()
    emu = O3REmulator(cam, xmlrpc_port=args.xmlrpc_port, pcic_port=args.pcic_port, port_name=args.port_name,
                      state=args.state, frame_rate_hz=args.frame_rate)
    try:
        emu.start()
    except OSError as exc:
        print(f"error: cannot listen: {exc}", file=sys.stderr)
        return 2
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    print(f"O3R emulator ready: xmlrpc=127.0.0.1:{emu.xmlrpc_port} pcic=127.0.0.1:{emu.pcic_port} "
          f"port={args.port_name} state={args.state}", flush=True)
    try:
        while not done.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        emu.close()
        cam.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
