"""``python -m cellcal.sims.xarm``: prints the pty path first (TCP: a ``ready`` line), serves until terminated."""

from __future__ import annotations

import signal
import subprocess
import sys

import numpy as np
import pytest
from emulator_cli import first_line, stop

from cellcal.devices.pose import Pose
from cellcal.drivers.xarm.arm import XArmArm


def _moves_where_told(cfg: XArmArm.Config, axes: int) -> None:
    with XArmArm(cfg) as drv:
        assert drv.info().model == f"xArm {axes}"
        start = drv.get_pose()
        target = Pose(start.rotation, start.translation + np.array([0.02, -0.03, -0.05]))
        drv.move_linear(target, speed=0.2, acceleration=2.0, timeout=10.0)
        assert drv.get_pose().distance_to(target) < 1e-3


@pytest.mark.parametrize(("axes", "tcp"), [(5, False), (7, False), (5, True)], ids=["pty-5", "pty-7", "tcp-5"])
def test_module_prints_where_it_serves_and_serves(axes: int, tcp: bool) -> None:
    extra = ["--tcp-port", "0", "--report-port", "0"] if tcp else []
    proc = subprocess.Popen([sys.executable, "-m", "cellcal.sims.xarm", "--axes", str(axes), "--time-scale", "0",
                             *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = first_line(proc, 30.0)
        if tcp:  # "ready 127.0.0.1 tcp=P report=Q" once both ports listen
            assert line.startswith("ready 127.0.0.1 ")
            ports = dict(w.split("=") for w in line.split()[2:])
            cfg = XArmArm.Config(host="127.0.0.1", tcp_port=int(ports["tcp"]), report_port=int(ports["report"]),
                                 axes=axes)  # type: ignore[arg-type]
        else:
            assert line.startswith("/dev/pts/") or line.startswith("/dev/tty")
            cfg = XArmArm.Config(port=line, axes=axes)  # type: ignore[arg-type]
        _moves_where_told(cfg, axes)
    finally:
        out, err = stop(proc, signal.SIGTERM)
    assert proc.returncode == 0, err
    assert out.strip() == ""  # nothing after the first line on stdout
