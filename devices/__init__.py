"""cellcal.devices: the Camera3D and RobotArm interfaces, data types, errors, registry, wrappers, safety.

Depends on numpy/scipy only; never on a vendor SDK, a driver or a simulator.
"""

from .arm import RobotArm
from .base import BackendContext, Device
from .camera import Camera3D
from .errors import (
    CalibrationError,
    CalibrationQualityError,
    CellcalError,
    ConfigError,
    DeviceConnectionError,
    DeviceError,
    DeviceTimeoutError,
    MissingDependencyError,
    MotionError,
    NotConnectedError,
    OutputError,
    ProtocolError,
    RegistryError,
    SafetyError,
    VendorError,
)
from .forwarding import ForwardingArm, ForwardingCamera
from .pose import Pose
from .registry import BackendEntry, Registry, default_registry
from .safety import SafeArm, SafetyLimits
from .types import ArmStatus, DeviceInfo, Frame, Intrinsics

__all__ = [
    "ArmStatus",
    "BackendContext",
    "BackendEntry",
    "CalibrationError",
    "CalibrationQualityError",
    "Camera3D",
    "CellcalError",
    "ConfigError",
    "Device",
    "DeviceConnectionError",
    "DeviceError",
    "DeviceInfo",
    "DeviceTimeoutError",
    "ForwardingArm",
    "ForwardingCamera",
    "Frame",
    "Intrinsics",
    "MissingDependencyError",
    "MotionError",
    "NotConnectedError",
    "OutputError",
    "Pose",
    "ProtocolError",
    "Registry",
    "RegistryError",
    "RobotArm",
    "SafeArm",
    "SafetyError",
    "SafetyLimits",
    "VendorError",
    "default_registry",
]
