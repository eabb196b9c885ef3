"""cellcal.testing.sim: a simulated cell from a configuration, as ``cellcal calibrate`` builds it."""

from __future__ import annotations

import numpy as np
import pytest

from cellcal.core.calibration import load_config
from cellcal.devices.errors import CellcalError, ConfigError, DeviceTimeoutError, VendorError
from cellcal.devices.safety import SafeArm
from cellcal.devices.systematic import SystematicError
from cellcal.sims.arm import SimArm
from cellcal.sims.camera import SimCamera
from cellcal.testing import SimCell, sim_arm, sim_camera, sim_cell

FAST = {"plan": {"perimeters_px": [20], "methods": ["plane_fit"], "capture_timeout_s": 0.5, "move_timeout_s": 1.5}}


def test_the_default_cell_is_the_packaged_sim_config_unconnected_and_closed_on_exit() -> None:
    with sim_cell() as cell:
        assert isinstance(cell, SimCell)
        assert cell.config.source == "<packaged sim.toml>" and cell.config.cell.seed == 7
        assert isinstance(cell.camera, SimCamera) and cell.sim_camera is cell.camera
        assert isinstance(cell.arm, SafeArm) and isinstance(cell.sim_arm, SimArm) and cell.arm.inner is cell.sim_arm
        assert cell.world is cell.sim_arm.world  # one world for both devices
        assert not cell.camera.connected and not cell.arm.connected
        cell.camera.connect(1.0)
        cell.arm.connect(1.0)
        # the camera renders the world from the arm's true pose: the table (z = 0) 0.44 m below
        frame = cell.camera.capture(1.0)
        centre = frame.distance[84:89, 110:115][frame.valid[84:89, 110:115]]
        camera_z = cell.world.camera_pose().translation[2]
        # what the camera measures of that range at the image centre: its systematic error on (ADR 0054)
        measured = SystematicError.from_dict(frame.metadata["sim_systematic"]).distort(camera_z, 0.0, 0.0)
        assert abs(float(np.median(centre)) - measured) < 0.003
    assert not cell.camera.connected and not cell.arm.connected


def test_tables_are_merged_over_the_document() -> None:
    with sim_cell(tables={"camera": {"noise": False}, "cell": {"seed": 11}}) as quiet, quiet.camera:
        assert quiet.config.cell.seed == 11 and quiet.config.document["cell"]["name"] == "paper-sim"
        a, b = quiet.camera.capture(1.0), quiet.camera.capture(1.0)
        assert np.array_equal(a.distance, b.distance)  # no noise: the static scene gives the same frame
    with sim_cell() as noisy, noisy.camera:
        a, b = noisy.camera.capture(1.0), noisy.camera.capture(1.0)
        both = a.valid & b.valid
        assert np.abs(a.distance[both] - b.distance[both]).max() > 0.002


def test_a_document_a_file_and_a_config_object_build_the_same_cell(tmp_path: pytest.TempPathFactory) -> None:
    doc = {"camera": {"backend": "sim"}, "arm": {"backend": "sim", "time_scale": 0.0}, "cell": {"seed": 5},
           "reference": {"plane_point_m": [0.0, 0.0, 0.0], "plane_normal": [0.0, 0.0, 1.0]}}
    path = tmp_path / "mine.toml"  # type: ignore[operator]
    path.write_text('[cell]\nseed = 5\n[camera]\nbackend = "sim"\n[arm]\nbackend = "sim"\ntime_scale = 0.0\n'
                    '[reference]\nplane_point_m = [0.0, 0.0, 0.0]\nplane_normal = [0.0, 0.0, 1.0]\n')
    frames = []
    for source in (doc, path, load_config(path)):
        with sim_cell(source) as cell, cell.camera:
            assert cell.config.cell.seed == 5
            frames.append(cell.camera.capture(1.0).distance)
    assert np.array_equal(frames[0], frames[1]) and np.array_equal(frames[1], frames[2])  # same seed, same noise


def test_a_real_backend_is_refused_in_one_line_naming_the_key() -> None:
    with pytest.raises(ConfigError) as err, sim_cell(tables={"camera": {"backend": "o3r"}}):
        pass
    assert "key 'camera.backend'" in str(err.value) and "'o3r' is not simulated" in str(err.value)
    assert "\n" not in str(err.value)
    doc = load_config().document
    with pytest.raises(ConfigError, match=r"key 'arm\.backend'"), \
            sim_cell({**doc, "arm": {"backend": "xarm", "host": "127.0.0.1"}}):
        pass


def test_bad_tables_and_missing_files_are_config_errors(tmp_path: pytest.TempPathFactory) -> None:
    with pytest.raises(ConfigError, match=r"tables\['plan'\] must be a table"), sim_cell(tables={"plan": 3}):  # type: ignore[dict-item]
        pass
    with pytest.raises(ConfigError, match="file not found"), sim_cell(tmp_path / "none.toml"):  # type: ignore[operator]
        pass
    with pytest.raises(ConfigError, match=r"plan\.heights_m"), sim_cell(tables={"plan": {"heights_m": "high"}}):
        pass


def test_sim_camera_and_sim_arm_yield_connected_devices_closed_on_exit() -> None:
    with sim_camera(tables={"camera": {"width": 64, "height": 48}}) as camera:
        assert camera.connected and camera.capture(1.0).distance.shape == (48, 64)
    assert not camera.connected
    with sim_arm() as arm:
        assert arm.connected and isinstance(arm, SafeArm)
        start = arm.get_pose()
        target = start.with_translation(start.translation + np.array([0.0, 0.0, -0.03]))
        arm.move_linear(target, speed=0.1, acceleration=1.0, timeout=5.0)
        assert arm.get_pose().distance_to(target) < 0.001
    assert not arm.connected


def test_the_calibrator_of_a_cell_runs_its_plan() -> None:
    with sim_cell(tables=FAST) as cell:
        result = cell.calibrator().run()
    rows = [row for pose in result["poses"] for row in pose["measurements"]]
    assert len(result["poses"]) == 3 and len(rows) == 3
    assert all(abs(row["angle_deg"] - row["expected_angle_deg"]) < 1.0 for row in rows)


def test_emulated_backends_expose_the_simulation_behind_the_wire() -> None:
    tables = {**FAST, "camera": {"backend": "o3r-emulated", "trigger": "software", "io_timeout_s": 2.0},
              "arm": {"backend": "xarm-emulated", "axes": 5, "time_scale": 0.001, "reply_timeout_s": 0.3,
                      "poll_interval_s": 0.005}}
    with sim_cell(tables=tables) as cell:
        assert cell.camera.backend_name == "o3r-emulated" and isinstance(cell.sim_camera, SimCamera)
        assert cell.sim_camera is not cell.camera and isinstance(cell.sim_arm, SimArm)
        with pytest.raises(CellcalError, match=r"needs the 'sim' camera backend.*'o3r-emulated'"):
            cell.faults.camera_timeout()
        with cell.camera, cell.arm:
            # a blank frame crosses the PCIC wire as a frame with no valid pixel
            cell.faults.blank_frame(capture=1)
            blank = cell.camera.capture(2.0)
            assert blank.valid.sum() == 0 and cell.faults.fired["blank_frame"] == 1
            assert cell.camera.capture(2.0).valid.mean() > 0.9
            # a controller error reaches cellcal's xArm driver as a VendorError
            cell.faults.arm_error(code=22, move=1)
            start = cell.arm.get_pose()
            with pytest.raises(VendorError, match="22"):
                cell.arm.move_linear(start.with_translation(start.translation + np.array([0.0, 0.0, -0.02])),
                                     speed=0.1, acceleration=1.0, timeout=2.0)


def test_a_stalled_emulated_frame_times_out_in_the_o3r_driver() -> None:
    tables = {**FAST, "camera": {"backend": "o3r-emulated", "trigger": "software", "io_timeout_s": 2.0}}
    with sim_cell(tables=tables) as cell, cell.camera:
        cell.faults.camera_stall(1.5, capture=1)
        with pytest.raises(DeviceTimeoutError):
            cell.camera.capture(0.5)
