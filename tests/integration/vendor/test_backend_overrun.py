"""The calibrator and the monitor do not trust a backend to honour its timeout.

A vendor camera whose ``capture`` never returns (or swallows every exception while it
waits) is registered at run time next to cellcal's simulated arm. Each run must end
within the capture timeout plus the guard's grace, name the backend and the call, tell
the arm to stop, and (through the CLI) exit 1 — on the main thread (a SIGALRM timer
interrupts the call) and off it (the call runs in a worker that is abandoned).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest

from cellcal.core.calibration import calibrator as calibrator_module
from cellcal.core.calibration.calibrator import Calibrator, build_devices
from cellcal.core.calibration.config import load_config
from cellcal.core.cli import main
from cellcal.core.monitor import monitor as monitor_module
from cellcal.devices import BackendContext, Camera3D, DeviceInfo, Frame, Intrinsics, default_registry
from cellcal.devices.errors import BackendOverrunError

#: Set at teardown so nothing a test abandons outlives it.
_release = threading.Event()
INTR = Intrinsics(32, 24, 30.0, 30.0, 15.5, 11.5)
GRACE_S = 0.5
CAPTURE_TIMEOUT_S = 0.3

CELL = """
[cell]
name = "overrun"
[camera]
backend = "{backend}"
[arm]
backend = "sim"
time_scale = 0.0
[mount]
translation_m = [0.0, 0.04, 0.06]
rpy_deg = [0.0, 0.0, 90.0]
[reference]
plane_point_m = [0.0, 0.0, 0.0]
plane_normal = [0.0, 0.0, 1.0]
[safety]
workspace_min_m = [-0.1, -0.5, 0.05]
workspace_max_m = [0.7, 0.5, 0.9]
max_speed_m_s = 0.5
max_acceleration_m_s2 = 2.0
min_standoff_m = 0.2
[plan]
heights_m = [0.46]
inclination_deg = 80.0
target_m = [0.3, 0.0, 0.0]
perimeters_px = [10]  # the 32x24 image holds the P1-P9 grid up to 10 px
capture_timeout_s = {timeout}
"""


class StuckCamera(Camera3D):
    """A vendor camera whose capture blocks for ever, ignoring its timeout (``stubborn``: and every exception)."""

    backend_name = "stuck-cam"
    stubborn: ClassVar[bool] = False
    captures_started: ClassVar[int] = 0

    @dataclass(frozen=True)
    class Config:
        pass

    def __init__(self, config: Any = None, context: BackendContext | None = None):
        super().__init__()

    def _connect(self, timeout: float) -> None:
        pass

    def _close(self) -> None:
        pass

    def _info(self) -> DeviceInfo:
        return DeviceInfo(backend=self.backend_name, vendor="Stuck", model="S1")

    def _intrinsics(self) -> Intrinsics:
        return INTR

    def _capture(self, timeout: float) -> Frame:
        type(self).captures_started += 1
        while not _release.is_set():
            try:
                _release.wait(0.05)
            except Exception:  # what a careless backend does: swallow everything and wait on
                if not self.stubborn:
                    raise
        raise RuntimeError("released at teardown")


class StubbornCamera(StuckCamera):
    backend_name = "stubborn-cam"
    stubborn = True


@pytest.fixture(autouse=True)
def _registered(monkeypatch: pytest.MonkeyPatch) -> Any:
    monkeypatch.setattr(calibrator_module, "GUARD_GRACE_S", GRACE_S)
    monkeypatch.setattr(monitor_module, "MONITOR_GRACE_S", GRACE_S)
    registry = default_registry()
    for cls in (StuckCamera, StubbornCamera):
        registry.register("camera", cls.backend_name, cls)
    _release.clear()
    yield
    _release.set()
    for cls in (StuckCamera, StubbornCamera):
        registry.unregister("camera", cls.backend_name)


def _cell(tmp_path: Path, backend: str) -> Path:
    path = tmp_path / "cell.toml"
    path.write_text(CELL.format(backend=backend, timeout=CAPTURE_TIMEOUT_S))
    return path


def _run(tmp_path: Path, backend: str) -> tuple[BaseException | None, float, Calibrator]:
    config = load_config(str(_cell(tmp_path, backend)))
    camera, arm = build_devices(config)
    calibrator = Calibrator(config, camera, arm)
    t0 = time.monotonic()
    try:
        calibrator.run()
    except BaseException as exc:
        return exc, time.monotonic() - t0, calibrator
    return None, time.monotonic() - t0, calibrator


@pytest.mark.parametrize("backend", ["stuck-cam", "stubborn-cam"])
def test_a_capture_that_never_returns_ends_the_run_naming_the_backend_and_the_arm_stops(
        tmp_path: Path, backend: str) -> None:
    assert threading.current_thread() is threading.main_thread()     # the SIGALRM path
    error, took, calibrator = _run(tmp_path, backend)
    assert isinstance(error, BackendOverrunError)
    assert str(error) == (f"camera backend '{backend}': capture(timeout={CAPTURE_TIMEOUT_S:g} s) did not return "
                          f"within {CAPTURE_TIMEOUT_S + GRACE_S:g} s (its timeout + {GRACE_S:g} s): the backend "
                          "does not honour its timeout")
    # abandoned at its deadline: never before it; after it by less than 5 s even on a loaded machine (a capture
    # that is waited for never returns)
    assert CAPTURE_TIMEOUT_S + GRACE_S <= took < CAPTURE_TIMEOUT_S + GRACE_S + 5.0
    assert calibrator.arm.inner.stops == 1 and not calibrator.arm.connected and not calibrator.camera.connected


def test_off_the_main_thread_the_call_is_abandoned_in_time(tmp_path: Path) -> None:
    outcome: list[tuple[BaseException | None, float, Calibrator]] = []
    runner = threading.Thread(target=lambda: outcome.append(_run(tmp_path, "stuck-cam")))
    runner.start()
    runner.join(10.0)
    (error, took, calibrator), = outcome
    assert isinstance(error, BackendOverrunError) and "camera backend 'stuck-cam': capture" in str(error)
    assert took < CAPTURE_TIMEOUT_S + GRACE_S + 5.0  # room for a loaded machine; a capture waited for never returns
    assert calibrator.arm.inner.stops == 1


def test_the_cli_exits_1_with_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["calibrate", "--config", str(_cell(tmp_path, "stuck-cam")), "--out", str(tmp_path / "out"),
                 "--quiet"])
    assert code == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "camera backend 'stuck-cam': capture(timeout=0.3 s) did not return" in err[0]
    assert not (tmp_path / "out" / "result.json").exists()


def test_the_monitor_ends_on_an_overrunning_camera(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    t0 = time.monotonic()
    code = main(["monitor", "--config", str(_cell(tmp_path, "stuck-cam")), "--duration", "20"])
    took = time.monotonic() - t0
    assert code == 1 and took < 12.0                  # not the 20 s of --duration: the first capture ended it
    err = capsys.readouterr().err
    assert "camera backend 'stuck-cam'" in err and "capture(timeout=" in err and "does not honour its timeout" in err


def test_a_guarded_call_that_returns_in_time_is_untouched() -> None:
    from cellcal.devices.blocking import DeadlineGuard

    guard = DeadlineGuard("camera backend 'x'", grace_s=0.2)
    values = [guard.call(lambda i=i: np.float64(i) * 2, 0.1, "capture(timeout=0.1 s)") for i in range(200)]
    assert values == [2.0 * i for i in range(200)]
    time.sleep(0.4)                                   # no stray alarm fires after the calls
