"""Universal Robots over ur_rtde: backend class :class:`URArm`, entry point ``arms: ur`` (extra ``ur``)."""

from cellcal.drivers.ur.arm import URArm
from cellcal.drivers.ur.config import URConfig

__all__ = ["URArm", "URConfig"]
