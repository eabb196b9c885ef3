"""The ACME Z1 backend: the cellcal conformance kit, plus what only this camera promises.

Run against the installed package (``pip install .`` then ``pytest``): the entry
point test needs the distribution's metadata, as cellcal itself does.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from cellcal.core.cli import main
from cellcal.devices import ConfigError, DeviceTimeoutError, default_registry
from cellcal.testing import CameraConformance, CameraOptions, check_camera

from acme_cellcal.camera import RANGE_M, AcmeZ1Camera

HERE = Path(__file__).resolve().parent


# ---------------------------------------------------------------- the kit, one test per contract rule
class TestAcmeZ1Conformance(CameraConformance):
    options = CameraOptions(distance_range_m=RANGE_M)

    def make_camera(self) -> AcmeZ1Camera:
        return AcmeZ1Camera.from_config({"serial": "Z1-000417", "frame_rate_hz": 60.0})


def test_kit_function_api_also_passes_at_low_frame_rate() -> None:
    # at 5 Hz a 0.25 s capture may time out: the kit accepts DeviceTimeoutError there, in bounded time
    report = check_camera(lambda: AcmeZ1Camera.from_config({"frame_rate_hz": 5.0}),
                          CameraOptions(distance_range_m=RANGE_M))
    assert report.ok and report.backend == "acme-z1" and len(report.results) == 14


# ---------------------------------------------------------------- registration
def test_found_through_the_entry_point() -> None:
    registry = default_registry()
    assert registry.get("camera", "acme-z1") is AcmeZ1Camera
    (entry,) = [e for e in registry.entries("camera") if e.name == "acme-z1"]
    assert entry.origin == "cellcal-acme-camera 0.1.0" and entry.target == "acme_cellcal.camera:AcmeZ1Camera"


def test_cellcal_devices_lists_and_scans_it(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["devices", "--scan", "--timeout", "0.5"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"\n  acme-z1 +acme_cellcal\.camera:AcmeZ1Camera  \[cellcal-acme-camera 0\.1\.0\]\n", out)
    assert "camera acme-z1: ACME Z1 Z1-000417" in out and "camera acme-z1: ACME Z1 Z1-000842" in out


def test_a_cell_config_builds_it(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["calibrate", "--check", "--config", str(HERE.parent / "acme_cell.toml")]) == 0
    assert "camera:  backend 'acme-z1' (acme_cellcal.camera.AcmeZ1Camera)" in capsys.readouterr().out


# ---------------------------------------------------------------- this camera's own promises
def test_sees_the_configured_plane() -> None:
    tilt_deg, dist_m = 25.0, 1.5
    with AcmeZ1Camera.from_config({"plane_tilt_deg": tilt_deg, "plane_distance_m": dist_m, "noise_m": 0.0}) as cam:
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
    with pytest.raises(ConfigError, match="frame_rate_hz"):
        AcmeZ1Camera.from_config({"frame_rate_hz": 0})
    with pytest.raises(ConfigError, match=r"exposure.*unknown key"):
        AcmeZ1Camera.from_config({"exposure": 3})


def test_unknown_serial_is_a_connection_error() -> None:
    from cellcal.devices import DeviceConnectionError

    cam = AcmeZ1Camera.from_config({"serial": "Z1-999999"})
    with pytest.raises(DeviceConnectionError, match=r"Z1-999999.*ACME error 404"):
        cam.connect(1.0)
    assert not cam.connected


def test_no_frame_before_the_next_period_is_a_timeout() -> None:
    with AcmeZ1Camera.from_config({"frame_rate_hz": 1.0}) as cam:
        cam.capture(0.5)                                      # frame 0 is ready at once
        with pytest.raises(DeviceTimeoutError, match=r"no frame within 0\.05 s"):
            cam.capture(0.05)                                 # frame 1 is ~1 s away
