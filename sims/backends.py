"""Entry-point targets of the built-in ``sim`` backends (see pyproject.toml).

Both build on the one :class:`~cellcal.sims.world.SimWorld` of their configuration
document (``world_from_context``), so a ``sim`` camera and a ``sim`` arm created from
the same :class:`~cellcal.devices.base.BackendContext` are coupled: the camera hangs
off the arm's flange.
"""

from __future__ import annotations

from .arm import SimRobotArm
from .camera import SimCamera3D

SimCamera3DBackend = SimCamera3D
SimRobotArmBackend = SimRobotArm

__all__ = ["SimCamera3DBackend", "SimRobotArmBackend"]
