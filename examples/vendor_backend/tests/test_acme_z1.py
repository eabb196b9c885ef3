"""The ACME Z1 backend: the cellcal conformance kit against a fake Z1 on TCP port 0, plus its own promises.

Run against the installed package (``pip install .`` then ``pytest``): the entry point
test needs the distribution's metadata, as cellcal itself does.
"""

from __future__ import annotations

import math
import re
import socket
import threading
from collections.abc import Callable, Iterator

import numpy as np
import pytest
from cellcal.core.cli import main
from cellcal.devices import ConfigError, DeviceConnectionError, DeviceTimeoutError, ProtocolError, default_registry
from cellcal.testing import CameraConformance, CameraOptions, ScenePlane, check_camera

from acme_cellcal import wire
from acme_cellcal.camera import RANGE_M, Z1_MODEL, AcmeZ1Camera
from acme_cellcal.emulated import AcmeZ1EmulatedCamera
from acme_cellcal.fake_device import FakeZ1, FakeZ1Settings

#: What the fake Z1 shows without a simulated cell: a plane 1.2 m ahead on the optical axis, tilted 20 deg about
#: the camera's x axis (FakeZ1Settings' defaults); the kit runs calibrate's full-frame fit on it.
_FIXED = FakeZ1Settings()
SCENE = ScenePlane(normal=(0.0, math.sin(math.radians(_FIXED.plane_tilt_deg)),
                           -math.cos(math.radians(_FIXED.plane_tilt_deg))), axis_distance_m=_FIXED.plane_distance_m)
OPTIONS = CameraOptions(distance_range_m=RANGE_M, scene_plane=SCENE)


def camera_at(device: FakeZ1, **keys: object) -> AcmeZ1Camera:
    """An unconnected ``acme-z1`` camera pointed at ``device``, built from a config table as cellcal would."""
    return AcmeZ1Camera.from_config({"host": "127.0.0.1", "port": device.port, **keys})


# ---------------------------------------------------------------- the kit, one test per contract rule
class TestAcmeZ1Conformance(CameraConformance):
    """Every contract rule against a fake Z1 this fixture starts on 127.0.0.1, port 0."""

    options = OPTIONS

    @pytest.fixture
    def camera_factory(self) -> Iterator[Callable[[], AcmeZ1Camera]]:
        with FakeZ1(FakeZ1Settings(frame_rate_hz=60.0)) as device:   # started before the test, stopped after
            yield lambda: camera_at(device)

    @pytest.fixture
    def stalled_camera_factory(self) -> Iterator[Callable[[], AcmeZ1Camera]]:
        with FakeZ1(stalled=True) as device:                          # answers INFO, never a GRAB
            yield lambda: camera_at(device)


def test_kit_function_api_also_passes_at_low_frame_rate() -> None:
    # at 5 Hz a 0.25 s capture may time out: the kit accepts DeviceTimeoutError there, in bounded time
    with FakeZ1(FakeZ1Settings(frame_rate_hz=5.0)) as device:
        report = check_camera(lambda: camera_at(device), OPTIONS, quiet=True)
    assert report.ok and report.backend == "acme-z1" and len(report.results) == 17


def test_a_z1_too_small_for_the_default_plan_fails_the_kit_as_calibrate_refuses_it() -> None:
    """A 64 x 48 Z1 passed the 15 rules of the kit before, and `cellcal calibrate` refused it (issue #37)."""
    with FakeZ1(FakeZ1Settings(width=64, height=48, frame_rate_hz=60.0)) as device:
        report = check_camera(lambda: camera_at(device), OPTIONS, raise_on_failure=False, quiet=True)
    (failure,) = report.failures
    assert failure.rule == "camera.calibrate-image"
    assert failure.detail.endswith(
        "refuses this camera before the arm moves: perimeters 30, 40, 50 px put the P1-P9 grid with its 3 px "
        "sampling windows outside the 64x48 image (at most 22.5 px from the principal point (31.5, 23.5) px); use "
        "perimeters_px of at most 22 px")


def test_the_z1_states_its_model_and_the_frames_measure_up_to_it() -> None:
    # a wall 1 m ahead, face on: every pixel's Z is 1 m + noise, sent in whole millimetres
    with FakeZ1(FakeZ1Settings(plane_tilt_deg=0.0, plane_distance_m=1.0)) as device, camera_at(device) as cam:
        frame = cam.capture(2.0)
        model = cam.measurement_model
    assert model == Z1_MODEL and model.kind == "tof" and model.source == "backend"
    assert frame.measurement == model
    z = frame.xyz[..., 2][frame.valid].astype(np.float64)
    predicted = float(model.range_sigma_m(1.0))          # 1 mm noise and the 1 mm step's 0.29 mm: 1.041 mm
    assert predicted == pytest.approx(math.sqrt(0.001 ** 2 + 0.001 ** 2 / 12))
    assert z.size > 10_000 and np.std(z - 1.0) == pytest.approx(predicted, rel=0.05)


def test_the_emulated_backend_passes_the_kit() -> None:
    report = check_camera(lambda: AcmeZ1EmulatedCamera.from_config({"frame_rate_hz": 60.0}), OPTIONS, quiet=True)
    assert report.ok and report.backend == "acme-z1-emulated"


# ---------------------------------------------------------------- registration
def test_found_through_the_entry_points() -> None:
    registry = default_registry()
    assert registry.get("camera", "acme-z1") is AcmeZ1Camera
    assert registry.get("camera", "acme-z1-emulated") is AcmeZ1EmulatedCamera
    (entry,) = [e for e in registry.entries("camera") if e.name == "acme-z1"]
    assert entry.origin == "cellcal-acme-camera 0.1.0" and entry.target == "acme_cellcal.camera:AcmeZ1Camera"


def test_cellcal_devices_lists_it_and_scan_says_no_discovery(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["devices", "--scan", "--hosts", "127.0.0.1", "--timeout", "0.5"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"\n  acme-z1 +acme_cellcal\.camera:AcmeZ1Camera  \[cellcal-acme-camera 0\.1\.0\]\n", out)
    assert re.search(r"\n  camera acme-z1: no discovery", out)


# ---------------------------------------------------------------- this camera's own promises
def test_sees_the_configured_plane() -> None:
    tilt_deg, dist_m = 25.0, 1.5
    with FakeZ1(FakeZ1Settings(plane_tilt_deg=tilt_deg, plane_distance_m=dist_m, noise_m=0.0)) as device, \
            camera_at(device) as cam:
        frame = cam.capture(2.0)
    p = frame.xyz[frame.valid].astype(np.float64)
    centroid = p.mean(axis=0)
    normal = np.linalg.svd(p - centroid, full_matrices=False)[2][-1]  # least-squares plane normal
    normal *= -np.sign(normal[2])                             # facing the camera
    assert math.degrees(math.acos(abs(normal[2]))) == pytest.approx(tilt_deg, abs=0.05)
    # the plane crosses the optical axis at dist_m: solve n . (t * z_axis - centroid) = 0
    assert float(normal @ centroid / normal[2]) == pytest.approx(dist_m, abs=0.001)
    assert np.nanmax(np.abs(frame.distance[frame.valid] - np.linalg.norm(p, axis=1))) < 1e-5


def test_config_errors_name_the_key() -> None:
    with pytest.raises(ConfigError, match="port"):
        AcmeZ1Camera.from_config({"port": 0})
    with pytest.raises(ConfigError, match=r"exposure.*unknown key"):
        AcmeZ1Camera.from_config({"exposure": 3})


def test_nobody_listening_is_a_connection_error() -> None:
    with socket.create_server(("127.0.0.1", 0)) as s:
        port = s.getsockname()[1]                             # a port that was free a moment ago
    cam = AcmeZ1Camera.from_config({"host": "127.0.0.1", "port": port})
    with pytest.raises(DeviceConnectionError, match=rf"cannot reach 127\.0\.0\.1:{port}"):
        cam.connect(1.0)
    assert not cam.connected


def test_no_frame_before_the_next_period_is_a_timeout_and_the_camera_recovers() -> None:
    with FakeZ1(FakeZ1Settings(frame_rate_hz=2.0)) as device, camera_at(device) as cam:
        first = cam.capture(0.5)                              # frame 0 is ready at once
        with pytest.raises(DeviceTimeoutError, match=r"no frame within"):
            cam.capture(0.05)                                 # frame 1 is ~0.5 s away
        assert cam.capture(1.0).sequence > first.sequence


def test_a_stalled_device_times_out_in_time_and_the_link_is_reopened() -> None:
    with FakeZ1(stalled=True) as device, camera_at(device) as cam:
        for _ in range(2):
            with pytest.raises(DeviceTimeoutError, match="no reply to GRAB"):
                cam.capture(0.1)
        device.stalled = False
        assert cam.capture(1.0).valid_fraction > 0.9


def test_a_lying_device_is_a_protocol_error() -> None:
    with socket.create_server(("127.0.0.1", 0)) as server:
        cam = AcmeZ1Camera.from_config({"host": "127.0.0.1", "port": server.getsockname()[1]})
        conn = None
        try:
            server.settimeout(2.0)

            def answer() -> None:
                nonlocal conn
                conn, _ = server.accept()
                conn.recv(wire.REQUEST.size)
                conn.sendall(wire.HEADER.pack(wire.REPLY_INFO, 0, 1 << 30))   # a 1 GiB "INFO" reply

            t = threading.Thread(target=answer)
            t.start()
            with pytest.raises(ProtocolError, match="bad reply header"):
                cam.connect(2.0)
            t.join()
        finally:
            if conn is not None:
                conn.close()
