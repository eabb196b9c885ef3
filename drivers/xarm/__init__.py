"""UFACTORY xArm 5/6/7 over serial (extra ``xarm``) or TCP: backend :class:`XArmArm`, entry point ``arms: xarm``."""

from cellcal.drivers.xarm.arm import XArmArm

__all__ = ["XArmArm"]
