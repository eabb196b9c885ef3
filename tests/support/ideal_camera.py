"""The sims' off switch for tests of ideal-camera figures: ``[sim.systematic] enabled = false`` (ADR 0054).

The shipped sims draw a systematic depth error (millimetres of height bias) by default. A test that
pins a noise-only figure (a height to 0.1 mm of the truth, a Cramér–Rao bound, a noise model's
coverage) says so with one of these; a test of what a user sees on the shipped sims does not.
"""

from __future__ import annotations

from typing import Any

from cellcal.core.calibration import CellConfig
from cellcal.testing.sim import ConfigSource, cell_config

__all__ = ["IDEAL_CAMERA", "IDEAL_CAMERA_TOML", "IDEAL_CELL", "IDEAL_CELL_TOML", "ideal_config"]

#: Tables to merge over a cell's document (``testing.sim.cell_config(..., tables=IDEAL_CAMERA)``).
IDEAL_CAMERA: dict[str, dict[str, Any]] = {"sim": {"systematic": {"enabled": False}}}
#: The same, to append to a TOML document that has no ``[sim.systematic]`` table of its own.
IDEAL_CAMERA_TOML = "\n[sim.systematic]\nenabled = false  # an ideal camera: noise only (ADR 0054)\n"

#: An ideal camera on an ideal arm: no kinematic error either (``[sim.arm_errors]``, ADR 0055), so that
#: the camera stands exactly where the plan commands it (a height to 0.1 mm of the planned one).
IDEAL_CELL: dict[str, dict[str, Any]] = {"sim": {"systematic": {"enabled": False}, "arm_errors": {"enabled": False}}}
#: The same, to append to a TOML document that has neither table of its own.
IDEAL_CELL_TOML = IDEAL_CAMERA_TOML + "\n[sim.arm_errors]\nenabled = false  # an ideal arm (ADR 0055)\n"


def ideal_config(config: ConfigSource = None, *, ideal_arm: bool = False) -> CellConfig:
    """``config`` (None: the packaged ``sim.toml``) with the sims' systematic errors off (and the arm's)."""
    return cell_config(config, IDEAL_CELL if ideal_arm else IDEAL_CAMERA)
