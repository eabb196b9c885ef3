"""The OAK backend with depthai in a worker process (``isolate = true``, the default; ADR 0063).

The device is the streaming fake of oak_in_worker.py (test_oak.py's real depthai queues and
messages, autospecced device and nodes), installed in the worker by the camera's
``worker_factory``. Frames through the worker's shared-memory ring equal the in-process ones bit
for bit; a worker killed in the middle of a capture is a NativeCrashError, its ring unlinked
from /dev/shm, and the next connect() starts a new worker; the conformance kit passes.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

dai = pytest.importorskip("depthai")
import oak_in_worker  # noqa: E402
from test_oak import DEVICE_ID, H, W  # noqa: E402

from cellcal.devices.errors import NativeCrashError  # noqa: E402
from cellcal.drivers.oak.camera import OakCamera  # noqa: E402
from cellcal.testing import CAMERA_RULES, CameraOptions, check_camera  # noqa: E402

HERE = Path(__file__).parent
SUPPORT = HERE.parents[2] / "support"
ARRAYS = ("distance", "xyz", "amplitude", "valid")
SHM = Path("/dev/shm")


class WorkerOak(OakCamera):
    """The OAK backend whose worker opens the streaming fake instead of a device."""

    worker_factory = "oak_in_worker:make_camera"


@pytest.fixture
def control(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """The worker finds oak_in_worker.py and test_oak.py, and the stall switch in ``control``."""
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(HERE), str(SUPPORT), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setenv("CELLCAL_TEST_OAK_DIR", str(tmp_path))
    return tmp_path


def camera(isolate: bool = True) -> OakCamera:
    config = {"backend": "oak", "device_id": DEVICE_ID, "width": W, "height": H, "amplitude": "none",
              "isolate": isolate}
    return (WorkerOak if isolate else OakCamera).from_config(config)


def _segments() -> set[str]:
    """This process's shared-memory segments (the ring's names carry the parent's pid)."""
    return {p.name for p in SHM.iterdir() if p.name.startswith(f"cellcal_{os.getpid()}_")}


def _wait_for(path: Path, limit_s: float = 30.0) -> None:
    end = time.monotonic() + limit_s
    while not path.exists():
        assert time.monotonic() < end, f"{path} did not appear"
        time.sleep(0.01)


@pytest.fixture
def isolated(control: Path) -> Iterator[OakCamera]:
    cam = camera().connect(timeout=20.0)
    yield cam
    cam.close()


def test_frames_through_the_worker_equal_the_in_process_ones(isolated: OakCamera, mocker: Any) -> None:
    oak_in_worker.patch_depthai(mocker.patch.object)
    with camera(isolate=False) as here:
        for _ in range(3):
            a, b = isolated.capture(5.0), here.capture(5.0)
            assert a.sequence == b.sequence
            for name in ARRAYS:
                x, y = getattr(a, name), getattr(b, name)
                assert x.dtype == y.dtype and x.shape == y.shape
                assert x.tobytes() == y.tobytes(), name  # bit for bit, NaN included
            assert a.intrinsics == b.intrinsics == isolated.intrinsics == here.intrinsics
            assert a.measurement == b.measurement and a.measurement.kind == "stereo"
        assert isolated.info() == here.info() and isolated.measurement_model == here.measurement_model
    assert 0.5 < a.valid_fraction < 1.0 and np.isnan(a.xyz[~a.valid]).all()
    assert isolated.worker_pid not in (None, os.getpid())


def test_a_worker_killed_mid_capture_is_a_native_crash_and_connect_starts_a_new_one(
        isolated: OakCamera, control: Path) -> None:
    isolated.capture(5.0)
    (ring,) = _segments()                                   # made at the first frame
    pid = isolated.worker_pid
    assert pid is not None
    (control / "stall").touch()                             # no frame comes: the capture waits in the worker

    def kill_when_waiting() -> None:
        _wait_for(control / "waiting")
        os.kill(pid, signal.SIGKILL)

    killer = threading.Thread(target=kill_when_waiting)
    killer.start()
    with pytest.raises(NativeCrashError, match=r"died during capture\(timeout=60 s\).*SIGKILL") as err:
        isolated.capture(60.0)                              # a crash, not this timeout
    killer.join(5.0)
    assert err.value.signal_name == "SIGKILL" and err.value.backend == "oak"
    assert ring not in _segments() and not _segments()      # unlinked at the crash
    with pytest.raises(NativeCrashError, match="died earlier"):
        isolated.capture(1.0)                               # every later call, at once
    (control / "stall").unlink()
    isolated.connect(timeout=20.0)                          # a new worker
    assert isolated.worker_pid not in (None, pid)
    frame = isolated.capture(5.0)
    assert frame.shape == (H, W) and frame.sequence == 1    # a new worker, a new fake device
    isolated.close()
    assert not _segments()


def test_close_unlinks_the_ring_and_ends_the_worker(control: Path) -> None:
    cam = camera().connect(timeout=20.0)
    pid = cam.worker_pid
    cam.capture(5.0)
    assert len(_segments()) == 1
    cam.close()
    assert not _segments() and cam.worker_pid is None
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)                                     # reaped by close


def test_the_isolated_oak_passes_the_conformance_kit(control: Path) -> None:
    # as test_device_contract.py's run of the in-process OAK: the fake's 64x40 output, one depth per pixel
    options = CameraOptions(distance_range_m=(0.2, 10.0), perimeters_px=(10, 17),
                            scene_reason="the mocked depthai sends random depths, no scene")
    report = check_camera(camera, options)
    assert report.backend == "oak" and [r.rule for r in report.results] == list(CAMERA_RULES)
    assert report.ok, report
    assert not _segments()
