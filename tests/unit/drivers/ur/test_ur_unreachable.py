"""An unreachable UR is one line: refused told from a silent listener, ur_rtde's own output kept out of sight.

Real ur_rtde (skipped where it is absent) against loopback addresses: one with nothing
listening (every port refused) and one where a listener accepts and says nothing.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
from collections.abc import Iterator

import pytest

from cellcal.devices.errors import DeviceConnectionError, DeviceTimeoutError
from cellcal.drivers.ur.arm import URArm
from cellcal.drivers.ur.dashboard import DashboardLink
from cellcal.drivers.ur.fd_capture import captured_output

pytest.importorskip("rtde_receive")
pytest.importorskip("dashboard_client")

UR_PORTS = (30004, 30003, 29999)


def _free_loopback(tried: range = range(150, 250)) -> str:
    """A 127.0.0.N whose UR ports nothing listens on (checked by binding them)."""
    for n in tried:
        host = f"127.0.0.{n}"
        socks: list[socket.socket] = []
        try:
            for port in UR_PORTS:
                s = socket.socket()
                socks.append(s)
                s.bind((host, port))
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
        return host
    pytest.skip("no free 127.0.0.N with the UR ports closed")


@pytest.fixture
def closed_host() -> str:
    return _free_loopback()


@pytest.fixture
def silent_host() -> Iterator[str]:
    """A loopback address whose UR ports accept connections and never send a byte."""
    host = _free_loopback(range(200, 250))
    with contextlib.ExitStack() as stack:
        for port in UR_PORTS:
            s = stack.enter_context(socket.socket())
            s.bind((host, port))
            s.listen(8)
        yield host


def _arm(host: str, *, isolate: bool = True) -> URArm:
    return URArm.from_config({"backend": "ur", "host": host, "timeout_s": 1.0, "isolate": isolate})


def test_a_closed_port_is_one_line_saying_refused(closed_host: str, capfd: pytest.CaptureFixture[str],
                                                  caplog: pytest.LogCaptureFixture) -> None:
    arm = _arm(closed_host)
    with caplog.at_level(logging.WARNING), pytest.raises(DeviceConnectionError) as info:
        arm.connect(timeout=1.0)
    message = str(info.value)
    assert message == (f"ur {closed_host}: connection refused on the RTDE port 30004 (nothing listens there: "
                       f"is the controller on, and is {closed_host} its address?)")
    assert "\n" not in message and "timeout" not in message.lower()
    assert not arm.connected
    out, err = capfd.readouterr()
    assert (out, err) == ("", "")                          # nothing of ur_rtde's, no second line
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING] == []


def test_a_silent_listener_is_a_timeout_not_refused(silent_host: str, capfd: pytest.CaptureFixture[str]) -> None:
    arm = _arm(silent_host)
    with pytest.raises(DeviceTimeoutError) as info:
        arm.connect(timeout=0.5)
    message = str(info.value)
    assert message.startswith(f"ur {silent_host}: the RTDE port 30004 accepted the connection but sent no data "
                              "within 0.5 s")
    assert "refused" not in message and "\n" not in message
    assert capfd.readouterr() == ("", "")


def test_a_refused_dashboard_says_refused_not_timeout(closed_host: str, caplog: pytest.LogCaptureFixture) -> None:
    link = DashboardLink(closed_host, 29999)
    with caplog.at_level(logging.WARNING, logger="cellcal.drivers.ur.dashboard"):
        assert link.open(1.0, required=False) is None
    (record,) = caplog.records
    assert record.getMessage() == (f"ur {closed_host}: dashboard unavailable (connection refused on the dashboard "
                                   f"port 29999 (nothing listens there: is the controller on, and is {closed_host} "
                                   "its address?)); identity unknown")
    with pytest.raises(DeviceConnectionError, match=r"dashboard server port 29999: connection refused"):
        link.open(1.0, required=True)


def test_output_written_to_the_file_descriptors_goes_to_the_debug_log(capfd: pytest.CaptureFixture[str],
                                                                     caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.DEBUG, logger="cellcal.drivers.ur.fd_capture"):
        with captured_output("ur 127.0.0.9: connect"):
            os.write(2, b"connect: Connection refused\n")  # as a C++ library writes: below sys.stderr
            os.write(1, b"RTDE: reconnecting\n")
        print("after the capture")
    out, err = capfd.readouterr()
    assert (out, err) == ("after the capture\n", "")
    (record,) = caplog.records
    assert record.levelno == logging.DEBUG
    assert record.getMessage() == ("ur 127.0.0.9: connect: the vendor library printed: "
                                   "connect: Connection refused | RTDE: reconnecting")


def test_ur_rtde_own_dashboard_output_is_captured(closed_host: str, capfd: pytest.CaptureFixture[str]) -> None:
    import dashboard_client

    with captured_output("dashboard"):
        client = dashboard_client.DashboardClient(closed_host, 29999)
        with contextlib.suppress(RuntimeError):
            client.connect(200)
    assert capfd.readouterr() == ("", "")


def test_the_captured_text_is_bounded(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.DEBUG, logger="cellcal.drivers.ur.fd_capture"), captured_output("noisy", limit=10):
        os.write(2, b"x" * 100_000)
    assert caplog.records[0].getMessage() == "noisy: the vendor library printed: xxxxxxxxxx [...]"


def test_ur_rtde_own_constructor_output_goes_to_the_debug_log(closed_host: str, capfd: pytest.CaptureFixture[str],
                                                              caplog: pytest.LogCaptureFixture) -> None:
    import rtde_receive

    arm = _arm(closed_host, isolate=False)                  # in-process: the output capture of this process
    arm._rtde_receive = rtde_receive
    with caplog.at_level(logging.DEBUG, logger="cellcal.drivers.ur.fd_capture"), \
            pytest.raises(DeviceConnectionError, match=f"ur {closed_host}: cannot open the RTDE receive interface"):
        arm._new_receive(arm._clock() + 1.0)                # ur_rtde itself, past the driver's probe
    assert capfd.readouterr() == ("", "")
    (record,) = caplog.records
    assert record.getMessage().startswith(f"ur {closed_host}: open the RTDE receive interface: the vendor library "
                                          "printed: ")
    assert "Connection refused" in record.getMessage()
