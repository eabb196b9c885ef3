"""Emulated UFACTORY xArm controller on a pty serving a simulated arm: :class:`XArmEmulator`, and backend
:class:`EmulatedXArmArm` (``arms: xarm-emulated``). Standalone: ``python -m cellcal.sims.xarm``."""

from cellcal.sims.xarm.backend import EmulatedXArmArm
from cellcal.sims.xarm.emulator import XArmEmulator

__all__ = ["EmulatedXArmArm", "XArmEmulator"]
