"""The o3r-ifm3d backend with ifm3dpy in a worker process (``isolate = true``, the default; ADR 0063),
against the O3R emulator (a subprocess, as in test_o3r_ifm3d_backend.py, which runs the conformance kit
with the default, isolated).

Frames through the worker's shared-memory ring equal those of ifm3dpy in this process bit for bit
(noise off: a static scene); the worker killed while it waits for a frame (the emulator stopped) is a
NativeCrashError, its ring unlinked from /dev/shm, and the next connect() starts a new worker.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import DeviceTimeoutError, NativeCrashError
from cellcal.devices.registry import default_registry

pytest.importorskip("ifm3dpy.framegrabber")

ARRAYS = ("distance", "xyz", "amplitude", "valid", "confidence")
SHM = Path("/dev/shm")


@pytest.fixture
def emulator() -> Iterator[tuple[subprocess.Popen[str], int]]:
    """The standalone emulator in RUN, noise off; yields the process and its XML-RPC port."""
    proc = subprocess.Popen([sys.executable, "-m", "cellcal.sims.o3r", "--xmlrpc-port", "0", "--pcic-port", "0",
                             "--state", "RUN", "--frame-rate", "20", "--state-change-s", "0.1", "--no-noise"],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert "ready" in line, line
        yield proc, int(line.split("xmlrpc=127.0.0.1:")[1].split()[0])
    finally:
        proc.send_signal(signal.SIGCONT)
        proc.terminate()
        proc.wait(timeout=10)


def camera(xport: int, isolate: bool) -> Camera3D:
    return default_registry().create_camera({"backend": "o3r-ifm3d", "host": "127.0.0.1", "xmlrpc_port": xport,
                                             "isolate": isolate})


def _segments() -> set[str]:
    """This process's shared-memory segments (the ring's names carry the parent's pid)."""
    return {p.name for p in SHM.iterdir() if p.name.startswith(f"cellcal_{os.getpid()}_")}


def test_frames_through_the_worker_equal_ifm3dpy_in_process(emulator: tuple[subprocess.Popen[str], int]) -> None:
    _, xport = emulator
    with camera(xport, isolate=True) as isolated, camera(xport, isolate=False) as here:
        assert isolated.worker_pid not in (None, os.getpid())  # type: ignore[attr-defined]
        a, b = isolated.capture(5.0), here.capture(5.0)
        assert isolated.intrinsics == here.intrinsics == a.intrinsics
        assert isolated.info() == here.info() and isolated.measurement_model == here.measurement_model
    for name in ARRAYS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape
        assert x.tobytes() == y.tobytes(), name  # bit for bit, NaN included (a static, noise-free scene)
    assert a.valid.mean() > 0.9 and a.measurement == b.measurement
    assert a.metadata.keys() == b.metadata.keys() and a.metadata["tof_info_version"] == 4
    assert not _segments()


def test_a_worker_killed_mid_capture_is_a_native_crash_and_connect_starts_a_new_one(
        emulator: tuple[subprocess.Popen[str], int]) -> None:
    proc, xport = emulator
    cam = camera(xport, isolate=True)
    cam.connect(timeout=10.0)
    try:
        cam.capture(5.0)
        (ring,) = _segments()
        host = cam._worker.host  # type: ignore[attr-defined]
        pid = host.pid
        proc.send_signal(signal.SIGSTOP)                       # no frame comes: the capture waits in the worker
        for _ in range(20):                                    # ... once those already sent are taken
            try:
                cam.capture(1.0)
            except DeviceTimeoutError:
                break
        else:
            pytest.fail("frames kept coming from the stopped emulator")

        def kill_when_waiting() -> None:
            end = time.monotonic() + 30.0
            while not host._lock.locked():                     # the capture's call is out, its reply awaited
                assert time.monotonic() < end
                time.sleep(0.01)
            os.kill(pid, signal.SIGKILL)

        killer = threading.Thread(target=kill_when_waiting)
        killer.start()
        with pytest.raises(NativeCrashError, match=r"died during capture\(timeout=60 s\).*SIGKILL") as err:
            cam.capture(60.0)                                  # a crash, not this timeout
        killer.join(5.0)
        assert err.value.backend == "o3r-ifm3d" and err.value.signal_name == "SIGKILL"
        assert ring not in _segments() and not _segments()
        with pytest.raises(NativeCrashError, match="died earlier"):
            cam.info()
        proc.send_signal(signal.SIGCONT)
        cam.connect(timeout=10.0)                              # a new worker
        assert cam.worker_pid not in (None, pid)  # type: ignore[attr-defined]
        assert cam.capture(5.0).valid.mean() > 0.9
    finally:
        proc.send_signal(signal.SIGCONT)
        cam.close()
    assert not _segments()
