"""The ``cellcal`` pytest plugin: fixtures for testing cell code against simulated devices and emulators.

Registered through the ``pytest11`` entry point. It imports nothing of cellcal until a ``cellcal_*``
fixture is used, so it costs a test run that does not use them nothing. docs/testing.md, ADR 0033.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from cellcal.devices.camera import Camera3D
    from cellcal.devices.safety import SafeArm

    from .emulators import O3RAddress, URAddress, XArmAddress
    from .faults import CellFaults
    from .sim import ConfigSource, SimCell

#: The ini option naming the cell configuration of ``cellcal_sim_cell`` (relative to the rootdir).
INI_CONFIG = "cellcal_sim_config"


def pytest_addoption(parser: pytest.Parser) -> None:
    """The ``cellcal_sim_config`` ini option."""
    parser.addini(INI_CONFIG, "cell configuration (TOML) of the cellcal_sim_cell fixture, relative to the rootdir; "
                  "default: cellcal's packaged configs/sim.toml", default="")


@pytest.fixture
def cellcal_sim_config(request: pytest.FixtureRequest) -> ConfigSource:
    """The configuration ``cellcal_sim_cell`` builds: the ini option ``cellcal_sim_config`` or the packaged sim.toml.

    Override it in a conftest.py to return a path, a parsed document (dict) or a ``CellConfig``.
    """
    value = str(request.config.getini(INI_CONFIG) or "").strip()
    return Path(request.config.rootpath, value) if value else None


@pytest.fixture
def cellcal_sim_tables() -> dict[str, dict[str, Any]]:
    """Tables merged over ``cellcal_sim_config``'s document (default none), e.g. ``{"camera": {"noise": False}}``.

    Override it (in a conftest.py, a module or a class) to change a few keys without a file of your own.
    """
    return {}


@pytest.fixture
def cellcal_sim_cell(cellcal_sim_config: ConfigSource, cellcal_sim_tables: dict[str, dict[str, Any]]
                     ) -> Iterator[SimCell]:
    """A simulated cell built from ``cellcal_sim_config`` (``cellcal.testing.SimCell``); closed after the test.

    Its ``camera`` and ``arm`` are built as ``cellcal calibrate`` builds them and left unconnected.
    """
    from .sim import sim_cell

    with sim_cell(cellcal_sim_config, tables=cellcal_sim_tables) as cell:
        yield cell


@pytest.fixture
def cellcal_sim_camera(cellcal_sim_cell: SimCell) -> Camera3D:
    """The camera of ``cellcal_sim_cell``, connected."""
    return cellcal_sim_cell.camera.connect(10.0)


@pytest.fixture
def cellcal_sim_arm(cellcal_sim_cell: SimCell) -> SafeArm:
    """The safety-wrapped arm of ``cellcal_sim_cell``, connected."""
    return cellcal_sim_cell.arm.connect(10.0)


@pytest.fixture
def cellcal_faults(cellcal_sim_cell: SimCell) -> CellFaults:
    """Fault injection on ``cellcal_sim_cell`` (``cellcal.testing.CellFaults``); disarmed after the test."""
    return cellcal_sim_cell.faults


@pytest.fixture
def cellcal_o3r_emulator() -> Iterator[O3RAddress]:
    """An O3R emulator in a child process; yields its ``O3RAddress`` (host, xmlrpc_port, pcic_port)."""
    from .emulators import o3r_emulator

    with o3r_emulator() as address:
        yield address


@pytest.fixture
def cellcal_xarm_emulator() -> Iterator[XArmAddress]:
    """An xArm emulator over TCP, its report on port 30002 (what xarm-python-sdk reads); yields its ``XArmAddress``."""
    from .emulators import xarm_emulator

    with xarm_emulator(sdk_report_port=True) as address:
        yield address


@pytest.fixture
def cellcal_ur_emulator() -> Iterator[URAddress]:
    """A UR emulator in a child process on its own loopback address; yields its ``URAddress``."""
    from .emulators import ur_emulator

    with ur_emulator() as address:
        yield address
