"""``cellcal devices --scan`` survives backends whose discovery aborts, hangs or chatters.

Each backend here is a real installed distribution (a ``.dist-info`` with entry points on
PYTHONPATH), so the scan's child process finds it exactly as it finds a vendor's package.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

_MODULE = '''
import os, sys, time
from cellcal.devices.camera import Camera3D
from cellcal.devices.types import DeviceInfo

class _Base(Camera3D):
    backend_name = "x"

class AbortCamera(_Base):
    @classmethod
    def discover(cls, timeout=2.0):
        sys.stderr.write("native: fatal assertion\\n"); sys.stderr.flush()
        os.abort()

class HangCamera(_Base):
    @classmethod
    def discover(cls, timeout=2.0):
        time.sleep(3600)

class ChattyCamera(_Base):
    @classmethod
    def discover(cls, timeout=2.0):
        sys.stderr.write("SDK banner on stderr\\n")
        print("SDK banner on stdout")
        return [DeviceInfo(backend="chatty", vendor="Chat", model="C1", serial="42")]
'''


@pytest.fixture
def plugin_path(tmp_path: Path) -> Path:
    """A tiny installed distribution providing three hostile camera backends."""
    (tmp_path / "hostile_scan.py").write_text(_MODULE)
    info = tmp_path / "hostile_scan-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: hostile-scan\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(
        "[cellcal.cameras]\n"
        "zz-abort = hostile_scan:AbortCamera\nzz-hang = hostile_scan:HangCamera\n"
        "zz-chatty = hostile_scan:ChattyCamera\n")
    return tmp_path


def _scan(plugin_path: Path, timeout: float) -> tuple[subprocess.CompletedProcess[str], float]:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(plugin_path), os.environ.get("PYTHONPATH", "")]))
    start = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "cellcal.core.cli", "devices", "--scan", "--hosts", "127.0.0.1",
                           "--timeout", str(timeout)],
                          capture_output=True, text=True, env=env, timeout=300, check=False)
    return done, time.monotonic() - start


def test_abort_hang_and_chatter_each_cost_one_line(plugin_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from cellcal.core.cli import devices
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(plugin_path), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setattr(devices, "_CHILD_STARTUP_S", 5.0)
    assert devices.scan_lines("camera", "zz-abort", 0.2) == [
        "unavailable: discovery crashed (signal SIGABRT): native: fatal assertion"]
    assert devices.scan_lines("camera", "zz-chatty", 0.2) == ["Chat C1 42"]
    # a discovery that never returns is killed at its timeout plus the start-up allowance
    start = time.monotonic()
    assert devices.scan_lines("camera", "zz-hang", 0.2) == ["unavailable: discovery did not finish within 5.2 s"]
    assert 5.2 <= time.monotonic() - start < 5.2 + 3.0


def test_scan_command_survives_hostile_backends(plugin_path: Path) -> None:
    done, elapsed = _scan(plugin_path, 0.2)
    assert done.returncode == 0, done.stderr
    out = done.stdout
    assert "camera zz-abort: unavailable: discovery crashed (signal SIGABRT): native: fatal assertion" in out
    assert "camera zz-hang: unavailable: discovery did not finish within 10.2 s" in out
    assert "camera zz-chatty: Chat C1 42" in out
    # the SDK's own chatter goes nowhere near the report
    assert "banner" not in out and "banner" not in done.stderr
    assert "Traceback" not in out + done.stderr
    # every other backend is still scanned after them
    assert "camera sim: no discovery" in out
    assert elapsed < 60
