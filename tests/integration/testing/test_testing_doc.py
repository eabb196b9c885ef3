"""docs/testing.md section 6 shows code that runs: its blocks are the example suite's, its TOML a valid cell.

The example suite (examples/cell_tests, run by .ci/run) runs the Python; these tests keep the page and the
suite the same text, and build (without connecting) the devices the page's TOML names.
"""

from __future__ import annotations

import re
import tomllib

from repo_paths import REPO_ROOT

from cellcal.core.calibration import build_devices, parse_config
from cellcal.drivers.o3r import O3RCamera
from cellcal.drivers.xarm import XArmArm

DOC = REPO_ROOT / "docs" / "testing.md"
EXAMPLES = REPO_ROOT / "examples" / "cell_tests"
SECTION = "## 6. cellcal's drivers and your cell configuration on an emulator"


def section_blocks(language: str) -> list[str]:
    """The ``language`` code blocks of section 6 of docs/testing.md."""
    text = DOC.read_text(encoding="utf-8")
    assert SECTION in text
    section = text.split(SECTION, 1)[1].split("\n## ", 1)[0]
    return re.findall(rf"```{language}\n(.*?)```", section, flags=re.S)


def test_every_python_block_of_the_section_is_in_the_example_suite() -> None:
    suite = (EXAMPLES / "test_cellcal_drivers.py").read_text(encoding="utf-8")
    blocks = section_blocks("python")
    assert len(blocks) == 3
    suite_lines = set(suite.splitlines())
    missing = []
    for block in blocks:
        lines = block.splitlines()
        missing += [line for line in lines if line.startswith(("from ", "import ")) and line not in suite_lines]
        body = "\n".join(line for line in lines if not line.startswith(("from ", "import "))).strip("\n")
        if body not in suite:
            missing.append(body)
    assert missing == []
    tests = re.findall(r"^def (test_\w+)", suite, flags=re.M)
    shown = re.findall(r"^def (test_\w+)", "".join(blocks), flags=re.M)
    assert shown == tests  # the page shows the whole suite, in its order


def test_the_section_s_toml_names_a_real_o3r_and_xarm_in_the_example_cell() -> None:
    (block,) = section_blocks("toml")
    tables = tomllib.loads(block)
    document = tomllib.loads((EXAMPLES / "cell.toml").read_text(encoding="utf-8"))
    document.pop("sim")  # a real cell simulates nothing
    config = parse_config({**document, **tables}, "docs/testing.md")
    camera, arm = build_devices(config)  # built, not connected: nothing is reached over the network
    assert isinstance(camera, O3RCamera) and isinstance(arm.inner, XArmArm)
    assert (camera.config.host, camera.config.xmlrpc_port, camera.config.port) == ("192.168.0.69", 80, "port2")
    xarm = arm.inner.config
    assert (xarm.host, xarm.tcp_port, xarm.report_port, xarm.axes) == ("192.168.1.210", 502, 30002, 5)
