"""cellcal.devices: the Camera3D and RobotArm interfaces, data types, errors, registry, wrappers, safety.

Depends on numpy/scipy only; never on a vendor SDK, a driver or a simulator. The public
names are re-exported here and imported on first use (PEP 562), so importing one light
module (``cellcal.devices.errors``, say) does not load numpy and every interface (ADR 0021).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .lazy import lazy_exports

#: Public name -> the module (relative to this package) that defines it.
_EXPORTS = {
    "RobotArm": ".arm",
    "BackendContext": ".base",
    "CameraPlacement": ".base",
    "Device": ".base",
    "BoundedCaller": ".blocking",
    "DeadlineGuard": ".blocking",
    "Camera3D": ".camera",
    "BackendOverrunError": ".errors",
    "CalibrationError": ".errors",
    "CalibrationQualityError": ".errors",
    "CellcalError": ".errors",
    "ConfigError": ".errors",
    "DeviceConnectionError": ".errors",
    "DeviceError": ".errors",
    "DeviceTimeoutError": ".errors",
    "FrameError": ".errors",
    "MissingDependencyError": ".errors",
    "MotionError": ".errors",
    "NativeCrashError": ".errors",
    "NotConnectedError": ".errors",
    "OutputError": ".errors",
    "ProtocolError": ".errors",
    "RegistryError": ".errors",
    "SafetyError": ".errors",
    "VendorError": ".errors",
    "ForwardingArm": ".forwarding",
    "ForwardingCamera": ".forwarding",
    "MeasurementModel": ".measurement",
    "Pose": ".pose",
    "BackendEntry": ".registry",
    "Registry": ".registry",
    "default_registry": ".registry",
    "SafeArm": ".safety",
    "SafetyLimits": ".safety",
    "BoxView": ".scene_view",
    "SceneSnapshot": ".scene_view",
    "SceneView": ".scene_view",
    "scene_view": ".scene_view",
    "ArmStatus": ".types",
    "DeviceInfo": ".types",
    "Frame": ".types",
    "Intrinsics": ".types",
}

__all__ = [
    "ArmStatus",
    "BackendContext",
    "BackendEntry",
    "BackendOverrunError",
    "BoundedCaller",
    "BoxView",
    "CalibrationError",
    "CalibrationQualityError",
    "Camera3D",
    "CameraPlacement",
    "CellcalError",
    "ConfigError",
    "DeadlineGuard",
    "Device",
    "DeviceConnectionError",
    "DeviceError",
    "DeviceInfo",
    "DeviceTimeoutError",
    "ForwardingArm",
    "ForwardingCamera",
    "Frame",
    "FrameError",
    "Intrinsics",
    "MeasurementModel",
    "MissingDependencyError",
    "MotionError",
    "NativeCrashError",
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
    "SceneSnapshot",
    "SceneView",
    "VendorError",
    "default_registry",
    "scene_view",
]

if TYPE_CHECKING:
    from .arm import RobotArm
    from .base import BackendContext, CameraPlacement, Device
    from .blocking import BoundedCaller, DeadlineGuard
    from .camera import Camera3D
    from .errors import (
        BackendOverrunError,
        CalibrationError,
        CalibrationQualityError,
        CellcalError,
        ConfigError,
        DeviceConnectionError,
        DeviceError,
        DeviceTimeoutError,
        FrameError,
        MissingDependencyError,
        MotionError,
        NativeCrashError,
        NotConnectedError,
        OutputError,
        ProtocolError,
        RegistryError,
        SafetyError,
        VendorError,
    )
    from .forwarding import ForwardingArm, ForwardingCamera
    from .measurement import MeasurementModel
    from .pose import Pose
    from .registry import BackendEntry, Registry, default_registry
    from .safety import SafeArm, SafetyLimits
    from .scene_view import BoxView, SceneSnapshot, SceneView, scene_view
    from .types import ArmStatus, DeviceInfo, Frame, Intrinsics


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
