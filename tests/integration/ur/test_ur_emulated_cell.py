"""``backend = "ur-emulated"``: a calibration through ur_rtde and the UR emulator gives the pure sim's angles."""

from __future__ import annotations

import json
import time
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cellcal.core.calibration.calibrator import Calibrator, build_devices
from cellcal.core.calibration.config import load_config
from cellcal.core.cli import main
from cellcal.devices.base import BackendContext
from cellcal.devices.errors import ConfigError
from cellcal.devices.pose import Pose
from cellcal.devices.registry import default_registry
from cellcal.sims.motion import trapezoid_duration
from cellcal.sims.ur.backend import EmulatedURArm

pytest.importorskip("rtde_control")  # the ur extra

CONFIGS = Path(str(resources.files("cellcal.configs")))


def angles(result: dict[str, Any]) -> list[tuple[int, int, str, float]]:
    return [(p["index"], m["perimeter_px"], m["method"], m["angle_deg"]) for p in result["poses"]
            for m in p["measurements"]]


def test_calibrate_with_the_ur_behind_the_emulator_matches_the_pure_sim(tmp_path: Path) -> None:
    config = load_config(CONFIGS / "sim.toml")
    pure = angles(Calibrator(config, *build_devices(config)).run())
    assert main(["calibrate", "--config", str(CONFIGS / "ur_emulated.toml"), "--out", str(tmp_path), "--quiet"]) == 0
    emulated = angles(json.loads((tmp_path / "result.json").read_text()))
    assert [a[:3] for a in emulated] == [a[:3] for a in pure] and len(pure) >= 12
    worst = max(abs(e[3] - s[3]) for e, s in zip(emulated, pure, strict=True))
    assert worst < 0.01, f"largest angle difference {worst:.3g} deg"


def test_the_backend_shares_the_sim_world_and_ends_its_emulator() -> None:
    ctx = BackendContext(section="arm", document={"sim": {}}, seed=7)
    with pytest.raises(ConfigError):
        default_registry().create_arm({"backend": "ur-emulated", "bogus": 1}, ctx)
    arm = default_registry().create_arm({"backend": "ur-emulated", "time_scale": 0.001}, ctx)
    assert isinstance(arm, EmulatedURArm) and arm.config.reach_m == 0.85        # UR5e-like defaults
    world = ctx.shared["sim.world"]
    clock0 = world.clock.elapsed_s
    with arm:
        emulator = arm.emulator
        assert emulator is not None and arm.host.startswith("127.0.0.")
        assert arm.driver is not None and arm.driver.backend_name == "ur"      # the registry's ur driver
        assert arm.info().backend == "ur-emulated" and arm.info().extra["emulated"]
        start = arm.get_pose()
        true_start = world.arm.flange_pose()
        assert start.distance_to(true_start) < 1e-4                            # the child starts where the world is
        target = Pose(start.rotation, start.translation + np.array([0.03, -0.02, 0.04]))
        arm.move_linear(target, speed=0.3, acceleration=2.0)
        assert world.arm.flange_pose().distance_to(target) < 1e-9              # mirrored exactly
        # the clock advanced by the motion's simulated duration, as in a pure sim
        expected = trapezoid_duration(true_start.distance_to(target), 0.3, 2.0)
        assert world.clock.elapsed_s - clock0 == pytest.approx(expected, rel=1e-9)
    assert arm.emulator is None and arm.driver is None
    deadline = time.monotonic() + 60.0
    while emulator.running and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not emulator.running


def test_a_slow_emulator_start_is_within_the_connect_the_calibrator_allows(tmp_path: Path) -> None:
    """On a loaded machine the emulator process takes seconds to start: the calibrator's connect allows its
    start_timeout_s on top of the driver's timeout (it gave 2 s + 2 s grace, and abandoned the connect)."""
    config = load_config(CONFIGS / "ur_emulated.toml")
    camera, arm = build_devices(config)
    inner = arm.inner
    assert isinstance(inner, EmulatedURArm)
    assert arm.connect_timeout_s == inner.config.start_timeout_s + inner.default_timeout_s  # through SafeArm
    inner.on_emulator_started = lambda _emulator: time.sleep(inner.default_timeout_s + 3.0)  # a start beyond 4 s
    calibrator = Calibrator(config, camera, arm)
    t0 = time.monotonic()
    result = calibrator.run()
    assert time.monotonic() - t0 > inner.default_timeout_s + 3.0 and len(result["poses"]) == 3
