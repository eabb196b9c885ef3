"""O3R over PCIC on loopback: the emulator's serving rate, and the driver against ifm3dpy on the same stream.

Two parts, each against the standalone emulator (``python -m cellcal.sims.o3r``) in its
own process, 224 x 172 frames with chunks 100/101/300/420:

* ``emulator`` -- the emulator in RUN at an unreachable frame rate (``--frames
  per_pose``: one render per arm pose, fresh noise per frame, one reused encode
  buffer), as a PCIC client on loopback receives it: a bare client (connect, ``p1``,
  then ``recv_into`` one buffer, no decoding) counts the bytes of whole frames it got
  in ``--seconds``. The loopback floor is measured in the same run, interleaved with
  the emulator (``--repeats`` each): a sender process doing nothing but ``sendall`` of
  one message of the same size to the same client. Printed: the medians, the
  emulator's share of the floor, the target (issue #38: >= 8000 frames/s) and PASS or
  FAIL.
* ``peer`` -- at 30 and 100 Hz, the cellcal ``o3r`` driver (free run, ``capture``)
  and ifm3dpy's ``FrameGrabber`` (distance, XYZ, confidence, amplitude buffers copied
  to numpy, as the driver hands them out) each consume the stream in a process of
  their own: CPU seconds per frame of that process, and the latency from the
  timestamp the emulator stamps into each frame (``--clock unix``: the sender's
  ``time.time()`` when it encoded the frame) to the frame in the consumer's hands.
  Target (issue #18): driver <= 0.5x ifm3dpy in CPU and latency, each printed with PASS
  or FAIL. A bare reader (whole messages into one buffer, no decoding) shows the
  transport floor of the latency.

    python benchmarks/pcic_ingest.py [--part emulator|peer|all] [--seconds 3] [--repeats 3]
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing as mp
import socket
import statistics
import subprocess
import sys
import time
from collections.abc import Iterator

#: Frames each consumer takes per rate (after a warm-up of 10).
WARMUP = 10
#: The driver's CPU and latency per frame against ifm3dpy's (issue #18).
PEER_TARGET_RATIO = 0.5


@contextlib.contextmanager
def emulator(rate_hz: float) -> Iterator[tuple[int, int]]:
    """The standalone emulator streaming at ``rate_hz`` (Unix clock, per-pose frames); yields (xml-rpc, PCIC) ports."""
    proc = subprocess.Popen([sys.executable, "-m", "cellcal.sims.o3r", "--xmlrpc-port", "0", "--pcic-port", "0",
                             "--state", "RUN", "--frames", "per_pose", "--clock", "unix", "--frame-rate",
                             str(rate_hz), "--max-frame-rate", str(max(rate_hz, 30.0))],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        if "ready" not in line:
            raise RuntimeError(f"emulator did not start: {line!r}")
        yield (int(line.split("xmlrpc=127.0.0.1:")[1].split()[0]), int(line.split("pcic=127.0.0.1:")[1].split()[0]))
    finally:
        proc.terminate()
        proc.wait(timeout=10)


# ---------------------------------------------------------------------- part 1: the emulator's rate
#: Frames/s the emulator must serve to a bare client (issue #38).
EMULATOR_TARGET_FPS = 8000.0
#: A sender of nothing but ``sendall`` of one message, to ``argv[1]``'s port, ``argv[2]`` bytes long.
_FLOOR_SENDER = """
import os, socket, sys
s = socket.create_connection(("127.0.0.1", int(sys.argv[1])))
s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
msg = memoryview(bytearray(os.urandom(int(sys.argv[2]))))  # real bytes: a zeroed buffer maps one page
try:
    while True:
        s.sendall(msg)
except OSError:
    pass
"""


def _count(s: socket.socket, seconds: float, size: int) -> float:
    """Whole ``size``-byte messages per second a bare client reads from ``s`` (after a 0.5 s warm-up)."""
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    buf = memoryview(bytearray(4 << 20))
    t_end = time.perf_counter() + 0.5
    while time.perf_counter() < t_end:
        s.recv_into(buf)
    total = 0
    t0 = time.perf_counter()
    while (now := time.perf_counter()) - t0 < seconds:
        total += s.recv_into(buf)
    return (total // size) / (now - t0)


def _emulator_rate(pcic: int, seconds: float) -> tuple[float, int]:
    """Frames/s the emulator serves to a fresh bare client, and the message size in bytes."""
    with socket.create_connection(("127.0.0.1", pcic), timeout=5.0) as s:
        s.sendall(b"1002L000000008\r\n1002p1\r\n")
        reply = len(b"1002L000000007\r\n1002*\r\n")
        head = b""
        while len(head) < reply + 16:  # the reply, then the first frame's header
            head += s.recv(reply + 16 - len(head))
        size = 16 + int(head[reply + 5:reply + 14])
        return _count(s, seconds, size), size


def _floor_rate(size: int, seconds: float) -> float:
    """Frames/s of ``size`` bytes a bare ``sendall`` loop in its own process gets to the same client."""
    with socket.create_server(("127.0.0.1", 0)) as lst:
        proc = subprocess.Popen([sys.executable, "-c", _FLOOR_SENDER, str(lst.getsockname()[1]), str(size)])
        try:
            lst.settimeout(10.0)
            conn, _ = lst.accept()
            with conn:
                return _count(conn, seconds, size)
        finally:
            proc.terminate()
            proc.wait(timeout=10)


def serve_rate(seconds: float, repeats: int) -> None:
    """Print the emulator's frames/s to a bare client against the loopback floor, interleaved, with the target."""
    emu_rates, floor_rates = [], []
    with emulator(100000.0) as (_, pcic):
        size = _emulator_rate(pcic, 0.2)[1]
        for _ in range(repeats):
            floor_rates.append(_floor_rate(size, seconds))
            emu_rates.append(_emulator_rate(pcic, seconds)[0])
    emu, floor = statistics.median(emu_rates), statistics.median(floor_rates)
    print(f"emulator: 224x172 frames of {size} bytes to a bare client over loopback, median of {repeats} "
          f"interleaved runs of {seconds:g} s")
    print(f"  loopback floor (a process doing only sendall): {floor:7.0f} frames/s  "
          f"(runs: {', '.join(f'{r:.0f}' for r in floor_rates)})")
    print(f"  emulator (--frames per_pose):                  {emu:7.0f} frames/s  "
          f"(runs: {', '.join(f'{r:.0f}' for r in emu_rates)}); {emu * size / 1e6:.0f} MB/s, "
          f"{emu / floor:.2f}x the floor")
    verdict = "PASS" if emu >= EMULATOR_TARGET_FPS else "FAIL"
    print(f"  target >= {EMULATOR_TARGET_FPS:.0f} frames/s: {emu:.0f} -> {verdict}"
          + ("" if verdict == "PASS" or floor >= EMULATOR_TARGET_FPS else
             " (the loopback floor itself is below the target on this machine now)"))


# ---------------------------------------------------------------------- part 2: driver vs ifm3dpy
def _driver_consumer(xport: int, frames: int, out: mp.Queue) -> None:  # type: ignore[type-arg]
    from cellcal.drivers.o3r.camera import O3RCamera, O3RConfig

    cam = O3RCamera(O3RConfig(host="127.0.0.1", xmlrpc_port=xport, set_state=False)).connect(timeout=5.0)
    lat: list[float] = []
    try:
        for _ in range(WARMUP):
            cam.capture(5.0)
        cpu0 = time.process_time()
        for _ in range(frames):
            f = cam.capture(5.0)
            lat.append(time.time() - f.metadata["device_timestamp_s"])
        cpu = time.process_time() - cpu0
    finally:
        cam.close()
    out.put((cpu / frames, lat))


def _ifm3dpy_consumer(xport: int, pport: int, frames: int, out: mp.Queue) -> None:  # type: ignore[type-arg]
    import numpy as np
    from ifm3dpy.device import O3R
    from ifm3dpy.framegrabber import FrameGrabber, buffer_id

    b = buffer_id
    fg = FrameGrabber(O3R("127.0.0.1", xport), pcic_port=pport)
    fg.start([b.RADIAL_DISTANCE_IMAGE, b.XYZ, b.CONFIDENCE_IMAGE, b.NORM_AMPLITUDE_IMAGE]).wait_for(5000)
    lat: list[float] = []
    seen = -1
    taken = 0
    try:
        cpu0 = 0.0
        while taken < frames + WARMUP:
            ok, frame = fg.wait_for_frame().wait_for(5000)
            if not ok or frame.frame_count() == seen:  # wait_for_frame can hand out the last frame again
                continue
            seen = frame.frame_count()
            for buf in (b.RADIAL_DISTANCE_IMAGE, b.XYZ, b.CONFIDENCE_IMAGE, b.NORM_AMPLITUDE_IMAGE):
                np.array(frame.get_buffer(buf))
            taken += 1
            if taken == WARMUP:
                cpu0 = time.process_time()
            elif taken > WARMUP:
                lat.append(time.time() - frame.timestamps()[0].timestamp())
        cpu = time.process_time() - cpu0
    finally:
        fg.stop().wait_for(5000)
    out.put((cpu / frames, lat))


def _bare_consumer(pport: int, frames: int, out: mp.Queue) -> None:  # type: ignore[type-arg]
    """The transport floor: whole messages read into one buffer, no decoding; latency at the last byte."""
    import struct

    lat: list[float] = []
    with socket.create_connection(("127.0.0.1", pport), timeout=5.0) as s:
        s.sendall(b"1002L000000008\r\n1002p1\r\n")
        buf = bytearray(1 << 20)
        view = memoryview(buf)
        cpu0 = 0.0
        taken = -1  # the first message is the reply to p1
        while taken < frames + WARMUP:
            _recv_exact(s, view[:16])
            length = int(buf[5:14])
            _recv_exact(s, view[16:16 + length])
            if taken == WARMUP:
                cpu0 = time.process_time()
            if taken >= WARMUP:
                # first chunk header: PCIC header (16), ticket (4), "star" (4); TIME_STAMP_SEC/NSEC at 0x28
                sec, nsec = struct.unpack_from("<2I", buf, 24 + 0x28)
                lat.append(time.time() - (sec + nsec * 1e-9))
            taken += 1
        cpu = time.process_time() - cpu0
    out.put((cpu / frames, lat))


def _recv_exact(s: socket.socket, view: memoryview) -> None:
    got = 0
    while got < len(view):
        n = s.recv_into(view[got:])
        if n == 0:
            raise ConnectionError("the emulator closed the stream")
        got += n


def _run(target: object, *args: object) -> tuple[float, list[float]]:
    ctx = mp.get_context("spawn")
    q: mp.Queue = ctx.Queue()  # type: ignore[type-arg]
    proc = ctx.Process(target=target, args=(*args, q))  # type: ignore[arg-type]
    proc.start()
    result = q.get(timeout=120)
    proc.join(timeout=30)
    return result  # type: ignore[no-any-return]


def _p95(values: list[float]) -> float:
    return sorted(values)[int(0.95 * (len(values) - 1))]


def peer(seconds: float, repeats: int) -> None:
    """Print CPU per frame and latency of the driver and of ifm3dpy at 30 and 100 Hz.

    The two clients take turns ``repeats`` times on one stream; CPU is the median of
    the runs, latencies are pooled (the machine is shared: single runs are noisy).
    """
    try:
        import ifm3dpy  # noqa: F401
    except ImportError:
        print("peer: ifm3dpy is not installed (pip install ifm3dpy): skipped")
        return
    print(f"{'rate':>6} {'client':>8} {'CPU/frame':>10} {'lat median':>11} {'lat p95':>9}   ({repeats} runs each)")
    for rate in (30.0, 100.0):
        frames = max(30, int(rate * seconds))
        d_cpus, i_cpus, d_lat, i_lat = [], [], [], []
        with emulator(rate) as (xport, pport):
            b_cpu, b_lat = _run(_bare_consumer, pport, frames)
            for _ in range(repeats):
                cpu, lat = _run(_driver_consumer, xport, frames)
                d_cpus.append(cpu)
                d_lat += lat
                cpu, lat = _run(_ifm3dpy_consumer, xport, pport, frames)
                i_cpus.append(cpu)
                i_lat += lat
        d_cpu, i_cpu = statistics.median(d_cpus), statistics.median(i_cpus)
        rows = (("bare", b_cpu, b_lat), ("cellcal", d_cpu, d_lat), ("ifm3dpy", i_cpu, i_lat))
        for name, cpu, lat in rows:
            print(f"{rate:5.0f}Hz {name:>8} {cpu * 1e3:8.2f}ms {statistics.median(lat) * 1e3:9.2f}ms "
                  f"{_p95(lat) * 1e3:7.2f}ms")
        ratios = (d_cpu / i_cpu, statistics.median(d_lat) / statistics.median(i_lat), _p95(d_lat) / _p95(i_lat))
        verdicts = ["PASS" if r <= PEER_TARGET_RATIO else "FAIL" for r in ratios]
        print(f"        ratio driver/ifm3dpy (target <= {PEER_TARGET_RATIO:g}x): CPU {ratios[0]:.2f}x {verdicts[0]}, "
              f"latency median {ratios[1]:.2f}x {verdicts[1]}, p95 {ratios[2]:.2f}x {verdicts[2]}; the bare "
              f"reader's latency is the transport floor both pay")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", choices=("emulator", "peer", "all"), default="all")
    ap.add_argument("--seconds", type=float, default=3.0, help="measuring time per run, s")
    ap.add_argument("--repeats", type=int, default=3,
                    help="runs of the emulator and of the loopback floor, interleaved; runs per client and rate (peer)")
    args = ap.parse_args()
    if args.part in ("emulator", "all"):
        serve_rate(args.seconds, args.repeats)
    if args.part in ("peer", "all"):
        peer(args.seconds, args.repeats)


if __name__ == "__main__":
    main()
