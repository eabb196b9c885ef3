"""The official client agrees: ifm3dpy (ifm's own library) against the emulator.

ifm3dpy's calls hold the GIL, so the emulator runs in a subprocess (the standalone
``python -m cellcal.sims.o3r``); noise is off, so every frame of the static scene has
the same content and ifm3dpy's frame can be compared with the cellcal driver's.
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator

import numpy as np
import pytest

from cellcal.drivers.o3r.camera import O3RCamera, O3RConfig

ifm3dpy_device = pytest.importorskip("ifm3dpy.device")
ifm3dpy_fg = pytest.importorskip("ifm3dpy.framegrabber")

MM = 0.001


@pytest.fixture
def emulator() -> Iterator[tuple[int, int]]:
    proc = subprocess.Popen([sys.executable, "-m", "cellcal.sims.o3r", "--xmlrpc-port", "0", "--pcic-port", "0",
                             "--state", "RUN", "--frame-rate", "20", "--no-noise"],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert "ready" in line, line
        xport = int(line.split("xmlrpc=127.0.0.1:")[1].split()[0])
        pport = int(line.split("pcic=127.0.0.1:")[1].split()[0])
        yield xport, pport
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_ifm3dpy_frames_agree_with_cellcal_driver(emulator: tuple[int, int]) -> None:
    xport, pport = emulator
    o3r = ifm3dpy_device.O3R("127.0.0.1", xport)
    assert o3r.get(["/ports/port2/info/features/type"]) == {"ports": {"port2": {"info": {"features": {"type": "3D"}}}}}
    assert o3r.get(["/ports/port2/data/pcicTCPPort"])["ports"]["port2"]["data"]["pcicTCPPort"] == pport
    # a user frame that differs from the optical frame, set through ifm3dpy
    o3r.set({"ports": {"port2": {"processing": {"extrinsicHeadToUser": {"transX": 0.1, "rotY": 0.2}}}}})

    B = ifm3dpy_fg.buffer_id
    fg = ifm3dpy_fg.FrameGrabber(o3r, pcic_port=pport)
    ok, _ = fg.start([B.RADIAL_DISTANCE_IMAGE, B.XYZ, B.CONFIDENCE_IMAGE, B.NORM_AMPLITUDE_IMAGE]).wait_for(5000)
    assert ok
    try:
        ok, frame = fg.wait_for_frame().wait_for(5000)
        assert ok
        ifm_dist = np.array(frame.get_buffer(B.RADIAL_DISTANCE_IMAGE), dtype=np.float32)
        ifm_xyz = np.array(frame.get_buffer(B.XYZ), dtype=np.float32)
        ifm_conf = np.array(frame.get_buffer(B.CONFIDENCE_IMAGE))
        assert frame.frame_count() >= 1
    finally:
        fg.stop().wait_for(5000)

    optical = O3RCamera(O3RConfig(host="127.0.0.1", xmlrpc_port=xport)).connect(timeout=3.0)
    user = O3RCamera(O3RConfig(host="127.0.0.1", xmlrpc_port=xport, xyz_frame="user")).connect(timeout=3.0)
    try:
        ours, ours_user = optical.capture(3.0), user.capture(3.0)
    finally:
        optical.close()
        user.close()

    assert ifm_dist.shape == ours.distance.shape == (172, 224)
    valid = ours.valid
    assert valid.mean() > 0.9
    assert np.array_equal(valid, (ifm_conf & 1) == 0)
    assert np.max(np.abs(ifm_dist[valid] - ours.distance[valid])) < 1 * MM
    assert np.all(ifm_xyz[~valid] == 0)  # ifm marks invalid pixels with 0, cellcal with NaN
    # ifm3d's XYZ is in the user frame: compare with the driver in that frame ...
    assert np.max(np.abs(ifm_xyz[valid] - ours_user.xyz[valid])) < 1 * MM
    # ... and, after undoing the extrinsic, with the optical-frame XYZ
    shift = np.max(np.abs(ifm_xyz[valid] - ours.xyz[valid]))
    assert shift > 0.05  # the user frame really differs (0.1 m, 0.2 rad)
    assert np.max(np.abs(np.linalg.norm(ifm_xyz[valid] - [0.1, 0, 0], axis=1)
                         - np.linalg.norm(ours.xyz[valid], axis=1))) < 1 * MM


def test_ifm3dpy_software_trigger(emulator: tuple[int, int]) -> None:
    xport, pport = emulator
    o3r = ifm3dpy_device.O3R("127.0.0.1", xport)
    o3r.set({"ports": {"port2": {"state": "IDLE"}}})
    B = ifm3dpy_fg.buffer_id
    fg = ifm3dpy_fg.FrameGrabber(o3r, pcic_port=pport)
    ok, _ = fg.start([B.RADIAL_DISTANCE_IMAGE]).wait_for(5000)
    assert ok
    try:
        counts: list[int] = []
        for _ in range(2):
            for _attempt in range(3):  # ifm3d's trigger/frame futures can race; the frame counts
                fg.sw_trigger().wait_for(3000)
                ok, frame = fg.wait_for_frame().wait_for(3000)
                if ok and frame.frame_count() not in counts:
                    counts.append(frame.frame_count())
                    break
                time.sleep(0.1)
        assert counts[1] > counts[0]
    finally:
        fg.stop().wait_for(5000)
