"""The sims' off switch for tests of ideal-camera figures: ``[sim.systematic] enabled = false`` (ADR 0054).

The shipped sims draw a systematic depth error (millimetres of height bias) by default. A test that
pins a noise-only figure (a height to 0.1 mm of the truth, a Cramér–Rao bound, a noise model's
coverage) says so with one of these; a test of what a user sees on the shipped sims does not.
"""

from __future__ import annotations

from typing import Any

from cellcal.core.calibration import CellConfig
from cellcal.testing.sim import ConfigSource, cell_config

__all__ = ["IDEAL_CAMERA", "IDEAL_CAMERA_TOML", "ideal_config"]

#: Tables to merge over a cell's document (``testing.sim.cell_config(..., tables=IDEAL_CAMERA)``).
IDEAL_CAMERA: dict[str, dict[str, Any]] = {"sim": {"systematic": {"enabled": False}}}
#: The same, to append to a TOML document that has no ``[sim.systematic]`` table of its own.
IDEAL_CAMERA_TOML = "\n[sim.systematic]\nenabled = false  # an ideal camera: noise only (ADR 0054)\n"


def ideal_config(config: ConfigSource = None) -> CellConfig:
    """``config`` (None: the packaged ``sim.toml``) with the sims' systematic errors off."""
    return cell_config(config, IDEAL_CAMERA)
