"""A configured simulated cell for tests of cell code: :func:`sim_cell`, :func:`sim_camera`, :func:`sim_arm`.

Built exactly as ``cellcal calibrate`` builds its devices (``load_config`` / ``build_devices``), so the
code under test sees the same camera and safety-wrapped arm it would in a run. ADR 0033.
"""

from __future__ import annotations

import contextlib
import copy
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cellcal.core.calibration import CellConfig, build_devices, load_config, parse_config
from cellcal.core.calibration.calibrator import Calibrator
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import ConfigError
from cellcal.devices.safety import SafeArm
from cellcal.sims.arm import SimArm
from cellcal.sims.camera_shell import SimCameraShell
from cellcal.sims.world import SimWorld

from .faults import CellFaults

__all__ = ["ConfigSource", "SimCell", "cell_config", "sim_arm", "sim_camera", "sim_cell"]

#: What names a cell configuration: None (the packaged ``sim.toml``), a TOML file, a parsed document or a config.
ConfigSource = str | Path | Mapping[str, Any] | CellConfig | None


@dataclass
class SimCell:
    """A simulated cell: the devices a configuration builds and the simulation behind them.

    Attributes:
        config: The validated configuration.
        camera: The camera as the configuration builds it (``sim``, ``o3r-emulated``, …), unconnected
            until something connects it.
        arm: The arm, wrapped in :class:`~cellcal.devices.safety.SafeArm` with the config's safety
            envelope, unconnected until something connects it.
        sim_camera: The simulated camera behind ``camera`` (the same object for ``sim``).
        sim_arm: The simulated arm behind ``arm``; None for ``ur-emulated``, whose arm runs in a child process.
        faults: Fault injection on this cell's devices (:class:`~cellcal.testing.faults.CellFaults`).
    """

    config: CellConfig
    camera: Camera3D
    arm: SafeArm
    sim_camera: SimCameraShell
    sim_arm: SimArm | None
    faults: CellFaults = field(init=False)

    def __post_init__(self) -> None:
        self.faults = CellFaults(self)

    @property
    def world(self) -> SimWorld:
        """The simulated world (scene, true mount, true arm state, clock) both devices share."""
        return self.sim_camera.world

    def calibrator(self) -> Calibrator:
        """A :class:`~cellcal.core.calibration.Calibrator` running the config's plan on this cell's devices."""
        return Calibrator(self.config, self.camera, self.arm)

    def close(self) -> None:
        """Close both devices (safe to call more than once)."""
        try:
            self.camera.close()
        finally:
            self.arm.close()


def _merged(document: Mapping[str, Any], tables: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    doc = copy.deepcopy(dict(document))
    for name, values in tables.items():
        if not isinstance(values, Mapping):
            raise ConfigError(f"tables[{name!r}] must be a table (a dict), got {type(values).__name__}")
        current = doc.get(name)
        doc[name] = {**(dict(current) if isinstance(current, Mapping) else {}), **copy.deepcopy(dict(values))}
    return doc


def cell_config(config: ConfigSource = None, tables: Mapping[str, Mapping[str, Any]] | None = None) -> CellConfig:
    """The validated configuration ``config`` names, with ``tables`` merged over its tables.

    Args:
        config: None (the packaged ``configs/sim.toml``), a TOML file path, a parsed document or a
            :class:`CellConfig`.
        tables: Table name -> keys to set in it, e.g. ``{"camera": {"noise": False}}``; a table
            the document lacks is added.

    Raises:
        ConfigError: If the file or the merged document is invalid (one line naming file and key).
    """
    if isinstance(config, CellConfig):
        base, source = config, config.source
    elif isinstance(config, Mapping):
        return parse_config(_merged(config, tables or {}), "<sim_cell document>")
    else:
        base = load_config(config)
        source = base.source
    return parse_config(_merged(base.document, tables), source) if tables else base


def _simulated_camera(camera: Camera3D) -> SimCameraShell | None:
    camera = getattr(camera, "raw", camera)  # behind a [camera.correction] (CorrectedCamera, ADR 0058)
    if isinstance(camera, SimCameraShell):
        return camera
    behind = getattr(camera, "sim", None)  # o3r-emulated
    return behind if isinstance(behind, SimCameraShell) else None


def _simulated_arm(arm: SafeArm) -> SimArm | None:
    inner = arm.inner
    if isinstance(inner, SimArm):
        return inner
    behind = getattr(inner, "sim_arm", None)  # xarm-emulated
    return behind if isinstance(behind, SimArm) else None


@contextlib.contextmanager
def sim_cell(config: ConfigSource = None, *, tables: Mapping[str, Mapping[str, Any]] | None = None
             ) -> Iterator[SimCell]:
    """A simulated cell built from a configuration; its devices are closed on exit.

    The devices are built unconnected, as ``cellcal calibrate`` builds them: the code under
    test connects them (``with cell.camera:`` or a :class:`Calibrator`).

    Args:
        config: None (the packaged ``configs/sim.toml``), a TOML file path, a parsed document or a
            :class:`CellConfig`. Its camera must be simulated (``sim``, ``o3r-emulated``) and its
            arm too (``sim``, ``xarm-emulated``, ``ur-emulated``).
        tables: Table name -> keys merged over the document, e.g. ``{"plan": {"perimeters_px": [20]}}``.

    Raises:
        ConfigError: If the configuration is invalid or names a real (not simulated) backend.
    """
    cfg = cell_config(config, tables)
    camera, arm = build_devices(cfg)
    try:
        behind_camera = _simulated_camera(camera)
        if behind_camera is None:
            raise ConfigError(f"camera backend {camera.backend_name!r} is not simulated; "
                              "sim_cell needs 'sim' or 'o3r-emulated'", source=cfg.source, key="camera.backend")
        behind_arm = _simulated_arm(arm)
        if behind_arm is None and arm.backend_name != "ur-emulated":
            raise ConfigError(f"arm backend {arm.backend_name!r} is not simulated; "
                              "sim_cell needs 'sim', 'xarm-emulated' or 'ur-emulated'",
                              source=cfg.source, key="arm.backend")
        cell = SimCell(cfg, camera, arm, behind_camera, behind_arm)
    except BaseException:
        camera.close()
        arm.close()
        raise
    try:
        yield cell
    finally:
        cell.faults.clear()
        cell.close()


@contextlib.contextmanager
def sim_camera(config: ConfigSource = None, *, tables: Mapping[str, Mapping[str, Any]] | None = None,
               timeout_s: float = 10.0) -> Iterator[Camera3D]:
    """The connected camera of :func:`sim_cell` (``config``, ``tables`` as there), closed on exit.

    Args:
        timeout_s: Seconds the connect may take.
    """
    with sim_cell(config, tables=tables) as cell:
        yield cell.camera.connect(timeout_s)


@contextlib.contextmanager
def sim_arm(config: ConfigSource = None, *, tables: Mapping[str, Mapping[str, Any]] | None = None,
            timeout_s: float = 10.0) -> Iterator[SafeArm]:
    """The connected, safety-wrapped arm of :func:`sim_cell` (``config``, ``tables`` as there), closed on exit.

    Args:
        timeout_s: Seconds the connect may take.
    """
    with sim_cell(config, tables=tables) as cell:
        yield cell.arm.connect(timeout_s)
