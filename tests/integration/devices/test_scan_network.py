"""``cellcal devices --scan --hosts 127.0.0.1``: the O3R, xArm and UR emulators found and named; hostile peers.

Every server here listens on 127.0.0.1 and every scan targets 127.0.0.1 only. The
emulators run on free ports (80 and 502 need root), given to the scan with ``--ports``.
"""

from __future__ import annotations

import contextlib
import re
import socket
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import pytest

from cellcal.core.cli import main
from cellcal.devices.base import BackendContext
from cellcal.devices.discovery import HostScan, scan, sweep
from cellcal.drivers.o3r.camera import O3RCamera
from cellcal.drivers.ur.arm import URArm
from cellcal.drivers.xarm.arm import XArmArm
from cellcal.sims.arm import SimArm, SimArmConfig
from cellcal.sims.camera import SimCamera, SimCameraConfig
from cellcal.sims.o3r.emulator import O3REmulator
from cellcal.sims.ur.emulator import UREmulator
from cellcal.sims.xarm.emulator import XArmEmulator
from cellcal.sims.xarm.tcp_server import XArmTcpServer

LOCAL = "127.0.0.1"


@pytest.fixture
def emulators() -> Iterator[dict[str, int]]:
    """The three emulators on 127.0.0.1, free ports; yields the ports by service name."""
    with contextlib.ExitStack() as stack:
        cam = SimCamera(SimCameraConfig(), BackendContext()).connect()
        stack.callback(cam.close)
        o3r = O3REmulator(cam, state="IDLE").start()
        stack.callback(o3r.close)
        xarm_sim = SimArm(SimArmConfig(time_scale=0.0), BackendContext()).connect()
        stack.callback(xarm_sim.close)
        xarm = XArmTcpServer(XArmEmulator(xarm_sim, axes=5))
        xarm_port, _ = xarm.start()
        stack.callback(xarm.close)
        ur_sim = SimArm(SimArmConfig(time_scale=0.0), BackendContext()).connect()
        stack.callback(ur_sim.close)
        ur = UREmulator(ur_sim, LOCAL, ports=(0, 0, 0))
        ur.start()
        stack.callback(ur.close)
        rtde, _script, dashboard = ur.ports
        yield {"o3r-rpc": o3r.xmlrpc_port, "o3r-pcic": o3r.pcic_port, "xarm": xarm_port,
               "ur-dashboard": dashboard, "ur-rtde": rtde}


def _ports_arg(ports: dict[str, int]) -> str:
    return ",".join(f"{k}={v}" for k, v in ports.items())


def _scan_lines(out: str) -> dict[str, list[str]]:
    """The scan section's lines by backend (``"arm xarm"`` -> its lines)."""
    lines: dict[str, list[str]] = {}
    for line in out.split("scan:\n", 1)[1].splitlines():
        who, _, what = line.strip().partition(": ")
        lines.setdefault(who, []).append(what)
    return lines


def test_scan_finds_the_three_emulators_and_names_them(emulators: dict[str, int],
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    p = emulators
    assert main(["devices", "--scan", "--hosts", LOCAL, "--ports", _ports_arg(p), "--timeout", "5"]) == 0
    captured = capsys.readouterr()
    lines = _scan_lines(captured.out)
    o3r = lines["camera o3r"]
    assert o3r[0] == (f"ifm electronic OVP800 000000000000 firmware 1.4.30, host=127.0.0.1, port={p['o3r-rpc']}, "
                      f"pcic_port={p['o3r-pcic']}, name=cellcal-emulator")
    # then every port of the VPU: its 2D head (port0), the 3D head on the scanned PCIC port, the IMU
    assert len(o3r) == 4 and o3r[2] == f"  head port2: 3D, PCIC port {p['o3r-pcic']}, IDLE"
    assert re.fullmatch(r"  head port0: 2D, PCIC port \d+, RUN", o3r[1]), o3r[1]
    assert re.fullmatch(r"  head port6: IMU, PCIC port \d+, RUN", o3r[3]), o3r[3]
    assert lines["arm xarm"] == [
        f"UFACTORY xArm5 XS1305EMU0001 firmware 2.5.0, host=127.0.0.1, port={p['xarm']}, arm_type=5, "
        "control_box=AC1305EMU0001"]
    assert lines["arm ur"] == [
        "Universal Robots UR5 20235500001 firmware URSoftware 5.11.0.108249 (Nov 04 2021), host=127.0.0.1, "
        f"dashboard_port={p['ur-dashboard']}, rtde_port={p['ur-rtde']}"]
    # the emulated backends start their own emulator: nothing to look for
    assert lines["arm xarm-emulated"] == [
        "no discovery (this backend cannot look for devices; configure its address)"]
    assert "Traceback" not in captured.out + captured.err


def test_a_plain_scan_looks_at_the_factory_addresses(monkeypatch: pytest.MonkeyPatch,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """Without --hosts / --subnet every network backend probes its factory addresses (the child gets hosts None)."""
    from cellcal.core.cli import devices
    from cellcal.drivers.o3r import discover as o3r_discover
    from cellcal.drivers.xarm import discover as xarm_discover

    asked: dict[str, object] = {}

    def record(kind: str, name: str, timeout: float, target: object = None) -> list[str]:
        asked[f"{kind} {name}"] = target  # only what the command asked for; no packet leaves the machine
        return ["recorded"]

    monkeypatch.setattr(devices, "scan_lines", record)
    assert main(["devices", "--scan", "--timeout", "0.5", "--ports", "xarm=5020"]) == 0
    for backend in ("camera o3r", "arm xarm", "arm ur"):
        assert asked[backend] == devices.NetworkTarget(hosts=None, ports={"xarm": 5020}), backend
    assert main(["devices", "--scan", "--factory"]) == 0  # the explicit spelling of the default
    assert asked["arm xarm"] == devices.NetworkTarget(hosts=None, ports={})
    # and what hosts=None means to each driver: the vendor's factory addresses (UR has none: one note)
    assert o3r_discover.FACTORY_HOSTS == ("192.168.0.69",)
    assert tuple(f"192.168.1.{i}" for i in range(1, 255)) == xarm_discover.FACTORY_HOSTS
    ur = URArm.scan_hosts(None, 0.5)
    assert ur.found == [] and ur.notes and "no factory address" in ur.notes[0]
    capsys.readouterr()


# ---------------------------------------------------------------- hostile and absent peers
@dataclass
class Peer:
    """A TCP server on 127.0.0.1 that accepts and then behaves as told."""

    port: int
    connections: int = 0


@contextlib.contextmanager
def _peer(behave: Callable[[socket.socket], None]) -> Iterator[Peer]:
    server = socket.create_server((LOCAL, 0))
    server.settimeout(0.05)
    peer = Peer(server.getsockname()[1])
    stop = threading.Event()
    clients: list[socket.socket] = []

    def serve() -> None:
        while not stop.is_set():
            try:
                conn, _ = server.accept()
            except TimeoutError:
                continue
            peer.connections += 1
            clients.append(conn)
            with contextlib.suppress(OSError):
                behave(conn)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield peer
    finally:
        stop.set()
        thread.join(5)
        server.close()
        for conn in clients:
            conn.close()


def _silent(conn: socket.socket) -> None:
    """Accept and say nothing."""


def _garbage(conn: socket.socket) -> None:
    """Accept and say something that is no vendor's protocol."""
    conn.sendall(b"SSH-2.0-OpenSSH_9.6\r\n" + bytes(range(256)) * 4)


def _closed_port() -> int:
    """A port on 127.0.0.1 that refuses (bound, then closed)."""
    with socket.create_server((LOCAL, 0)) as s:
        return int(s.getsockname()[1])


SCANNERS: dict[str, Callable[[int, int], HostScan]] = {
    # (port of the probed service, a refused port for the vendor's other service)
    "o3r": lambda port, closed: O3RCamera.scan_hosts([LOCAL], 0.6, {"o3r-rpc": port, "o3r-pcic": closed}),
    "xarm": lambda port, _closed: XArmArm.scan_hosts([LOCAL], 0.6, {"xarm": port}),
    "ur": lambda port, closed: URArm.scan_hosts([LOCAL], 0.6, {"ur-dashboard": port, "ur-rtde": closed}),
}

SILENT_NOTE = {
    "o3r": "127.0.0.1:{port}: accepted, but no XML-RPC reply within {t} s (not an O3R)",
    "xarm": "127.0.0.1:{port}: accepted, but no xArm reply in time (not an xArm)",
    "ur": "127.0.0.1:{port}: accepted, but no reply in time (not a UR dashboard)",
}
GARBAGE_NOTE = {
    "o3r": "127.0.0.1:{port}: not an O3R (malformed HTTP answer (BadStatusLine: SSH-2.0-OpenSSH_9.6\\r\\n))",
    "xarm": "127.0.0.1:{port}: not an xArm (xarm tcp: length field 12846 is not 1..512 (stream out of step) "
            "(at byte offset 4))",
    "ur": "127.0.0.1:{port}: greeting 'SSH-2.0-OpenSSH_9.6' is not the dashboard's (not a UR dashboard)",
}


@pytest.mark.parametrize("vendor", list(SCANNERS))
def test_a_silent_port_is_one_note(vendor: str) -> None:
    with _peer(_silent) as peer:
        report = SCANNERS[vendor](peer.port, _closed_port())
    assert report.found == []
    (note,) = report.notes
    if vendor == "o3r":  # the XML-RPC call had what was left of the scan's 0.6 s
        t = note.split("within ")[1].split(" s")[0]
        assert 0.0 < float(t) <= 0.6
        assert note == SILENT_NOTE[vendor].format(port=peer.port, t=t)
    else:
        assert note == SILENT_NOTE[vendor].format(port=peer.port)
    assert peer.connections >= 1


@pytest.mark.parametrize("vendor", list(SCANNERS))
def test_a_port_that_says_garbage_is_one_note(vendor: str) -> None:
    with _peer(_garbage) as peer:
        report = SCANNERS[vendor](peer.port, _closed_port())
    assert report.found == []
    assert report.notes == [GARBAGE_NOTE[vendor].format(port=peer.port)]


@pytest.mark.parametrize("vendor", list(SCANNERS))
def test_a_refused_port_finds_nothing_and_says_so_in_numbers(vendor: str) -> None:
    closed = _closed_port()
    report = SCANNERS[vendor](closed, closed)
    assert report.found == [] and report.notes == []
    assert report.summary == "1 host x 1 port: 1 refused"


def test_hostile_peers_cost_one_line_each_in_the_command(capsys: pytest.CaptureFixture[str]) -> None:
    closed = _closed_port()
    with _peer(_silent) as silent, _peer(_garbage) as garbage:
        ports = {"xarm": silent.port, "ur-dashboard": garbage.port, "ur-rtde": closed,
                 "o3r-rpc": closed, "o3r-pcic": closed}
        assert main(["devices", "--scan", "--hosts", LOCAL, "--ports", _ports_arg(ports), "--timeout", "0.6"]) == 0
    captured = capsys.readouterr()
    lines = _scan_lines(captured.out)
    assert lines["arm xarm"] == [SILENT_NOTE["xarm"].format(port=silent.port)]
    assert lines["arm ur"] == [GARBAGE_NOTE["ur"].format(port=garbage.port)]
    assert lines["camera o3r"] == ["no devices found (1 host x 1 port: 1 refused)"]
    assert "Traceback" not in captured.out + captured.err


def test_sweep_states_and_scan_limits() -> None:
    closed = _closed_port()
    with _peer(_silent) as peer:
        states = sweep([(LOCAL, peer.port), (LOCAL, closed)], 1.0)
    assert states == {(LOCAL, peer.port): "open", (LOCAL, closed): "refused"}
    with pytest.raises(ValueError, match="1025 hosts: at most 1024"):
        scan(["127.0.0.1"] * 1025, {"x": closed}, 0.5, lambda h, p, d: None)
    # no time at all: nothing is tried, and the report says so
    assert sweep([(LOCAL, closed)], 0.0) == {(LOCAL, closed): "not tried"}
