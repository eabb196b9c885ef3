"""The o3r-ifm3d backend (ifm's ifm3dpy) against the O3R emulator: the conformance kit, and agreement with the
own o3r driver on the same stream. ifm3dpy's calls hold the GIL, so the emulator runs as a subprocess."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator

import numpy as np
import pytest

from cellcal.devices.camera import Camera3D
from cellcal.devices.registry import default_registry
from cellcal.testing import CAMERA_RULES, CameraOptions, ScenePlane, check_camera

pytest.importorskip("ifm3dpy.framegrabber")

MM = 0.001


def _emulator(*options: str) -> Iterator[int]:
    """The standalone emulator in RUN with ``options``; yields its XML-RPC port."""
    proc = subprocess.Popen([sys.executable, "-m", "cellcal.sims.o3r", "--xmlrpc-port", "0", "--pcic-port", "0",
                             "--state", "RUN", "--frame-rate", "20", "--state-change-s", "0.1", *options],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert "ready" in line, line
        yield int(line.split("xmlrpc=127.0.0.1:")[1].split()[0])
    finally:
        proc.terminate()
        proc.wait(timeout=10)


@pytest.fixture(scope="module")
def emulator() -> Iterator[int]:
    """Noise off: a static scene gives equal frames."""
    yield from _emulator("--no-noise")


@pytest.fixture(scope="module")
def noisy_emulator() -> Iterator[int]:
    """With the simulated camera's noise: what calibrate's fit needs from a ToF camera stating the O3R's."""
    yield from _emulator()


def camera(backend: str, xport: int, **kw: object) -> Camera3D:
    return default_registry().create_camera({"backend": backend, "host": "127.0.0.1", "xmlrpc_port": xport, **kw})


def test_o3r_ifm3d_passes_the_conformance_kit(noisy_emulator: int) -> None:
    # the emulator's simulated camera, with no plan, sees the table straight below it, 0.44 m away (without its
    # noise, calibrate's residual_floor gate refuses the frames: 0.13 x the data-sheet noise the backend states)
    options = CameraOptions(distance_range_m=(0.1, 4.0), scene_plane=ScenePlane((0.0, 0.0, 1.0), 0.44))
    report = check_camera(lambda: camera("o3r-ifm3d", noisy_emulator), options, quiet=True)
    assert [r.rule for r in report.results] == list(CAMERA_RULES)
    assert report.ok


def test_o3r_ifm3d_agrees_with_the_own_driver(emulator: int) -> None:
    ifm, own = camera("o3r-ifm3d", emulator), camera("o3r", emulator)
    with ifm, own:
        a, b = ifm.capture(5.0), own.capture(5.0)
        assert ifm.intrinsics == own.intrinsics  # both from TOF_INFO's inverse model 1
        info = ifm.info()
    assert info.backend == "o3r-ifm3d" and info.extra["client"] == "ifm3dpy"
    assert np.array_equal(a.valid, b.valid) and a.valid.mean() > 0.9
    ok = a.valid
    assert np.max(np.abs(a.distance[ok] - b.distance[ok])) < 0.01 * MM
    # ifm3dpy's user-frame XYZ taken back to the optical frame meets the own driver's optical XYZ
    assert np.max(np.abs(a.xyz[ok] - b.xyz[ok])) < 0.1 * MM
    assert a.metadata["tof_info_version"] == 4 and a.metadata["timestamp_source"] == "receive"
    assert a.metadata["device_timestamp_s"] == pytest.approx(b.metadata["device_timestamp_s"], abs=5.0)
