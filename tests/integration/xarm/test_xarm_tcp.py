"""XArmArm over TCP <-> the xArm emulator's control and report ports, backed by the SimArm."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from leaks import open_fds
from repo_paths import REPO_ROOT

from cellcal.core.cli import main
from cellcal.devices.arm import RobotArm
from cellcal.devices.base import BackendContext
from cellcal.devices.config import parse_section
from cellcal.devices.errors import ConfigError, DeviceConnectionError, MotionError, ProtocolError
from cellcal.devices.pose import Pose
from cellcal.devices.registry import default_registry
from cellcal.drivers.xarm.arm import XArmArm
from cellcal.drivers.xarm.registers import Reg
from cellcal.drivers.xarm.report import ReportStream
from cellcal.sims.arm import SimArm, SimArmConfig
from cellcal.sims.xarm.emulator import XArmEmulator
from cellcal.sims.xarm.tcp_server import XArmTcpServer
from cellcal.testing import ARM_RULES, ArmOptions, check_arm

Rig = tuple[SimArm, XArmEmulator, XArmTcpServer, XArmArm]


@pytest.fixture
def leak_check() -> Iterator[None]:
    threads = set(threading.enumerate())
    fds = open_fds()
    yield
    for t in [t for t in threading.enumerate() if t not in threads]:
        t.join(timeout=5.0)
    extra = [t for t in threading.enumerate() if t not in threads]
    assert not extra, f"leaked threads: {extra}"
    leaked = open_fds() - fds
    assert not leaked, f"leaked file descriptors: {sorted(leaked)}"


def _make(time_scale: float = 0.002, report_hz: float = 50.0, **driver: object) -> Rig:
    sim = SimArm(SimArmConfig(time_scale=time_scale, repeatability_m=0.0, seed=3), BackendContext()).connect()
    emu = XArmEmulator(sim, axes=5)
    server = XArmTcpServer(emu, report_hz=report_hz)
    tcp_port, report_port = server.start()
    cfg = XArmArm.Config(host="127.0.0.1", tcp_port=tcp_port, report_port=report_port, axes=5,  # type: ignore[arg-type]
                         poll_interval_s=0.005, **driver)
    return sim, emu, server, XArmArm(cfg)


def _close(rig: Rig) -> None:
    sim, emu, server, drv = rig
    drv.close()
    server.close()
    emu.close()
    sim.close()


@pytest.fixture
def rig(leak_check: None) -> Iterator[Rig]:
    made = _make()
    made[3].connect()
    yield made
    _close(made)


def _down(x: float, y: float, z: float, yaw: float = 0.0) -> Pose:
    return Pose.from_xyz_rpy([x, y, z], [np.pi, 0.0, yaw])


def test_connects_over_tcp_reads_the_report_and_moves_exactly(rig: Rig) -> None:
    sim, emu, server, drv = rig
    info = drv.info()
    assert (info.model, info.firmware, info.extra["transport"]) == ("xArm 5", "2.5.0", "tcp")
    assert info.extra["port"] == f"127.0.0.1:{server.tcp_port}"
    report = drv.latest_report()
    assert report is not None and report.state == 2 and report.enabled_bits == 0b11111
    np.testing.assert_allclose(np.asarray(report.pose_mm_rad[:3]) / 1000.0, sim.true_flange_pose().translation,
                               atol=1e-6)
    for target in (_down(0.35, -0.05, 0.40, 0.3), _down(0.25, 0.10, 0.45)):
        drv.move_linear(target, speed=0.3, acceleration=2.0)
        assert drv.get_pose().distance_to(target) < 1e-6
    assert emu.requests[Reg.MOVE_LINE] == 2
    # every request carried a new transaction id, 1, 2, 3, ... in order
    assert server.transactions == list(range(1, len(server.transactions) + 1))
    assert drv.transport.stats["stale_replies"] == 0 and drv.transport.stats["retries"] == 0


def test_report_replaces_polling_while_the_arm_moves(leak_check: None) -> None:
    made = _make(time_scale=0.5, report_hz=50.0)  # a 100 mm move takes ~0.35 s of wall time
    sim, emu, _server, drv = made
    try:
        drv.connect()
        start = drv.get_pose()
        before = emu.requests.get(Reg.GET_STATE, 0)
        target = Pose(start.rotation, start.translation + np.array([0.1, 0.0, 0.0]))
        drv.move_linear(target, speed=0.5, acceleration=2.0)
        polls = emu.requests.get(Reg.GET_STATE, 0) - before
        # polling every 5 ms would read the state ~70 times; the report stream leaves a handful
        assert polls <= 6, polls
        assert not sim.is_moving()
    finally:
        _close(made)


def test_both_port_and_host_is_one_config_error() -> None:
    with pytest.raises(ConfigError) as err:
        parse_section(XArmArm.Config, {"port": "/dev/ttyUSB0", "host": "192.168.1.20"}, where="arm",
                      source="cell.toml")
    text = str(err.value)
    assert "\n" not in text and "port" in text and "host" in text and "cell.toml" in text
    cfg = parse_section(XArmArm.Config, {"host": "192.168.1.20"})
    assert (cfg.host, cfg.tcp_port, cfg.report_port, cfg.port) == ("192.168.1.20", 502, 30002, None)
    with pytest.raises(ConfigError, match="tcp_port"):
        parse_section(XArmArm.Config, {"host": "192.168.1.20", "tcp_port": 70000})
    with pytest.raises(ConfigError, match="host is empty"):
        parse_section(XArmArm.Config, {"host": " "})
    with pytest.raises(ConfigError, match="report_port 502 is the control port"):
        parse_section(XArmArm.Config, {"host": "192.168.1.20", "report_port": 502})


def test_lost_reply_to_a_move_is_never_resent_and_the_arm_is_stopped(leak_check: None) -> None:
    made = _make(time_scale=0.3)
    sim, emu, _server, drv = made
    try:
        drv.connect()
        emu.inject("drop", register=Reg.MOVE_LINE)
        target = _down(0.30, -0.10, 0.35)
        t0 = time.monotonic()
        with pytest.raises(MotionError, match=r"MOVE_LINE to .* was not confirmed.*not sent again") as err:
            drv.move_linear(target, speed=0.3, acceleration=2.0)
        took = time.monotonic() - t0
        assert emu.requests[Reg.MOVE_LINE] == 1  # the command went out once
        assert "stopped" in str(err.value) and not sim.is_moving()
        assert took < drv.config.reply_timeout_s + drv.config.stop_timeout_s + 2.0  # 2 s for a busy machine
    finally:
        _close(made)


def test_reply_with_a_stale_transaction_id_never_confirms_a_move(leak_check: None) -> None:
    made = _make(time_scale=0.3)
    _sim, emu, _server, drv = made
    try:
        drv.connect()
        emu.inject("stale_id", register=Reg.MOVE_LINE)
        with pytest.raises(MotionError, match="was not confirmed"):
            drv.move_linear(_down(0.30, 0.10, 0.35), speed=0.3, acceleration=2.0)
        assert emu.requests[Reg.MOVE_LINE] == 1
        assert drv.transport.stats["stale_replies"] == 1
    finally:
        _close(made)


@pytest.mark.parametrize("kind", ["drop", "stall", "lag", "stale_id", "corrupt_crc", "truncate"])
def test_a_spoilt_reply_to_a_read_is_retried_and_late_replies_are_told_apart(kind: str, rig: Rig) -> None:
    sim, emu, _server, drv = rig
    emu.inject(kind, register=Reg.GET_TCP_POSE, stall_s=0.7)  # longer than the 0.5 s reply timeout
    assert drv.get_pose().distance_to(sim.true_flange_pose()) < 1e-6
    stats = drv.transport.stats
    assert stats["retries"] == 1
    if kind in ("stall", "lag", "stale_id"):
        assert stats["stale_replies"] >= 1 or kind == "stall"  # a stalled reply may still be in flight
    if kind in ("corrupt_crc", "truncate"):
        assert stats["connects"] == 2  # a stream out of step is never read on: new connection
    target = _down(0.33, 0.02, 0.42)
    drv.move_linear(target, speed=0.3, acceleration=2.0)
    assert drv.get_pose().distance_to(target) < 1e-6 and emu.requests[Reg.MOVE_LINE] == 1


def test_reads_reconnect_after_the_link_drops(rig: Rig) -> None:
    sim, _emu, server, drv = rig
    assert server.drop_clients() >= 2  # control and report
    time.sleep(0.05)
    assert drv.get_pose().distance_to(sim.true_flange_pose()) < 1e-6
    assert drv.transport.stats["connects"] == 2
    drv.move_linear(_down(0.32, 0.0, 0.40), speed=0.3, acceleration=2.0)


def test_write_on_a_dead_link_is_a_connection_error_not_a_resend(leak_check: None) -> None:
    made = _make()
    _sim, emu, server, drv = made
    try:
        drv.connect()
        server.close()  # controller gone: nothing listens any more
        with pytest.raises(DeviceConnectionError, match=r"cannot connect|connection"):
            drv.transport.transact(int(Reg.SET_STATE), bytes([0]), expect_len=0, timeout=0.3)
        assert emu.requests[Reg.SET_STATE] == 1  # only the one of connect
    finally:
        _close(made)


@pytest.mark.parametrize("fault", ["garbage", "bad_values"])
def test_report_garbage_is_a_typed_error_and_the_registers_take_over(fault: str, rig: Rig) -> None:
    sim, _emu, server, drv = rig
    stream = drv._report
    assert stream is not None
    server.inject_report(fault, count=1000)  # every report from now on
    seen = stream.latest().seq if stream.latest() is not None else 0  # type: ignore[union-attr]
    t0 = time.monotonic()
    with pytest.raises(ProtocolError, match="report"):
        stream.wait_newer(seen, time.monotonic() + 1.0)  # the stream's error once the deadline passes
    assert time.monotonic() - t0 < 1.0 + 2.0  # the deadline (with room for a busy machine), not a hang
    assert stream.stats["bad_reports"] >= 1 and drv.latest_report() is None
    target = _down(0.30, 0.05, 0.38)
    drv.move_linear(target, speed=0.3, acceleration=2.0)  # state polled over the control port instead
    assert drv.get_pose().distance_to(target) < 1e-6 and drv.status().ok
    assert not sim.is_moving()


def test_report_port_that_never_answers_times_out_as_typed_error(leak_check: None) -> None:
    import socket

    silent = socket.socket()
    silent.bind(("127.0.0.1", 0))
    silent.listen(1)
    stream = ReportStream("127.0.0.1", silent.getsockname()[1], stale_after_s=0.2, connect_timeout_s=0.5)
    try:
        stream.start()
        t0 = time.monotonic()
        with pytest.raises(Exception) as err:
            stream.wait_newer(0, time.monotonic() + 0.6)
        assert type(err.value).__name__ in ("DeviceTimeoutError", "DeviceConnectionError")
        assert time.monotonic() - t0 < 0.6 + 2.0  # the deadline (with room for a busy machine), not a hang
    finally:
        stream.close()
        silent.close()


def test_emulated_backend_over_tcp_from_the_registry(leak_check: None) -> None:
    arm = default_registry().create_arm({"backend": "xarm-emulated", "transport": "tcp", "time_scale": 0.001},
                                        BackendContext())
    with arm:
        assert arm.info().extra["transport"] == "tcp" and arm.info().extra["emulated"] is True
        target = _down(0.30, -0.05, 0.40)
        arm.move_linear(target, speed=0.3, acceleration=2.0)
        assert arm.get_pose().distance_to(target) < 1e-3
        assert arm.server is not None and arm.server.reports_sent > 0  # type: ignore[attr-defined]


def test_tcp_emulated_backend_passes_the_conformance_kit(leak_check: None) -> None:
    def make() -> RobotArm:
        return default_registry().create_arm({"backend": "xarm-emulated", "transport": "tcp", "time_scale": 0.001},
                                             BackendContext())

    report = check_arm(make, ArmOptions(joint_count=5), quiet=True)
    assert report.backend == "xarm-emulated" and [r.rule for r in report.results] == list(ARM_RULES)


def _angles(out: Path) -> list[tuple[int, int, str, float]]:
    result = json.loads((out / "result.json").read_text())
    return [(p["index"], m["perimeter_px"], m["method"], m["angle_deg"]) for p in result["poses"]
            for m in p["measurements"]]


def test_calibrate_cli_runs_the_tcp_emulated_cell_and_matches_the_pure_sim(tmp_path: Path) -> None:
    for name in ("xarm_tcp_emulated", "sim"):
        assert main(["calibrate", "--config", str(REPO_ROOT / "configs" / f"{name}.toml"), "--out",
                     str(tmp_path / name), "--quiet"]) == 0
    tcp, sim = _angles(tmp_path / "xarm_tcp_emulated"), _angles(tmp_path / "sim")
    assert [a[:3] for a in tcp] == [a[:3] for a in sim] and len(tcp) > 30
    worst = max(abs(t[3] - s[3]) for t, s in zip(tcp, sim, strict=True))
    assert worst < 0.01, f"largest angle difference {worst:.3g} deg"  # float32 on the wire, nothing else


def test_cli_names_both_keys_in_one_line_when_port_and_host_are_given(tmp_path: Path) -> None:
    text = (REPO_ROOT / "configs" / "xarm_tcp_emulated.toml").read_text()
    arm = '[arm]\nbackend = "xarm"\nport = "/dev/ttyUSB0"\nhost = "192.168.1.20"\naxes = 5\n'
    start, end = text.index("[arm]"), text.index("[mount]")
    config = tmp_path / "both.toml"
    config.write_text(text[:start] + arm + "\n" + text[end:])
    done = subprocess.run([sys.executable, "-c", "import sys; from cellcal.core.cli import main; sys.exit(main())",
                           "calibrate", "--check", "--config", str(config)], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "port" in lines[0] and "host" in lines[0] and "Traceback" not in done.stderr


def test_check_names_the_tcp_address_not_the_serial_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    text = (REPO_ROOT / "configs" / "xarm_tcp_emulated.toml").read_text()
    arm = text[text.index("[arm]"):text.index("\n[", text.index("[arm]") + 1)]
    cell = text.replace(arm, '[arm]\nbackend = "xarm"\nhost = "192.168.1.185"\naxes = 5\n')
    # a real xArm 5 cannot tilt its tool sideways: the paper's inclination about the flange's y axis is refused
    # by --check (named), so this cell looks straight down
    cell = cell.replace("inclination_deg = 80.0", "inclination_deg = 90.0")
    (tmp_path / "cell.toml").write_text(cell)
    assert main(["calibrate", "--config", str(tmp_path / "cell.toml"), "--check"]) == 0
    line = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("arm:"))
    assert "at host='192.168.1.185', tcp_port=502, axes=5 (" in line
    assert "port=None" not in line and "baudrate" not in line
