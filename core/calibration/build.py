"""The devices of a cell configuration, built through the registry: :func:`build_devices`, :func:`build_camera`.

Every backend of one document gets a :class:`~cellcal.devices.base.BackendContext` sharing
one ``shared`` dict (so the simulated camera and arm see one world) and the ``[cell] seed``;
the arm is wrapped in :class:`~cellcal.devices.safety.SafeArm` with the configuration's
envelope. This module never names a driver or a simulator: the registry does.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from cellcal.core.calibration.config import CellConfig
from cellcal.core.calibration.sections import MountSection
from cellcal.devices.arm import RobotArm
from cellcal.devices.base import BackendContext, CameraPlacement
from cellcal.devices.camera import Camera3D
from cellcal.devices.config import parse_section
from cellcal.devices.registry import Registry, default_registry
from cellcal.devices.safety import SafeArm

__all__ = ["build_camera", "build_cell", "build_devices"]


def _context_factory(document: Mapping[str, Any], source: str | None, seed: int, names: tuple[str, ...] = ()
                     ) -> Callable[..., BackendContext]:
    """``(section, placement=None) -> BackendContext`` for the backends of one document (one ``shared`` dict);
    ``names``: the cell's cameras."""
    shared: dict[str, Any] = {}

    def ctx(section: str, placement: CameraPlacement | None = None) -> BackendContext:
        return BackendContext(source=source, section=section, document=document, shared=shared, seed=seed,
                              placement=placement, camera_names=names)

    return ctx


def _fixed_placement(config: CellConfig) -> CameraPlacement | None:
    """The placement of the camera the configuration runs when it is fixed (``on = "base"``), else None."""
    entry = config.camera_entry
    if entry.on != "base" or entry.pose_base is None:
        return None
    return CameraPlacement(entry.name, "base", entry.pose_base)


def build_cell(config: CellConfig, registry: Registry | None = None, *, apply_correction: bool = True
               ) -> tuple[dict[str, Camera3D], SafeArm]:
    """Every camera of the cell (``[[cameras]]``; unconnected) and the safety-wrapped arm, one world for all.

    The camera on the flange the configuration runs (:attr:`CellConfig.camera_name`) is built as
    :func:`build_devices` builds it; each other camera (and a fixed one the configuration runs) from its
    own table with its :class:`CameraPlacement` in the context
    (section ``cameras.NAME``), sharing the backends' ``shared`` objects (a simulated cell's one world).

    Returns:
        ``({name: camera}`` in the configuration's order, arm).

    Raises:
        ConfigError: If a backend is unknown or rejects its section.
    """
    registry = registry or default_registry()
    ctx = _context_factory(config.document, config.source, config.cell.seed, tuple(c.name for c in config.cameras))
    cameras: dict[str, Camera3D] = {}
    for i, entry in enumerate(config.cameras):
        if entry.name == config.camera_name and entry.on == "flange":
            cameras[entry.name] = registry.create_camera(config.camera_section, ctx(config.camera_key),
                                                         apply_correction=apply_correction)
            continue
        if entry.on == "base":
            assert entry.pose_base is not None          # parse_cameras requires it
            placement = CameraPlacement(entry.name, "base", entry.pose_base)
        else:
            mount = parse_section(MountSection, entry.mount, where=f"cameras[{i}].mount",
                                  source=config.source)
            placement = CameraPlacement(entry.name, "flange", mount.pose())
        cameras[entry.name] = registry.create_camera(entry.table, ctx(f"cameras[{i}]", placement),
                                                     apply_correction=apply_correction)
    arm: RobotArm = registry.create_arm(config.arm_section, ctx("arm"))
    return cameras, SafeArm(arm, config.safety_limits())


def build_devices(config: CellConfig, registry: Registry | None = None, *, source: str | None = None,
                  camera: Mapping[str, Any] | None = None, arm: Mapping[str, Any] | None = None,
                  apply_correction: bool = True) -> tuple[Camera3D, SafeArm]:
    """Create the (unconnected) camera and the safety-wrapped arm of a configuration.

    Args:
        config: The validated configuration (its document, ``[cell] seed`` and envelope).
        registry: Where to find the backends; default: the process-wide one.
        source: Configuration source the backends see; default ``config.source``.
        camera: Backend section to use instead of the document's ``[camera]``.
        arm: Backend section to use instead of the document's ``[arm]``.
        apply_correction: Wrap the camera so that its ``[camera.correction]`` is removed from every
            frame (default; ADR 0058); False: the raw camera (the table still checked), for ``cellcal depthcal``.

    Raises:
        ConfigError: If a backend is unknown or rejects its section.
    """
    registry = registry or default_registry()
    ctx = _context_factory(config.document, config.source if source is None else source, config.cell.seed,
                           tuple(c.name for c in config.cameras))
    cam = registry.create_camera(config.camera_section if camera is None else camera,
                                 ctx(config.camera_key, _fixed_placement(config)),
                                 apply_correction=apply_correction)
    inner: RobotArm = registry.create_arm(config.arm_section if arm is None else arm, ctx("arm"))
    return cam, SafeArm(inner, config.safety_limits())


def build_camera(document: Mapping[str, Any], registry: Registry | None = None, *,
                 source: str | None = None) -> Camera3D:
    """Create the (unconnected) camera of a raw configuration document, not validated as a cell.

    For documents that only describe a camera (e.g. a study trial); the seed is the
    document's ``[cell] seed`` (default 0).

    Raises:
        ConfigError: If the camera backend is unknown or rejects its section.
    """
    registry = registry or default_registry()
    ctx = _context_factory(document, source, int(document.get("cell", {}).get("seed", 0)))
    return registry.create_camera(document["camera"], ctx("camera"))
