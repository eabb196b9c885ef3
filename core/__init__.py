"""cellcal.core: the measuring-plane calibration built on :mod:`cellcal.devices`.

Subpackages: ``geometry`` (planes, frame chains, sampling, PlaneMap), ``methods`` (the
paper's grid methods, the full-frame fit), ``calibration`` (config, calibrator, journal,
report), ``monitor``, ``study`` and ``cli``. The names a user needs are re-exported here
and imported on first use, so ``import cellcal.core`` stays cheap (ADR 0006).

Example:
    >>> from cellcal.core import fit_full_frame, load_config, Calibrator  # doctest: +SKIP
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

#: Public name -> the subpackage that defines it.
_EXPORTS = {
    "Plane": "cellcal.core.geometry",
    "PlaneFit": "cellcal.core.geometry",
    "PlaneMap": "cellcal.core.geometry",
    "FrameChain": "cellcal.core.geometry",
    "fit_plane_ols": "cellcal.core.geometry",
    "fit_plane_robust": "cellcal.core.geometry",
    "FullFrameSettings": "cellcal.core.methods",
    "FullFrameResult": "cellcal.core.methods",
    "fit_full_frame": "cellcal.core.methods",
    "check_gates": "cellcal.core.methods",
    "paper_methods": "cellcal.core.methods",
    "measure_frames": "cellcal.core.methods",
    "CellConfig": "cellcal.core.calibration",
    "load_config": "cellcal.core.calibration",
    "parse_config": "cellcal.core.calibration",
    "Calibrator": "cellcal.core.calibration",
    "build_devices": "cellcal.core.calibration",
    "run_to_file": "cellcal.core.calibration",
    "Monitor": "cellcal.core.monitor",
    "run_study": "cellcal.core.study",
}

__all__ = [
    "Calibrator",
    "CellConfig",
    "FrameChain",
    "FullFrameResult",
    "FullFrameSettings",
    "Monitor",
    "Plane",
    "PlaneFit",
    "PlaneMap",
    "build_devices",
    "check_gates",
    "fit_full_frame",
    "fit_plane_ols",
    "fit_plane_robust",
    "load_config",
    "measure_frames",
    "paper_methods",
    "parse_config",
    "run_study",
    "run_to_file",
]

if TYPE_CHECKING:
    from cellcal.core.calibration import Calibrator, CellConfig, build_devices, load_config, parse_config, run_to_file
    from cellcal.core.geometry import FrameChain, Plane, PlaneFit, PlaneMap, fit_plane_ols, fit_plane_robust
    from cellcal.core.methods import (
        FullFrameResult,
        FullFrameSettings,
        check_gates,
        fit_full_frame,
        measure_frames,
        paper_methods,
    )
    from cellcal.core.monitor import Monitor
    from cellcal.core.study import run_study


def __getattr__(name: str) -> Any:
    """Import a re-exported name on first use (PEP 562)."""
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'cellcal.core' has no attribute {name!r}")
    value = getattr(import_module(module), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
