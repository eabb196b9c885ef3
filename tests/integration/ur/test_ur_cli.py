"""``python -m cellcal.sims.ur --host 127.0.0.N``: one ``ready`` line once all three ports listen, then serves."""

from __future__ import annotations

import random
import signal
import socket
import subprocess
import sys
import time

import pytest
from emulator_cli import first_line, stop

pytest.importorskip("rtde_control")  # the ur extra
import rtde_receive

from cellcal.sims.ur.__main__ import main


def free_loopback_host() -> str:
    """A 127.0.0.N whose UR ports are free now."""
    for n in random.sample(range(100, 250), 150):
        host = f"127.0.0.{n}"
        socks = []
        try:
            for port in (30004, 30003, 29999):
                s = socket.socket()
                socks.append(s)
                s.bind((host, port))
            return host
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
    pytest.skip("no free loopback address for the UR ports")


def test_module_prints_ready_serves_ur_rtde_and_exits_130_on_ctrl_c() -> None:
    host = free_loopback_host()
    proc = subprocess.Popen([sys.executable, "-m", "cellcal.sims.ur", "--host", host, "--time-scale", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert first_line(proc, 30.0) == f"ready {host} rtde=30004 script=30003 dashboard=29999"
        receive = rtde_receive.RTDEReceiveInterface(host)
        pose = receive.getActualTCPPose()
        assert receive.getRobotMode() == 7 and abs(pose[0] - 0.3) < 1e-3 and abs(pose[2] - 0.5) < 1e-3
        del receive
    finally:
        out, err = stop(proc, signal.SIGINT)
    assert proc.returncode == 130, err
    assert out.strip() == ""                     # nothing after the ready line on stdout


def test_bad_arguments_are_one_line_errors(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--host", "127.0.0.1", "--arm-config", "[1, 2]"]) == 1
    assert capsys.readouterr().err.strip() == "error: --arm-config must be a JSON object: not a JSON object"
    assert main(["--host", "127.0.0.1", "--arm-config", '{"wingspan": 1}']) == 1
    assert "unexpected keyword argument 'wingspan'" in capsys.readouterr().err
    t0 = time.monotonic()
    assert main(["--host", "192.0.2.1"]) == 1    # not a local address: nothing can listen there
    assert "cannot listen on 192.0.2.1" in capsys.readouterr().err and time.monotonic() - t0 < 5
