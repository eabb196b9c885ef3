"""The recording layout: format version, topics, their JSON schemas, and the lazy ``mcap`` import.

The layout and why it is so are in ADR 0009 (docs/adr/0009-recording-format.md).
"""

from __future__ import annotations

from typing import Any

from cellcal.devices.errors import MissingDependencyError

#: Version tag of the recording layout; bump on any incompatible change.
RECORDING_FORMAT = "cellcal.recording/1"
#: MCAP profile field (custom profile: plain JSON channels).
MCAP_PROFILE = ""
#: First bytes of every MCAP file (MCAP specification).
MCAP_MAGIC = b"\x89MCAP0\r\n"

TOPIC_SESSION = "/cellcal/session"
TOPIC_RESULT = "/cellcal/result"
TOPIC_CAMERA_INFO = "/camera/info"
TOPIC_CAMERA_CALIBRATION = "/camera/calibration"
TOPIC_CAPTURE = "/camera/capture"
TOPIC_DEPTH = "/camera/depth"
TOPIC_ARM_INFO = "/arm/info"
TOPIC_ARM_CALL = "/arm/call"
TOPIC_FLANGE_POSE = "/arm/flange_pose"

_TIME = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
_ARRAY = {
    "type": "object",
    "description": "an n-d array: numpy dtype string (byte order included), shape, C-order bytes (base64)",
    "properties": {"dtype": {"type": "string"}, "shape": {"type": "array", "items": {"type": "integer"}},
                   "data": {"type": "string", "contentEncoding": "base64"}},
}
_POSE_JSON = {
    "type": "object",
    "description": "rigid transform: translation (m) and the exact stored quaternion [x, y, z, w]",
    "properties": {"translation_m": {"type": "array", "items": {"type": "number"}},
                   "quaternion_xyzw": {"type": "array", "items": {"type": "number"}}},
}
_ERROR = {
    "type": ["object", "null"],
    "description": "a typed cellcal error: class name in cellcal.devices.errors, message, attributes",
    "properties": {"type": {"type": "string"}, "message": {"type": "string"}, "attrs": {"type": "object"}},
}
_XYZ = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}}

#: JSON schemas by schema name (custom ``cellcal.*`` and the Foxglove ones we use).
SCHEMAS: dict[str, dict[str, Any]] = {
    "cellcal.Session": {
        "title": "cellcal.Session", "type": "object",
        "properties": {"format": {"type": "string"}, "cellcal_version": {"type": "string"},
                       "created_utc": {"type": "string"}, "config_source": {"type": ["string", "null"]},
                       "config": {"type": ["object", "null"]}, "config_toml": {"type": ["string", "null"]}},
    },
    "cellcal.Result": {
        "title": "cellcal.Result", "type": "object",
        "properties": {"ok": {"type": "boolean"}, "result": {"type": ["object", "null"]}, "error": _ERROR},
    },
    "cellcal.DeviceInfo": {
        "title": "cellcal.DeviceInfo", "type": "object",
        "properties": {"event": {"type": "integer"}, "backend": {"type": "string"}, "vendor": {"type": "string"},
                       "model": {"type": "string"}, "serial": {"type": "string"}, "firmware": {"type": "string"},
                       "extra": {"type": "object"}, "intrinsics": {"type": ["object", "null"]},
                       "default_timeout_s": {"type": "number"}},
    },
    "cellcal.Capture": {
        "title": "cellcal.Capture", "type": "object",
        "properties": {"event": {"type": "integer"}, "capture": {"type": "integer"},
                       "timeout_s": {"type": "number"}, "duration_s": {"type": "number"},
                       "frame": {"type": ["object", "null"], "properties": {
                           "timestamp": {"type": "number"}, "sequence": {"type": "integer"},
                           "intrinsics": {"type": "object"},
                           "arrays": {"type": "object", "additionalProperties": _ARRAY}}},
                       "error": _ERROR},
    },
    "cellcal.ArmCall": {
        "title": "cellcal.ArmCall", "type": "object",
        "properties": {"event": {"type": "integer"}, "call": {"type": "integer"},
                       "method": {"type": "string", "enum": ["get_pose", "move_linear", "stop", "joint_positions",
                                                             "status", "clear_errors"]},
                       "args": {"type": "object", "properties": {
                           "timeout_s": {"type": "number"}, "target": _POSE_JSON,
                           "speed_m_s": {"type": "number"}, "acceleration_m_s2": {"type": "number"}}},
                       "result": {"description": "pose, joint angles (rad), status, or null"},
                       "error": _ERROR, "duration_s": {"type": "number"}},
    },
    "foxglove.RawImage": {
        "title": "foxglove.RawImage", "type": "object",
        "properties": {"timestamp": _TIME, "frame_id": {"type": "string"}, "width": {"type": "integer"},
                       "height": {"type": "integer"}, "encoding": {"type": "string"}, "step": {"type": "integer"},
                       "data": {"type": "string", "contentEncoding": "base64"}},
    },
    "foxglove.CameraCalibration": {
        "title": "foxglove.CameraCalibration", "type": "object",
        "properties": {"timestamp": _TIME, "frame_id": {"type": "string"}, "width": {"type": "integer"},
                       "height": {"type": "integer"}, "distortion_model": {"type": "string"},
                       **{k: {"type": "array", "items": {"type": "number"}} for k in "DKRP"}},
    },
    "foxglove.PoseInFrame": {
        "title": "foxglove.PoseInFrame", "type": "object",
        "properties": {"timestamp": _TIME, "frame_id": {"type": "string"},
                       "pose": {"type": "object", "properties": {
                           "position": _XYZ,
                           "orientation": {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}}}}},
    },
}

#: Schema of each topic.
CHANNELS: dict[str, str] = {
    TOPIC_SESSION: "cellcal.Session",
    TOPIC_RESULT: "cellcal.Result",
    TOPIC_CAMERA_INFO: "cellcal.DeviceInfo",
    TOPIC_CAMERA_CALIBRATION: "foxglove.CameraCalibration",
    TOPIC_CAPTURE: "cellcal.Capture",
    TOPIC_DEPTH: "foxglove.RawImage",
    TOPIC_ARM_INFO: "cellcal.DeviceInfo",
    TOPIC_ARM_CALL: "cellcal.ArmCall",
    TOPIC_FLANGE_POSE: "foxglove.PoseInFrame",
}


def import_mcap() -> tuple[Any, Any]:
    """The ``mcap`` writer and reader modules.

    Raises:
        MissingDependencyError: If ``mcap`` (extra ``record``) is not installed.
    """
    try:
        import mcap.reader as reader
        import mcap.writer as writer
    except ImportError:
        raise MissingDependencyError("mcap (needed to record and replay sessions)", "record") from None
    return writer, reader

