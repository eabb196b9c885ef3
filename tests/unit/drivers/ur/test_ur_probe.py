"""The driver's plain-socket RTDE probe against the UR emulator (in this process) and against bad peers."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator

import pytest

from cellcal.devices.base import BackendContext
from cellcal.devices.errors import DeviceConnectionError, DeviceTimeoutError, ProtocolError
from cellcal.drivers.ur.rtde_probe import probe_stream
from cellcal.sims.arm import SimArm, SimArmConfig
from cellcal.sims.ur.emulator import UREmulator


@pytest.fixture
def emulator() -> Iterator[UREmulator]:
    arm = SimArm(SimArmConfig(time_scale=0.0), BackendContext()).connect()
    emu = UREmulator(arm, "127.0.0.1", ports=(0, 0, 0))
    emu.start()
    yield emu
    emu.close()
    arm.close()


def test_a_streaming_controller_answers_with_its_time(emulator: UREmulator) -> None:
    time.sleep(0.05)
    ts = probe_stream("127.0.0.1", 1.0, port=emulator.ports[0])
    assert 0.04 <= ts <= emulator.state.timestamp() and round(ts / 0.002) * 0.002 == pytest.approx(ts)


def test_a_silent_stream_is_a_timeout_within_the_time_given(emulator: UREmulator) -> None:
    emulator.freeze_stream("all", new_sessions=True)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeoutError, match=r"sent no data within 0\.3 s"):
        probe_stream("127.0.0.1", 0.3, port=emulator.ports[0])
    assert 0.3 <= time.monotonic() - t0 < 3.0                 # the time given (with room for a busy machine)


def test_no_listener_is_a_connection_error(emulator: UREmulator) -> None:
    port = emulator.ports[0]
    emulator.close()
    with pytest.raises(DeviceConnectionError, match="refused"):
        probe_stream("127.0.0.1", 1.0, port=port)


def test_a_peer_that_does_not_speak_rtde_is_a_protocol_error() -> None:
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]

    def answer_nonsense() -> None:
        conn, _ = server.accept()
        with conn:
            conn.recv(100)
            conn.sendall(b"\x00\x04X\x01")           # a well-framed reply of the wrong type
            time.sleep(0.2)

    thread = threading.Thread(target=answer_nonsense)
    thread.start()
    try:
        with pytest.raises(ProtocolError, match="reply type 88"):
            probe_stream("127.0.0.1", 1.0, port=port)
    finally:
        thread.join(2.0)
        server.close()
