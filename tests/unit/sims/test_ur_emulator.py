"""The UR emulator in this process, spoken to by a bare RTDE / dashboard client written here from the spec.

No ur_rtde here (its constructors hold the GIL: tests/integration/ur/ use it against the
emulator as a child process). Ports are any free ones on 127.0.0.1.
"""

from __future__ import annotations

import select
import socket
import struct
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
from leaks import open_fds

from cellcal.devices.base import BackendContext
from cellcal.devices.geometry.vendor_poses import pose_from_ur, pose_to_ur
from cellcal.devices.pose import Pose
from cellcal.sims.arm import SimArm, SimArmConfig
from cellcal.sims.ur.controller import pose_from_joints, ur_joints
from cellcal.sims.ur.emulator import UR_LIKE, UREmulator
from cellcal.sims.ur.script_role import ProgramReader

HOME = Pose.from_xyz_rpy([0.40, 0.0, 0.45], [np.pi, 0.0, 0.0])
SCRIPT = "def rtde_control():\n    global reg_offset_float = 0\n    global reg_offset_int = 0\n    sync()\nend\n"


class RawRTDE:
    """An RTDE protocol-2 client from the C2 facts: u16 size + type byte, big-endian payloads."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=2.0)
        self.buf = bytearray()  # consumed from the front with del (no copy of the rest per message)

    def close(self) -> None:
        self.sock.close()

    def send(self, kind: str, payload: bytes = b"") -> None:
        self.sock.sendall(struct.pack(">HB", 3 + len(payload), ord(kind)) + payload)

    def read(self) -> tuple[str, bytes]:
        while len(self.buf) < 3 or len(self.buf) < struct.unpack(">H", self.buf[:2])[0]:
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError("closed")
            self.buf += chunk
        size = struct.unpack(">H", self.buf[:2])[0]
        kind, payload = chr(self.buf[2]), bytes(self.buf[3:size])
        del self.buf[:size]
        return kind, payload

    def request(self, kind: str, payload: bytes = b"") -> bytes:
        self.send(kind, payload)
        while True:
            got, reply = self.read()
            if got == kind:
                return reply

    def outputs(self, freq: float, names: str) -> tuple[int, str]:
        reply = self.request("O", struct.pack(">d", freq) + names.encode())
        return reply[0], reply[1:].decode()

    def inputs(self, names: str) -> tuple[int, str]:
        reply = self.request("I", names.encode())
        return reply[0], reply[1:].decode()

    def package(self) -> bytes:
        while True:
            kind, payload = self.read()
            if kind == "U":
                return payload

    def latest(self) -> bytes:
        """The newest data package: the next one, then any already received after it (a client on a
        busy machine reads slower than 500 Hz and would otherwise act on history)."""
        payload = self.package()
        while self._complete() or select.select([self.sock], [], [], 0)[0]:
            payload = self.package()
        return payload

    def _complete(self) -> bool:
        return len(self.buf) >= 3 and len(self.buf) >= struct.unpack(">H", self.buf[:2])[0]


@pytest.fixture
def emulator() -> Iterator[UREmulator]:
    threads, fds = set(threading.enumerate()), open_fds()
    arm = SimArm(SimArmConfig(**{**UR_LIKE, "time_scale": 0.05, "repeatability_m": 0.0}), BackendContext()).connect()
    arm.world.arm.set_flange_pose(HOME)
    emu = UREmulator(arm, "127.0.0.1", unlock_delay_s=0.2, ports=(0, 0, 0))
    emu.start()
    yield emu
    emu.close()
    arm.close()
    assert [t for t in threading.enumerate() if t not in threads and t.is_alive()] == []
    assert open_fds() - fds == set()


def turned_away(port: int) -> bool:
    """Whether a new connection is reset (during the handshake or at the first read) without a byte."""
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=1.0) as sock:
            return sock.recv(100) == b""
    except ConnectionResetError:
        return True


def upload(emu: UREmulator, text: str = SCRIPT) -> None:
    with socket.create_connection(("127.0.0.1", emu.ports[1]), timeout=2.0) as sock:
        sock.sendall(text.encode())
        deadline = time.monotonic() + 60.0
        while emu.role.programs_received == 0 and time.monotonic() < deadline:
            time.sleep(0.005)


def test_negotiation_and_recipe_setup(emulator: UREmulator) -> None:
    client = RawRTDE(emulator.ports[0])
    try:
        assert client.request("V", struct.pack(">H", 2)) == b"\x01"
        assert client.request("V", struct.pack(">H", 1)) == b"\x00"
        assert struct.unpack(">IIII", client.request("v")) == (5, 11, 0, 0)
        assert client.outputs(125.0, "timestamp,bogus,") == (0, "DOUBLE,NOT_FOUND")
        assert client.outputs(600.0, "timestamp,")[0] == 0                 # above the 500 Hz the controller has
        assert client.outputs(125.0, "timestamp,actual_TCP_pose,robot_mode,") == (1, "DOUBLE,VECTOR6D,INT32")
        assert client.inputs("input_int_register_0,") == (1, "INT32")       # numbered 1, 2... per connection
        assert client.inputs("input_double_register_0,input_int_register_1,") == (2, "DOUBLE,INT32")
        assert client.inputs("output_int_register_0,") == (0, "NOT_FOUND")   # outputs cannot be written
        other = RawRTDE(emulator.ports[0])
        assert other.inputs("input_int_register_0,input_int_register_5,") == (0, "IN_USE,INT32")
        client.close()
        deadline = time.monotonic() + 2.0
        while other.inputs("input_int_register_0,")[0] == 0 and time.monotonic() < deadline:
            time.sleep(0.01)                                                 # freed with its connection
        other.close()
    finally:
        client.close()


def test_stream_runs_at_the_requested_rate_with_controller_time(emulator: UREmulator) -> None:
    client = RawRTDE(emulator.ports[0])
    try:
        client.outputs(125.0, "timestamp,actual_TCP_pose,safety_status_bits,")
        assert client.request("S") == b"\x01"
        first = client.package()
        t0 = time.monotonic()
        stamps = [struct.unpack(">d", client.package()[1:9])[0] for _ in range(25)]
        assert time.monotonic() - t0 > 0.12                                  # 25 packages at 125 Hz: 0.2 s
        steps = np.diff(stamps)
        assert np.all(steps > 0) and np.median(steps) == pytest.approx(0.008, abs=0.0021)  # 8 ms apart
        assert np.allclose(np.round(np.array(stamps) / 0.002), np.array(stamps) / 0.002)   # whole 2 ms cycles
        pose = struct.unpack(">6d", first[9:57])
        assert pose_from_ur(pose).distance_to(HOME) < 1e-12 and struct.unpack(">I", first[57:61])[0] == 1
        assert client.request("P") == b"\x01"
    finally:
        client.close()


def _command(client: RawRTDE, cmd: int, doubles: list[float], asynchronous: int) -> None:
    client.send("U", bytes([1]) + struct.pack(">i8di", cmd, *doubles, asynchronous))


def _out(client: RawRTDE) -> tuple[int, int, int]:
    return struct.unpack(">iii", client.latest()[9:21])


def test_the_script_role_moves_the_arm_with_the_register_handshake(emulator: UREmulator) -> None:
    client = RawRTDE(emulator.ports[0])
    try:
        client.outputs(500.0, "timestamp,output_int_register_0,output_int_register_1,output_int_register_2,")
        recipe = ",".join(["input_int_register_0", *[f"input_double_register_{i}" for i in range(8)],
                           "input_int_register_1"]) + ","
        assert client.inputs(recipe)[0] == 1
        client.request("S")
        upload(emulator)
        assert emulator.state.program_running
        while _out(client)[0] != 1:                                          # the script signals ready
            pass
        target = Pose.from_xyz_rpy([0.42, 0.05, 0.40], [np.pi, 0.0, 0.4])
        _command(client, 3, [*pose_to_ur(target), 0.25, 1.2], 0)            # moveL, synchronous
        while _out(client)[0] != 2:                                          # done only once arrived
            pass
        assert emulator.state.arm.true_flange_pose().distance_to(target) < 1e-12
        _command(client, 0, [0.0] * 8, 0)                                     # clear: ready again
        while _out(client)[0] != 1:
            pass
        before = _out(client)[2]
        emulator.set_time_scale(1.0)                                         # real time: ~7 s, stopped early
        _command(client, 3, [*pose_to_ur(HOME), 0.01, 1.0], 1)                # moveL, asynchronous
        while True:
            state, _result, progress = _out(client)
            if state == 2:
                break
        assert progress & 0x8000 and (progress >> 24) == ((before >> 24) + 1) & 0x7F   # running, new operation
        _command(client, 0, [0.0] * 8, 0)
        # as ur_rtde does, wait for ready before the next command: the script takes a command only once
        # it has seen the clear (sent at once, a busy machine's script cycle could miss the clear)
        while _out(client)[0] != 1:
            pass
        _command(client, 33, [5.0] + [0.0] * 7, 0)                            # stopL
        while _out(client)[2] & 0x8000:
            pass
        assert not emulator.state.arm.is_moving()
        assert emulator.state.arm.true_flange_pose().distance_to(HOME) > 0.005
        assert emulator.role.commands == {3: 2, 33: 1}
    finally:
        client.close()


def test_safety_stops_set_the_modes_and_bits(emulator: UREmulator) -> None:
    state = emulator.state
    upload(emulator)
    assert (state.safety_mode, state.safety_status_bits(), state.robot_status_bits()) == (1, 1, 3)
    emulator.safety_stop("protective_stop")
    assert (state.safety_mode, state.safety_status_bits() & 4, state.program_running) == (3, 4, False)
    assert emulator.dashboard.reply("unlock protective stop").startswith("Cannot unlock protective stop")
    time.sleep(0.25)                                                         # unlock_delay_s = 0.2
    assert emulator.dashboard.reply("unlock protective stop") == "Protective stop releasing"
    emulator.safety_stop("emergency_stop")
    assert (state.safety_status_bits() & 0x80, state.robot_mode, emulator.dashboard.reply("robotmode")) == (
        0x80, 3, "Robotmode: POWER_OFF")
    assert emulator.dashboard.reply("power on") == "Powering on" and state.robot_mode == 3   # e-stop engaged
    emulator.release_emergency_stop()
    emulator.dashboard.reply("power on")
    emulator.dashboard.reply("brake release")
    assert state.robot_mode == 7 and emulator.dashboard.reply("play") == "Starting program"
    with pytest.raises(ValueError, match="at_progress"):
        emulator.safety_stop("protective_stop", at_progress=1.5)


def test_faults_freeze_the_stream_and_cut_the_links(emulator: UREmulator) -> None:
    client = RawRTDE(emulator.ports[0])
    client.outputs(500.0, "timestamp,")
    client.request("S")
    client.package()
    assert emulator.freeze_stream("receive") == 1
    client.sock.settimeout(0.2)
    with pytest.raises(TimeoutError):
        while True:
            client.package()                                                 # buffered ones, then silence
    client.sock.settimeout(2.0)
    emulator.unfreeze_stream()
    client.package()
    assert emulator.drop_connections(refuse_s=-1.0) >= 1
    with pytest.raises(ConnectionError):
        while True:
            client.package()
    client.close()
    assert turned_away(emulator.ports[2])                                    # reset at once, no greeting
    emulator.accept_connections()
    with socket.create_connection(("127.0.0.1", emulator.ports[2]), timeout=1.0) as dash:
        assert dash.recv(100) == b"Connected: Universal Robots Dashboard Server\n"


def test_dashboard_over_its_socket(emulator: UREmulator) -> None:
    with socket.create_connection(("127.0.0.1", emulator.ports[2]), timeout=2.0) as sock:
        stream = sock.makefile("rw", newline="\n")
        assert stream.readline() == "Connected: Universal Robots Dashboard Server\n"
        replies = {}
        for command in ("PolyscopeVersion", "get serial number", "is in remote control", "robotmode",
                        "safetystatus", "running", "programState", "stop", "bogus thing"):
            stream.write(command + "\n")
            stream.flush()
            replies[command] = stream.readline().rstrip("\n")
        assert replies == {
            "PolyscopeVersion": "URSoftware 5.11.0.108249 (Nov 04 2021)", "get serial number": "20235500001",
            "is in remote control": "true", "robotmode": "Robotmode: RUNNING", "safetystatus": "Safetystatus: NORMAL",
            "running": "Program running: false", "programState": "STOPPED rtde_control", "stop": "Stopped",
            "bogus thing": "could not understand: 'bogus thing'"}
        stream.write("quit\n")
        stream.flush()
        assert stream.readline() == "Disconnected\n" and stream.readline() == ""


def test_program_reader_finds_whole_programs_in_any_chunks() -> None:
    text = "stopj(2)\n" + SCRIPT + "def other():\n  textmsg(\"x\")\nend\n"
    reader = ProgramReader()
    found = [p for i in range(0, len(text), 7) for p in reader.feed(text[i:i + 7].encode())]
    assert found == [SCRIPT.rstrip("\n"), "def other():\n  textmsg(\"x\")\nend"]


def test_a_foreign_program_or_a_refused_script_does_not_run(emulator: UREmulator) -> None:
    upload(emulator, "def other():\n  sleep(1)\nend\n")
    assert not emulator.state.program_running
    emulator.refuse_script()
    emulator.role.programs_received = 0
    upload(emulator)
    assert not emulator.state.program_running and emulator.role.programs_received == 1


def test_joints_are_the_sim_chain_reported_as_six() -> None:
    q = np.array([0.0, 0.3, 1.1, 1.4, 0.0, 0.7])
    pose = pose_from_joints(q)
    back = ur_joints(pose, None)
    assert back.shape == (6,) and back[4] == 0.0
    np.testing.assert_allclose(back, q, atol=1e-9)
    turned = pose_from_joints([0.5, 0.3, 1.1, 1.4, 0.0, -0.6])
    again = ur_joints(turned, None)
    assert pose_from_joints(again).distance_to(turned) < 1e-9               # position exact
    assert again[0] == pytest.approx(0.5, abs=1e-12)                        # base joint as commanded
    assert again[4] == 0.0 and again[5] == pytest.approx(-0.6, abs=1e-3)   # the chain's own wrist solution
