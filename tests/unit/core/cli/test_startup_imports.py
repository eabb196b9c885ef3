"""What the ``cellcal`` command imports at start-up, checked in fresh interpreters (ADR 0021).

``cellcal --help`` imports no subcommand module (it lists them by name and summary), and the
parser with every subcommand loads no numerics and no vendor SDK;
``cellcal calibrate`` on the default sim loads numpy and OpenCV but neither scipy nor
matplotlib nor the recording stack. Speed itself is measured by ``benchmarks/startup.py``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from cellcal.core.cli.app import SUBCOMMANDS

#: Never imported by building the parser.
NOT_FOR_HELP = ("numpy", "scipy", "cv2", "matplotlib", "tqdm", "depthai", "ifm3dpy", "rtde_control",
                "rtde_receive", "xarm", "mcap", "foxglove", "cellcal.core.study.trials", "cellcal.core.calibration")
#: Never imported by ``cellcal --help``, which lists the subcommands without their modules (issue #38).
NOT_FOR_LISTING = (*NOT_FOR_HELP, *(f"cellcal.core.cli.{name}" for name in SUBCOMMANDS), "cellcal.core.study",
                   "cellcal.devices.discovery", "dataclasses", "concurrent.futures", "importlib.resources",
                   "socket", "subprocess", "threading", "tempfile")
#: Never imported by ``cellcal calibrate`` on the default sim.
NOT_FOR_CALIBRATE = ("scipy", "matplotlib", "depthai", "ifm3dpy", "rtde_control", "xarm", "mcap", "foxglove",
                     "cellcal.core.study.trials", "cellcal.devices.recording", "cellcal.core.liveview")


def _loaded_after(code: str, watch: tuple[str, ...]) -> list[str]:
    """Run ``code`` in a fresh interpreter; the watched modules it left in ``sys.modules``."""
    probe = f"{code}\nimport json, sys\nprint(json.dumps(sorted(m for m in {list(watch)!r} if m in sys.modules)))"
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True)
    loaded: list[str] = json.loads(done.stdout.strip().splitlines()[-1])
    return loaded


def test_building_the_parser_imports_no_numerics_and_no_vendor_sdk() -> None:
    code = "from cellcal.core.cli.app import build_parser\nbuild_parser()"
    assert _loaded_after(code, NOT_FOR_HELP) == []


def test_the_listing_imports_no_subcommand_module() -> None:
    code = "from cellcal.core.cli import main\ntry:\n    main(['--help'])\nexcept SystemExit:\n    pass"
    assert _loaded_after(code, NOT_FOR_LISTING) == []


def test_the_help_still_lists_every_subcommand() -> None:
    done = subprocess.run([sys.executable, "-m", "cellcal.core.cli", "--help"], capture_output=True, text=True,
                          timeout=120, check=True)
    for name in SUBCOMMANDS:
        assert name in done.stdout


def test_light_modules_stay_light() -> None:
    """The error tree and the study's design are importable without numpy."""
    code = "import cellcal.devices.errors, cellcal.devices, cellcal.core, cellcal.core.study.design"
    assert _loaded_after(code, ("numpy", "scipy", "cellcal.devices.pose")) == []


def test_calibrate_on_the_default_sim_imports_no_scipy(tmp_path: Path) -> None:
    code = ("import sys\nfrom cellcal.core.cli import main\n"
            f"assert main(['calibrate', '--quiet', '--out', {str(tmp_path)!r}]) == 0")
    assert _loaded_after(code, NOT_FOR_CALIBRATE) == []
    assert json.loads((tmp_path / "result.json").read_text())["poses"]
