"""The official client agrees: ifm3dpy (ifm's own library) against the emulator.

ifm3dpy's calls hold the GIL, so the emulator runs in a subprocess (the standalone
``python -m cellcal.sims.o3r``); noise is off, so every frame of the static scene has
the same content and ifm3dpy's frame can be compared with the cellcal driver's.
"""

from __future__ import annotations

import contextlib
import subprocess
import sys
import time
from collections.abc import Iterator

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cellcal.drivers.o3r.camera import O3RCamera, O3RConfig
from cellcal.sims.o3r.emulator import FACTORY_OPTIC_TO_HEAD

ifm3dpy_device = pytest.importorskip("ifm3dpy.device")
ifm3dpy_fg = pytest.importorskip("ifm3dpy.framegrabber")
ifm3dpy_deser = pytest.importorskip("ifm3dpy.deserialize")

MM = 0.001


@contextlib.contextmanager
def standalone(*extra: str) -> Iterator[tuple[int, int]]:
    """The standalone emulator (ephemeral ports, noise off) with ``extra`` arguments; yields (xml-rpc, PCIC) ports."""
    proc = subprocess.Popen([sys.executable, "-m", "cellcal.sims.o3r", "--xmlrpc-port", "0", "--pcic-port", "0",
                             "--state", "RUN", "--frame-rate", "20", "--no-noise", *extra],
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


@pytest.fixture
def emulator() -> Iterator[tuple[int, int]]:
    with standalone() as ports:
        yield ports


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
    # optical -> head (the emulator's non-zero factory extrinsic) -> user (0.1 m along x, 0.2 rad about y)
    tx, ty, tz, rx, ry, rz = FACTORY_OPTIC_TO_HEAD
    head = Rotation.from_euler("XYZ", [rx, ry, rz]).apply(ours.xyz[valid].astype(np.float64)) + np.array([tx, ty, tz])
    user = Rotation.from_euler("XYZ", [0.0, 0.2, 0.0]).apply(head) + np.array([0.1, 0.0, 0.0])
    assert np.max(np.abs(ifm_xyz[valid] - user)) < 1 * MM


@pytest.mark.parametrize("bits", [8, 16])
def test_ifm3dpy_reads_tof_info_v4_of_a_cycling_mode_and_either_confidence(bits: int) -> None:
    with standalone("--mode", "cyclic_4m_2m_4m_2m", "--confidence-bits", str(bits)) as (xport, pport):
        o3r = ifm3dpy_device.O3R("127.0.0.1", xport)
        B = ifm3dpy_fg.buffer_id
        fg = ifm3dpy_fg.FrameGrabber(o3r, pcic_port=pport)
        ok, _ = fg.start([B.RADIAL_DISTANCE_IMAGE, B.CONFIDENCE_IMAGE, B.TOF_INFO]).wait_for(5000)
        assert ok
        try:
            infos, confs = {}, []
            for _ in range(100):  # ifm3d's wait_for_frame may hand out the last frame again: collect 4 distinct
                ok, frame = fg.wait_for_frame().wait_for(5000)
                assert ok
                raw = np.array(frame.get_buffer(B.TOF_INFO), dtype=np.uint8).ravel()
                infos[frame.frame_count()] = ifm3dpy_deser.TOFInfoV4.deserialize(raw)
                confs.append(np.array(frame.get_buffer(B.CONFIDENCE_IMAGE)))
                if len(infos) == 4:
                    break
                time.sleep(0.02)
        finally:
            fg.stop().wait_for(5000)
        cam = O3RCamera(O3RConfig(host="127.0.0.1", xmlrpc_port=xport)).connect(timeout=3.0)
        try:
            ours = cam.capture(3.0)
        finally:
            cam.close()
    assert len(infos) == 4
    for count, info in infos.items():
        assert info.version == 4 and info.mode.rstrip("\0") == "cyclic_4m_2m_4m_2m"
        assert info.measurement_block_index == (count - 1) % 4  # ifm's deserializer reads the block we sent
        assert info.measurement_range_max == pytest.approx((4.0, 2.0, 4.0, 2.0)[info.measurement_block_index] * 1.035)
    assert len({i.measurement_range_max for i in infos.values()}) == 2  # frames of the two ranges differ
    assert confs[0].dtype == (np.uint8 if bits == 8 else np.uint16)
    # the driver exposes the same per-frame facts, and the same confidence depth
    assert ours.metadata["measurement_block_index"] == (ours.sequence - 1) % 4
    assert ours.metadata["mode"] == "cyclic_4m_2m_4m_2m" and ours.metadata["confidence_bits"] == bits
    assert ours.confidence is not None and ours.confidence.dtype == confs[0].dtype


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
