"""The emulator made like a real VPU (issue #22), and the driver's answers to it: ports, slow state changes,
CONF-only settings, the read-only table, the boot clock, per-pose frames with fresh noise."""

from __future__ import annotations

import json
import random
import socket
import time
from collections.abc import Iterator

import numpy as np
import pytest

from cellcal.devices.base import BackendContext
from cellcal.devices.errors import DeviceConnectionError, DeviceTimeoutError, VendorError
from cellcal.devices.pose import Pose
from cellcal.drivers.o3r.camera import O3RCamera, O3RConfig
from cellcal.drivers.o3r.pcic import encode_message
from cellcal.drivers.o3r.xmlrpc_config import O3RConfigClient
from cellcal.sims.camera import SimCamera, SimCameraConfig
from cellcal.sims.o3r.emulator import BOOT_UPTIME_S, O3REmulator


@pytest.fixture
def sim() -> Iterator[SimCamera]:
    cam = SimCamera(SimCameraConfig(noise=False), BackendContext(seed=5)).connect()
    yield cam
    cam.close()


def started(sim: SimCamera, **kw: object) -> O3REmulator:
    return O3REmulator(sim, **kw).start()  # type: ignore[arg-type]


def test_ports_are_numbered_as_on_a_vpu(sim: SimCamera) -> None:
    emu = None
    for _ in range(20):  # a free block of 1001 ports: try a few random bases
        base = random.randrange(20000, 40000, 10)
        try:
            emu = started(sim, pcic_base_port=base, state="IDLE")
            break
        except OSError:
            continue
    assert emu is not None
    try:
        rpc = O3RConfigClient("127.0.0.1", emu.xmlrpc_port)
        ports = rpc.get(["/ports"])["ports"]
        assert {k: v["data"]["pcicTCPPort"] for k, v in ports.items()} == {
            "port0": base, "port2": base + 2, "port6": base + 6}
        assert {k: v["info"]["features"]["type"] for k, v in ports.items()} == {
            "port0": "2D", "port2": "3D", "port6": "IMU"}
        apps = rpc.get(["/applications/instances"])["applications"]["instances"]
        assert apps["app0"]["data"]["pcicTCPPort"] == base + 1000
        for number in (base, base + 6, base + 1000):  # every port answers PCIC, only the 3D head sends frames
            with socket.create_connection(("127.0.0.1", number), timeout=2.0) as s:
                s.sendall(encode_message("1002", b"p1"))
                assert s.recv(64) == encode_message("1002", b"*")
        cam = O3RCamera(O3RConfig(host="127.0.0.1", xmlrpc_port=emu.xmlrpc_port, trigger="software",
                                  set_state=False)).connect(timeout=3.0)
        try:
            assert cam.info().extra["pcic_port"] == base + 2
            assert cam.capture(3.0).distance.shape == (172, 224)
        finally:
            cam.close()
    finally:
        emu.close()


def test_state_change_takes_time_and_the_driver_leaves_conf(sim: SimCamera) -> None:
    emu = started(sim, state="CONF", state_change_s=1.5)
    try:
        # io_timeout_s is 1 s, but a set has its own timeout: the 1.5 s switch succeeds
        cfg = O3RConfig(host="127.0.0.1", xmlrpc_port=emu.xmlrpc_port, trigger="software", io_timeout_s=1.0)
        t0 = time.monotonic()
        cam = O3RCamera(cfg).connect(timeout=3.0)
        try:
            assert time.monotonic() - t0 >= 1.5 and emu.state == "IDLE"
            assert cam.capture(1.0).valid.mean() > 0.9
        finally:
            cam.close()
        # a set timeout shorter than the switch is a timeout, named as such
        emu.set_state("CONF")
        with pytest.raises(DeviceTimeoutError, match="set"):
            O3RConfigClient("127.0.0.1", emu.xmlrpc_port, set_timeout_s=0.5).set_state("port2", "IDLE")
        # without set_state the driver refuses CONF plainly
        emu.set_state("CONF")
        with pytest.raises(DeviceConnectionError, match=r"CONF .sends no data.*set_state = true"):
            O3RCamera(O3RConfig(host="127.0.0.1", xmlrpc_port=emu.xmlrpc_port, set_state=False)).connect(timeout=3.0)
    finally:
        emu.close()


def test_conf_only_read_only_and_unknown_settings_are_faults_labelled_as_the_emulators(sim: SimCamera) -> None:
    emu = started(sim, state="RUN", state_change_s=0.05)
    try:
        rpc = O3RConfigClient("127.0.0.1", emu.xmlrpc_port)
        with pytest.raises(VendorError, match=r"cellcal O3R emulator .own code 901004.*only while .*CONF"):
            rpc.set({"ports": {"port2": {"mode": "standard_range2m"}}})
        rpc.set_state("port2", "CONF")
        rpc.set({"ports": {"port2": {"mode": "cyclic_4m_2m_4m_2m"}}})
        assert rpc.get(["/ports/port2/mode"])["ports"]["port2"]["mode"] == "cyclic_4m_2m_4m_2m"
        with pytest.raises(VendorError, match=r"901003.*pcicTCPPort is read-only"):
            rpc.set({"ports": {"port2": {"data": {"pcicTCPPort": 1234}}}})
        rpc.set({"device": {"info": {"name": "cell-7"}}})  # under /info/, yet writable: the table decides
        with pytest.raises(VendorError, match=r"901003.*serialNumber is read-only"):
            rpc.set({"device": {"info": {"serialNumber": "x"}}})
        with pytest.raises(VendorError, match=r"901000.*unknown key: /ports/port2/bogus"):
            rpc.set({"ports": {"port2": {"bogus": 1}}})
        schema = json.loads(rpc.call("getSchema"))
        port2 = schema["properties"]["ports"]["properties"]["port2"]["properties"]
        assert port2["data"]["properties"]["pcicTCPPort"]["readOnly"] is True
        assert port2["state"]["enum"] == ["RUN", "IDLE", "CONF"]
        assert "CONF" in port2["mode"]["description"]
    finally:
        emu.close()


def test_boot_clock_frames_carry_receive_time_and_device_time(sim: SimCamera) -> None:
    emu = started(sim, state="IDLE")
    cam = O3RCamera(O3RConfig(host="127.0.0.1", xmlrpc_port=emu.xmlrpc_port, trigger="software",
                              set_state=False)).connect(timeout=3.0)
    try:
        before = time.time()
        f = cam.capture(3.0)
        after = time.time()
        assert before <= f.timestamp <= after  # receive time, Unix
        assert f.metadata["timestamp_source"] == "receive"
        assert BOOT_UPTIME_S <= f.metadata["device_timestamp_s"] < BOOT_UPTIME_S + 600
        assert f.metadata["tof_info_version"] == 4 and f.metadata["imager"] == "IRS2381C"
    finally:
        cam.close()
        emu.close()


def test_per_pose_frames_render_once_and_draw_fresh_noise(sim: SimCamera) -> None:
    emu = started(sim, state="IDLE", frames="per_pose", noise_scale=1.0)
    cam = O3RCamera(O3RConfig(host="127.0.0.1", xmlrpc_port=emu.xmlrpc_port, trigger="software",
                              set_state=False)).connect(timeout=3.0)
    try:
        frames = [cam.capture(3.0) for _ in range(6)]
        assert sim.sequence == 1  # one render for the one pose
        truth = sim.render(sim.world.camera_pose()).distance
        ok = frames[0].valid & np.isfinite(truth)
        diffs = np.stack([f.distance[ok] - truth[ok] for f in frames])
        # fresh noise: every frame differs from the others, the noise averages out, sigma ~ data sheet at ~0.6 m
        assert all(not np.array_equal(diffs[0], d) for d in diffs[1:])
        assert abs(float(np.mean(diffs))) < 2e-4
        assert 0.8e-3 < float(np.std(diffs)) < 3e-3
        arm = sim.world.arm
        arm.set_flange_pose(Pose.from_xyz_rotvec([0.0, 0.0, 0.05], [0.0, 0.0, 0.0]) @ arm.flange_pose())
        cam.capture(3.0)
        assert sim.sequence == 2  # a new pose: rendered once more
    finally:
        cam.close()
        emu.close()
