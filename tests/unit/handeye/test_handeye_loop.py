"""The hand-eye loop: a [plan] with an estimated mount stays within a 5-axis arm's reach; what cannot is named."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
from repo_paths import REPO_ROOT

from cellcal.core.calibration.calibrator import Calibrator, build_devices
from cellcal.core.calibration.config import load_config, plan_flange_poses
from cellcal.core.calibration.dryrun import dry_run
from cellcal.core.calibration.reach import reachable_plan_poses
from cellcal.core.cli import main
from cellcal.core.handeye.board_config import missing_board_hint
from cellcal.devices.errors import SafetyError, VendorError
from cellcal.devices.geometry.reach import sideways_tilt_rad
from cellcal.devices.pose import Pose

CONFIG = REPO_ROOT / "configs" / "sim_handeye.toml"
TRUTH = tomllib.loads(CONFIG.read_text())["sim"]["mount"]
NOMINAL = 'translation_m = [0.0, 0.04, 0.06]\nrpy_deg = [0.0, 0.0, 90.0]\n'


def with_mount(tmp_path: Path, mount: str, extra: str = "") -> Path:
    """The shipped hand-eye config with ``[mount]`` replaced (and ``extra`` appended)."""
    text = CONFIG.read_text()
    assert NOMINAL in text
    path = tmp_path / "cell.toml"
    path.write_text(text.replace(NOMINAL, mount) + extra)
    return path


def true_mount_text() -> str:
    return f"translation_m = {TRUTH['translation_m']}\nrpy_deg = {TRUTH['rpy_deg']}\n"


def view(flange: Pose, mount: Pose) -> tuple[np.ndarray, float, np.ndarray]:
    """Where the optical axis meets the plane z = 0, the distance to it (m) and the axis."""
    camera = flange @ mount
    axis = camera.apply_vector([0.0, 0.0, 1.0])
    t = -camera.translation[2] / axis[2]
    return camera.translation + t * axis, float(t), axis


def test_an_off_axis_mount_would_tilt_the_tool_sideways_and_each_view_is_moved_within_reach(tmp_path: Path) -> None:
    config = load_config(with_mount(tmp_path, true_mount_text()))
    mount = config.mount.pose()
    asked, run = plan_flange_poses(config), reachable_plan_poses(config)
    tilts = [math.degrees(sideways_tilt_rad(p)) for p in asked]
    assert max(tilts) == pytest.approx(0.6875, abs=0.01)  # what an xArm 5 refused as "error 21"
    for a, r in zip(asked, run, strict=True):
        assert sideways_tilt_rad(r) < 1e-9
        target_a, h_a, axis_a = view(a, mount)
        target_r, h_r, axis_r = view(r, mount)
        assert np.allclose(target_r, target_a, atol=1e-9) and np.allclose(target_a, [0.3, 0.0, 0.0], atol=1e-9)
        assert h_r == pytest.approx(h_a, abs=1e-9)  # the same distance along the optical axis
        moved = math.degrees(math.acos(min(1.0, float(axis_a @ axis_r))))
        assert moved <= 1.5 * math.degrees(sideways_tilt_rad(a)) + 1e-6  # about the sideways tilt
        assert math.degrees(a.angle_to(r)) < 1.2


def test_a_plan_the_arm_can_take_is_left_as_it_is() -> None:
    config = load_config(CONFIG)  # the nominal mount: camera axes along the flange's
    for a, r in zip(plan_flange_poses(config), reachable_plan_poses(config), strict=True):
        assert r.is_close(a, atol_m=0.0, atol_rad=0.0)


def test_calibrate_dry_run_checks_reach_and_names_what_a_5_axis_arm_cannot_take(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = with_mount(tmp_path, true_mount_text())
    assert main(["calibrate", "--dry-run", "--config", str(cfg)]) == 0
    out = capsys.readouterr().out
    assert out.count("reach ok ('xarm5' arm)") == 4
    # explicit flange poses are the user's: the second one tilts the tool 3 deg sideways
    poses = ('\n[[plan.poses]]\nxyz_m = [0.3, 0.0, 0.5]\nrpy_deg = [180.0, 0.0, 0.0]\n'
             '\n[[plan.poses]]\nxyz_m = [0.3, 0.0, 0.5]\nrpy_deg = [177.0, 0.0, 0.0]\n')
    bad = with_mount(tmp_path, NOMINAL, poses)
    lines: list[str] = []
    with pytest.raises(SafetyError, match=r"plan pose 2 \(xyz=\(0\.3000, 0\.0000, 0\.5000\) m .*out of reach of a "
                                          r"'xarm5' arm: tool axis tilted 3\.000 deg sideways"):
        dry_run(load_config(bad), emit=lines.append)
    assert "REJECTED: out of reach of a 'xarm5' arm" in lines[-1] and lines[-1].startswith("move 2/2")
    assert main(["calibrate", "--dry-run", "--config", str(bad)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "plan pose 2" in err[0]


def test_a_pose_the_controller_refuses_is_named_in_the_error(tmp_path: Path) -> None:
    # the plan believes any orientation is fine ([handeye] reach = "any"); the simulated xArm 5 refuses
    cfg = with_mount(tmp_path, true_mount_text())
    cfg.write_text(cfg.read_text().replace("[handeye]\n", '[handeye]\nreach = "any"\n', 1))
    config = load_config(cfg)
    calibrator = Calibrator(config, *build_devices(config))
    with pytest.raises(VendorError, match=r"sim error 21: .*not reachable.* at plan pose 1 \(xyz=\(0\.129\d, "
                                          r"-0\.00\d\d, 0\.495\d\) m rpy=") as err:
        calibrator.run()
    assert err.value.code == 21


def test_too_few_board_views_say_what_to_check(tmp_path: Path) -> None:
    no_board = tmp_path / "c.toml"
    text = CONFIG.read_text()
    start = text.index("\n[sim.charuco]\n")
    no_board.write_text(text[:start] + text[text.index("\n[sim.mount]\n"):])
    assert "[sim.charuco]" in missing_board_hint(load_config(no_board))
    assert "7x5 squares of 40 mm" in missing_board_hint(load_config(CONFIG))



def test_a_large_sideways_tilt_is_refused_by_name_not_replaced() -> None:
    """The paper plan tilts 10 deg about the flange's y axis: 9.4 deg sideways for a 5-axis xArm. Moving it
    would turn an 80 deg view into a 90 deg one, so it is left as asked and refused before anything moves."""
    from cellcal.core.calibration.config import parse_config
    from cellcal.core.calibration.reach import MAX_MOVE_RAD, check_reach, within_reach

    doc = tomllib.loads((REPO_ROOT / "configs" / "sim.toml").read_text())
    doc["arm"]["reach"] = "xarm5"
    config = parse_config(doc, "sim.toml")
    asked = plan_flange_poses(config)
    assert all(sideways_tilt_rad(p) > MAX_MOVE_RAD for p in asked)
    assert math.degrees(sideways_tilt_rad(asked[0])) > 9.0
    kept = within_reach(config, asked)
    assert all(a is k for a, k in zip(asked, kept, strict=True))          # left as asked ...
    with pytest.raises(SafetyError, match=r"plan pose 1 .* out of reach of a 'xarm5' arm: tool axis tilted 9\.4"):
        check_reach(config, kept)                                         # ... and refused by name
