"""The cellcal pytest plugin as a user meets it: registered, light, its fixtures in a project of their own."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest
from repo_paths import REPO_ROOT

pytest_plugins = ["pytester"]

FIXTURES = ("cellcal_sim_config", "cellcal_sim_tables", "cellcal_sim_cell", "cellcal_sim_camera", "cellcal_sim_arm",
            "cellcal_faults", "cellcal_o3r_emulator", "cellcal_xarm_emulator", "cellcal_ur_emulator")


def test_the_plugin_is_registered_for_pytest_by_the_entry_point(tmp_path: Path) -> None:
    # from a user's folder: in the repository root a stale cellcal.egg-info left by a wheel build would be
    # found before the installed metadata (the current folder comes first on sys.path)
    probe = ("import json; from importlib.metadata import entry_points; "
             "print(json.dumps([ep.value for ep in entry_points(group='pytest11') if ep.name == 'cellcal']))")
    proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, check=True,
                          cwd=tmp_path)
    assert json.loads(proc.stdout) == ["cellcal.testing.plugin"]


def test_loading_the_plugin_imports_nothing_of_cellcal_but_itself() -> None:
    probe = ("import json, sys; before = set(sys.modules); import cellcal.testing.plugin; "
             "print(json.dumps(sorted(set(sys.modules) - before)))")
    proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, check=True)
    loaded = json.loads(proc.stdout)
    ours = [m for m in loaded if m.startswith("cellcal")]
    assert ours == ["cellcal", "cellcal.testing", "cellcal.testing.plugin"]
    assert not [m for m in loaded if m.split(".")[0] in ("numpy", "scipy", "cv2")]


def test_every_documented_fixture_is_offered(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(test_nothing="def test_nothing():\n    pass\n")
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider", "--fixtures")
    listed = result.stdout.str()
    assert [name for name in FIXTURES if f"{name} -- " not in listed] == []


def test_a_user_project_uses_its_own_config_tables_and_faults(pytester: pytest.Pytester) -> None:
    packaged = (REPO_ROOT / "configs" / "sim.toml").read_text(encoding="utf-8")
    pytester.makefile(".toml", mycell=packaged.replace("seed = 7", "seed = 23"))
    pytester.makeini("[pytest]\ncellcal_sim_config = mycell.toml\n")
    pytester.makeconftest("""
import pytest

@pytest.fixture
def cellcal_sim_tables():
    return {"camera": {"noise": False, "width": 80, "height": 60}}
""")
    pytester.makepyfile(test_mine="""
import numpy as np
import pytest
from cellcal.devices.errors import DeviceConnectionError, DeviceTimeoutError

def test_the_ini_config_and_the_tables(cellcal_sim_cell, cellcal_sim_camera):
    assert cellcal_sim_cell.config.cell.seed == 23 and cellcal_sim_cell.config.source.endswith("mycell.toml")
    a, b = cellcal_sim_camera.capture(1.0), cellcal_sim_camera.capture(1.0)
    assert a.distance.shape == (60, 80) and np.array_equal(a.distance, b.distance)

def test_faults_reach_the_test(cellcal_sim_camera, cellcal_sim_arm, cellcal_faults):
    cellcal_faults.camera_disconnect(capture=1)
    with pytest.raises(DeviceConnectionError):
        cellcal_sim_camera.capture(1.0)
    cellcal_faults.arm_stall(move=1)
    start = cellcal_sim_arm.get_pose()
    with pytest.raises(DeviceTimeoutError):
        cellcal_sim_arm.move_linear(start.with_translation(start.translation - [0, 0, 0.02]),
                                    speed=0.1, acceleration=1.0, timeout=0.3)

def test_each_test_gets_a_fresh_cell(cellcal_sim_camera, cellcal_faults):
    assert cellcal_faults.fired == {}
    assert cellcal_sim_camera.capture(1.0).valid.mean() > 0.9
""")
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider")
    result.assert_outcomes(passed=3)


def test_the_example_vendor_client_tests_pass_outside_the_repository(pytester: pytest.Pytester) -> None:
    source = REPO_ROOT / "examples" / "cell_tests" / "test_vendor_clients.py"
    pytester.makepyfile(test_clients=source.read_text(encoding="utf-8"))
    clients = ("ifm3dpy", "xarm", "rtde_control")
    installed = sum(importlib.util.find_spec(name) is not None for name in clients)
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider", "-rs")
    result.assert_outcomes(passed=installed, skipped=len(clients) - installed)


def test_in_this_repository_every_cellcal_fixture_is_the_plugin_s() -> None:
    """No conftest of the repository's own tests defines (and so shadows) a cellcal_* fixture."""
    conftests = sorted(str(p.relative_to(REPO_ROOT)) for p in (REPO_ROOT / "tests").rglob("conftest.py"))
    assert "tests/conftest.py" in conftests
    proc = subprocess.run([sys.executable, "-m", "pytest", "--fixtures", "-q", "-p", "no:cacheprovider", *conftests],
                          capture_output=True, text=True, timeout=300, cwd=REPO_ROOT, check=False)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("cellcal_") and " -- " in line]
    assert sorted(line.split(" -- ")[0] for line in lines) == sorted(FIXTURES), proc.stdout[-2000:]
    assert all(line.split(" -- ")[1].startswith("testing/plugin.py:") for line in lines), lines
