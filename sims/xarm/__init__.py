"""Emulated UFACTORY xArm controller serving a simulated arm on a pty (:class:`XArmEmulator`) or over TCP
(:class:`XArmTcpServer`), and backend :class:`EmulatedXArmArm` (``arms: xarm-emulated``). Standalone:
``python -m cellcal.sims.xarm``."""

from cellcal.sims.xarm.backend import EmulatedXArmArm
from cellcal.sims.xarm.emulator import XArmEmulator
from cellcal.sims.xarm.tcp_server import XArmTcpServer

__all__ = ["EmulatedXArmArm", "XArmEmulator", "XArmTcpServer"]
