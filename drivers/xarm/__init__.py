"""UFACTORY xArm 5/6/7 over serial: backend class :class:`XArmArm`, entry point ``arms: xarm`` (extra ``xarm``)."""

from cellcal.drivers.xarm.arm import XArmArm

__all__ = ["XArmArm"]
