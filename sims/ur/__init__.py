"""Emulated Universal Robots controller (RTDE, script port, dashboard) serving a simulated arm:
:class:`UREmulator`, :class:`UREmulatorProcess` (the emulator as a child process), and backend
:class:`EmulatedURArm` (``arms: ur-emulated``). Standalone: ``python -m cellcal.sims.ur``."""

from cellcal.sims.ur.backend import EmulatedURArm
from cellcal.sims.ur.emulator import UR_LIKE, UREmulator
from cellcal.sims.ur.process import UREmulatorProcess

__all__ = ["UR_LIKE", "EmulatedURArm", "UREmulator", "UREmulatorProcess"]
