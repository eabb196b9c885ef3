"""``python -m cellcal.sims.xarm``: prints the pty path first, serves until terminated."""

from __future__ import annotations

import selectors
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from cellcal.devices.pose import Pose
from cellcal.drivers.xarm.arm import XArmArm


def _first_line(proc: subprocess.Popen[str], timeout: float) -> str:
    assert proc.stdout is not None
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if sel.select(timeout=0.1):
            return proc.stdout.readline().strip()
        if proc.poll() is not None:
            break
    pytest.fail("emulator printed no path in time")


@pytest.mark.parametrize("axes", [5, 7])
def test_module_prints_pty_path_and_serves(axes: int) -> None:
    proc = subprocess.Popen([sys.executable, "-m", "cellcal.sims.xarm", "--axes", str(axes), "--time-scale", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        path = _first_line(proc, 30.0)
        assert path.startswith("/dev/pts/") or path.startswith("/dev/tty")
        with XArmArm(XArmArm.Config(port=path, axes=axes)) as drv:  # type: ignore[arg-type]
            assert drv.info().model == f"xArm {axes}"
            start = drv.get_pose()
            target = Pose(start.rotation, start.translation + np.array([0.02, -0.03, -0.05]))
            drv.move_linear(target, speed=0.2, acceleration=2.0, timeout=10.0)
            assert drv.get_pose().distance_to(target) < 1e-3
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            out, err = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
            raise
    assert proc.returncode == 0, err
    assert out.strip() == ""  # nothing after the path on stdout
