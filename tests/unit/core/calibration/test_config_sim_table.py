"""A ``[sim]`` table that no backend reads is reported (one warning line), not refused."""

from __future__ import annotations

import copy
import logging
import subprocess
import sys
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

import pytest

from cellcal.core.calibration.config import SIM_BACKENDS, parse_config
from cellcal.devices.registry import default_registry

SIM_DOC: dict[str, Any] = tomllib.loads(
    resources.files("cellcal.configs").joinpath("sim.toml").read_text(encoding="utf-8"))


def _doc(camera: str, arm: str, *, sim: bool = True) -> dict[str, Any]:
    doc = copy.deepcopy(SIM_DOC)
    assert "sim" in doc  # the packaged cell describes its simulated world
    doc["camera"], doc["arm"] = {"backend": camera}, {"backend": arm}
    if not sim:
        del doc["sim"]
    return doc


def _warnings(caplog: pytest.LogCaptureFixture, doc: dict[str, Any]) -> list[str]:
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="cellcal.core.calibration.config"):
        parse_config(doc, "cell.toml")
    return [r.getMessage() for r in caplog.records if r.name == "cellcal.core.calibration.config"]


def test_sim_table_with_only_real_backends_is_one_warning(caplog: pytest.LogCaptureFixture) -> None:
    assert _warnings(caplog, _doc("o3r", "xarm")) == [
        "cell.toml: [sim] has no effect: camera backend 'o3r' and arm backend 'xarm' are not simulated "
        "(only o3r-emulated, sim, ur-emulated, xarm-emulated read it)"]
    assert caplog.records[0].levelno == logging.WARNING


@pytest.mark.parametrize(("camera", "arm"), [("sim", "sim"), ("o3r", "sim"), ("sim", "ur"),
                                             ("o3r-emulated", "xarm"), ("oak", "xarm-emulated")])
def test_no_warning_when_a_simulated_backend_reads_it(caplog: pytest.LogCaptureFixture, camera: str,
                                                      arm: str) -> None:
    assert _warnings(caplog, _doc(camera, arm)) == []


def test_no_warning_without_a_sim_table(caplog: pytest.LogCaptureFixture) -> None:
    assert _warnings(caplog, _doc("o3r", "ur", sim=False)) == []


def test_sim_backends_are_the_registered_backends_of_cellcal_sims() -> None:
    """The list the warning relies on names every backend built on the simulated world, and only those."""
    in_sims = {e.name for e in default_registry().entries() if e.target.startswith("cellcal.sims.")}
    assert in_sims == SIM_BACKENDS


def test_cli_prints_the_warning_as_one_line_and_still_runs(tmp_path: Path) -> None:
    text = resources.files("cellcal.configs").joinpath("sim.toml").read_text(encoding="utf-8")
    real = tmp_path / "real.toml"
    real.write_text(text.replace('backend = "sim"', 'backend = "o3r"', 1)
                    .replace('backend = "sim"', 'backend = "ur"', 1))  # [camera], then [arm]
    done = subprocess.run([sys.executable, "-m", "cellcal.core.cli", "calibrate", "--dry-run", "--config", str(real)],
                          capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stderr == (f"{real}: [sim] has no effect: camera backend 'o3r' and arm backend 'ur' are not "
                           "simulated (only o3r-emulated, sim, ur-emulated, xarm-emulated read it)\n")
    assert done.stdout.rstrip().endswith("inside the safety envelope")
