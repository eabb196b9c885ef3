"""Several 3D heads on one emulated O3R VPU: our driver, ifm's ifm3dpy, a head that is not there, the scan.

The second head (port3) is a simulated camera in the same world as the first (port2), 0.1 m
along the first head's x axis and turned 10 deg about its y axis (:data:`OFFSET`). The scene's
table is a plane: its normal, fitted in each head's optical frame, turns by those 10 deg between
the heads (0.03 deg of it is the world's camera tilt; 0.2 deg is allowed). Noise is off, so each
frame meets a render of its own head's pose to within the 1 mm the sim quantises to. Loopback only.
"""

from __future__ import annotations

import contextlib
import math
import subprocess
import sys
import tomllib
from collections.abc import Iterator

import numpy as np
import pytest
from numpy.typing import NDArray

from cellcal.core.calibration.cameras import parse_cameras
from cellcal.core.cli import main
from cellcal.devices.base import BackendContext
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import ConfigError
from cellcal.devices.pose import Pose
from cellcal.devices.registry import default_registry
from cellcal.devices.types import Frame
from cellcal.drivers.o3r.camera import O3RCamera, O3RConfig
from cellcal.drivers.o3r.xmlrpc_config import O3RConfigClient
from cellcal.sims.camera import SimCamera, SimCameraConfig
from cellcal.sims.o3r.__main__ import DEFAULT_HEAD_SHIFT_M, DEFAULT_HEAD_TURN_DEG
from cellcal.sims.o3r.emulator import O3REmulator, wait_until
from cellcal.sims.o3r.frames import OffsetView
from cellcal.sims.o3r.options import two_d_partners

MM = 0.001
LOCAL = "127.0.0.1"
TURN_DEG = 10.0
#: The second head in the first head's optical frame: 0.1 m along x, 10 deg about y (the standalone's default).
OFFSET = Pose.from_xyz_rpy([0.1, 0.0, 0.0], [0.0, math.radians(TURN_DEG), 0.0])
#: What a VPU with 3D heads on port2 and port3 reports of its ports.
TYPES = {"port0": "2D", "port1": "2D", "port2": "3D", "port3": "3D", "port6": "IMU"}


def plane_normal(xyz: NDArray[np.float32], valid: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Unit normal of the plane fitted (least squares) to the valid points, facing the camera (-z)."""
    p = xyz[valid].astype(np.float64)
    _, _, vt = np.linalg.svd(p - p.mean(axis=0), full_matrices=False)
    n: NDArray[np.float64] = vt[2] if vt[2, 2] < 0 else -vt[2]
    return n


def angle_deg(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    return math.degrees(math.acos(min(1.0, abs(float(a @ b)))))


def assert_matches(frame: Frame, ref: Frame) -> None:
    """A driver's frame against a render of the same head's pose: same valid pixels, within 1 mm."""
    assert np.array_equal(frame.valid, ref.valid) and frame.valid.mean() > 0.9
    ok = frame.valid
    assert np.max(np.abs(frame.distance[ok] - ref.distance[ok])) < 1 * MM
    assert np.max(np.abs(frame.xyz[ok] - ref.xyz[ok])) < 1 * MM


@pytest.fixture
def vpu() -> Iterator[tuple[O3REmulator, SimCamera, OffsetView]]:
    """An emulated VPU in RUN with 3D heads on port2 (``first``) and port3 (``second``, at :data:`OFFSET`)."""
    first = SimCamera(SimCameraConfig(noise=False), BackendContext(seed=3)).connect()
    other = SimCamera(SimCameraConfig(noise=False, seed=4), world=first.world).connect()
    second = OffsetView(other, OFFSET)
    emu = O3REmulator(first, heads={"port3": second}, state="RUN", state_change_s=0.1).start()
    try:
        yield emu, first, second
    finally:
        emu.close()
        other.close()
        first.close()


# ---------------------------------------------------------------------- the emulated VPU
def test_the_vpu_numbers_and_describes_every_head() -> None:
    assert two_d_partners(["port2"]) == ["port0"] and two_d_partners(["port0"]) == ["port1"]
    assert two_d_partners(["port2", "port3"]) == ["port0", "port1"]
    assert two_d_partners(["port2", "port3", "port4", "port5"]) == ["port0", "port1"]
    cam = SimCamera(SimCameraConfig(noise=False), BackendContext(seed=3))
    with pytest.raises(ValueError, match=r"3D heads go on port0, .*, got 'port7'"):
        O3REmulator(cam, heads={"port7": cam})
    with pytest.raises(ValueError, match="port2 is given twice"):
        O3REmulator(cam, heads={"port2": cam})


def test_two_heads_each_serve_their_own_port_state_and_frames(vpu: tuple[O3REmulator, SimCamera, OffsetView]
                                                              ) -> None:
    emu, first, second = vpu
    ports = O3RConfigClient(LOCAL, emu.xmlrpc_port).get(["/ports"])["ports"]
    assert {k: v["info"]["features"]["type"] for k, v in ports.items()} == TYPES
    pcic = {k: v["data"]["pcicTCPPort"] for k, v in ports.items()}
    assert pcic == {k: emu.pcic_port_of(k) for k in TYPES} and len(set(pcic.values())) == 5
    assert [ports[k]["info"]["serialNumber"] for k in ("port2", "port3")] == ["000000000002", "000000000102"]

    # two [[cameras]] entries: one VPU address, one head each; port2 software-triggered, port3 free-running
    doc = tomllib.loads(f"""
        [[cameras]]
        name = "left"
        on = "base"
        pose = {{ translation_m = [0.3, 0.0, 0.5], rpy_deg = [180.0, 0.0, 0.0] }}
        backend = "o3r"
        host = "{LOCAL}"
        xmlrpc_port = {emu.xmlrpc_port}
        port = "port2"
        trigger = "software"
        [[cameras]]
        name = "right"
        on = "base"
        pose = {{ translation_m = [0.4, 0.0, 0.5], rpy_deg = [180.0, 10.0, 0.0] }}
        backend = "o3r"
        host = "{LOCAL}"
        xmlrpc_port = {emu.xmlrpc_port}
        port = "port3"
        trigger = "free_run"
    """)
    left, right = (default_registry().create_camera(e.table) for e in parse_cameras(doc, "cell.toml"))
    with left, right:
        # each driver set its own head's state: port2 IDLE (software trigger), port3 left in RUN
        assert (emu.heads["port2"].state, emu.heads["port3"].state) == ("IDLE", "RUN")
        assert left.info().extra["pcic_port"] == pcic["port2"] and right.info().extra["pcic_port"] == pcic["port3"]
        a = [left.capture(3.0), right.capture(3.0), left.capture(3.0), right.capture(3.0)]
        assert [a[0].sequence, a[2].sequence] == [1, 2]  # port2 sends only what its triggers ask for
        assert a[1].sequence < a[3].sequence
        assert_matches(a[2], first.render(first.world.camera_pose()))
        assert_matches(a[3], second.camera.render(second.pose()))
        right.close()  # one head's camera going away leaves the other alone
        assert left.capture(3.0).sequence == 3
    assert wait_until(lambda: emu.heads["port2"].frames_sent == 3, 2.0)  # counted once sent whole
    # the two heads see the table from their own poses: 0.44 m below the first, the second turned 10 deg
    n_left, n_right = plane_normal(a[2].xyz, a[2].valid), plane_normal(a[3].xyz, a[3].valid)
    assert angle_deg(n_left, n_right) == pytest.approx(TURN_DEG, abs=0.2)
    mean_left, mean_right = float(a[2].distance[a[2].valid].mean()), float(a[3].distance[a[3].valid].mean())
    assert mean_left == pytest.approx(0.5452, abs=2 * MM) and mean_right == pytest.approx(0.5554, abs=2 * MM)


def test_a_head_the_vpu_lacks_or_a_2d_head_is_one_line_before_any_frame(
        vpu: tuple[O3REmulator, SimCamera, OffsetView]) -> None:
    emu = vpu[0]
    cases = {"port4": "O3R at 127.0.0.1 has no port 'port4' (ports: port0, port1, port2, port3, port6); "
                      "its 3D heads: port2, port3",
             "port1": "O3R at 127.0.0.1: port1 is a 2D port, not a 3D head; its 3D heads: port2, port3",
             "port6": "O3R at 127.0.0.1: port6 is an IMU port, not a 3D head; its 3D heads: port2, port3"}
    for port, message in cases.items():
        cam = O3RCamera(O3RConfig(host=LOCAL, xmlrpc_port=emu.xmlrpc_port, port=port))
        with pytest.raises(ConfigError) as err:
            cam.connect(timeout=3.0)
        assert str(err.value) == f"key 'camera.port': {message}"
        assert err.value.key == "camera.port"
    # no PCIC client ever reached a head, and no state was changed
    assert all(h.commands == [] and h.state == "RUN" for h in emu.heads.values())


# ---------------------------------------------------------------------- cellcal devices --scan
def test_scan_lists_every_head_of_the_vpu(vpu: tuple[O3REmulator, SimCamera, OffsetView],
                                          capsys: pytest.CaptureFixture[str]) -> None:
    emu = vpu[0]
    emu.set_state("IDLE", port="port3")
    p = {k: emu.pcic_port_of(k) for k in TYPES}
    ports = f"o3r-rpc={emu.xmlrpc_port},o3r-pcic={p['port0']}"
    assert main(["devices", "--scan", "--hosts", LOCAL, "--ports", ports, "--timeout", "5"]) == 0
    out = capsys.readouterr().out.split("scan:\n", 1)[1]
    lines = [line.strip().removeprefix("camera o3r: ").strip() for line in out.splitlines()
             if line.strip().startswith("camera o3r:")]
    assert lines == [
        f"ifm electronic OVP800 000000000000 firmware 1.4.30, host=127.0.0.1, port={emu.xmlrpc_port}, "
        f"pcic_port={p['port0']}, name=cellcal-emulator",
        f"head port0: 2D, PCIC port {p['port0']}, RUN",
        f"head port1: 2D, PCIC port {p['port1']}, RUN",
        f"head port2: 3D, PCIC port {p['port2']}, RUN",
        f"head port3: 3D, PCIC port {p['port3']}, IDLE",
        f"head port6: IMU, PCIC port {p['port6']}, RUN"]


# ---------------------------------------------------------------------- ifm's own client
@contextlib.contextmanager
def standalone_two_heads() -> Iterator[tuple[int, dict[str, int]]]:
    """``python -m cellcal.sims.o3r --heads port2,port3`` (noise off, RUN); yields its XML-RPC port and PCIC ports."""
    proc = subprocess.Popen([sys.executable, "-m", "cellcal.sims.o3r", "--xmlrpc-port", "0", "--pcic-port", "0",
                             "--heads", "port2,port3", "--state", "RUN", "--frame-rate", "20", "--no-noise",
                             "--state-change-s", "0.1"], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert "ready" in line and "heads=port2,port3" in line, line
        xport = int(line.split("xmlrpc=127.0.0.1:")[1].split()[0])
        pcic = {k: int(v) for k, v in (item.split("=") for item in line.split("ports: ")[1].split())}
        yield xport, pcic
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_ifm3dpy_and_our_drivers_read_both_heads() -> None:
    device = pytest.importorskip("ifm3dpy.device", reason="ifm3dpy (the o3r-ifm3d extra) is not installed")
    fg_mod = pytest.importorskip("ifm3dpy.framegrabber", reason="ifm3dpy (the o3r-ifm3d extra) is not installed")
    assert (DEFAULT_HEAD_SHIFT_M, DEFAULT_HEAD_TURN_DEG) == (0.1, TURN_DEG)  # the standalone's second head: OFFSET
    B = fg_mod.buffer_id
    with standalone_two_heads() as (xport, pcic):
        o3r = device.O3R(LOCAL, xport)
        tree = o3r.get()
        assert {k: v["info"]["features"]["type"] for k, v in tree["ports"].items()} == TYPES
        assert {k: v["data"]["pcicTCPPort"] for k, v in tree["ports"].items()} == {k: pcic[k] for k in TYPES}
        ifm: dict[str, tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.uint16]]] = {}
        for port in ("port2", "port3"):
            fg = fg_mod.FrameGrabber(o3r, pcic_port=pcic[port])
            ok, _ = fg.start([B.RADIAL_DISTANCE_IMAGE, B.XYZ, B.CONFIDENCE_IMAGE]).wait_for(5000)
            assert ok
            try:
                ok, frame = fg.wait_for_frame().wait_for(5000)
                assert ok
                ifm[port] = (np.array(frame.get_buffer(B.RADIAL_DISTANCE_IMAGE), dtype=np.float32),
                             np.array(frame.get_buffer(B.XYZ), dtype=np.float32),
                             np.array(frame.get_buffer(B.CONFIDENCE_IMAGE)))
            finally:
                fg.stop().wait_for(5000)
        ours = {}
        for port in ("port2", "port3"):
            with O3RCamera(O3RConfig(host=LOCAL, xmlrpc_port=xport, port=port)) as cam:
                ours[port] = cam.capture(3.0)
        # the o3r-ifm3d backend picks its head the same way, and refuses a head that is not there in one line
        with camera("o3r-ifm3d", xport, port="port3") as cam:
            via_ifm3d = cam.capture(5.0)
        with pytest.raises(ConfigError, match=r"^key 'camera.port': O3R at 127.0.0.1 has no port 'port5' "
                                              r"\(ports: port0, port1, port2, port3, port6\); its 3D heads: "
                                              r"port2, port3$"):
            camera("o3r-ifm3d", xport, port="port5").connect(timeout=5.0)
    for port in ("port2", "port3"):
        dist, _xyz, conf = ifm[port]
        frame = ours[port]
        assert dist.shape == frame.distance.shape == (172, 224)
        assert np.array_equal(frame.valid, (conf & 1) == 0) and frame.valid.mean() > 0.9
        assert np.max(np.abs(dist[frame.valid] - frame.distance[frame.valid])) < 1 * MM
    assert np.max(np.abs(via_ifm3d.distance[via_ifm3d.valid] - ours["port3"].distance[via_ifm3d.valid])) < 1 * MM
    # ifm's XYZ (user frames: both heads carry the same factory extrinsic) shows the heads 10 deg apart
    normals = [plane_normal(ifm[p][1], ours[p].valid) for p in ("port2", "port3")]
    assert angle_deg(*normals) == pytest.approx(TURN_DEG, abs=0.2)


def camera(backend: str, xport: int, **kw: object) -> Camera3D:
    return default_registry().create_camera({"backend": backend, "host": LOCAL, "xmlrpc_port": xport, **kw})
