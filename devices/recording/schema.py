"""The recording layout: format version, topics, their JSON schemas, and the lazy ``mcap`` import.

The layout and why it is so are in ADR 0009 (docs/adr/0009-recording-format.md).
"""

from __future__ import annotations

from typing import Any

from cellcal.devices.errors import MissingDependencyError

#: Version tag of the recording layout; bump on any incompatible change. Version 2 adds the
#: camera's measurement model (``/camera/info`` and each frame; docs/adr/0032-model-in-recordings-and-kit.md).
RECORDING_FORMAT = "cellcal.recording/2"
#: Formats this cellcal reads: version 1 recordings replay with an ``unknown`` measurement model.
READABLE_FORMATS: tuple[str, ...] = ("cellcal.recording/1", RECORDING_FORMAT)
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
    "description": "rigid transform: translation (m), quaternion [x, y, z, w] and the exact rotation matrix "
                   "(row-major)",
    "properties": {"translation_m": {"type": "array", "items": {"type": "number"}},
                   "quaternion_xyzw": {"type": "array", "items": {"type": "number"}},
                   "rotation_matrix": {"type": "array", "items": {"type": "number"}}},
}
_ERROR = {
    "type": ["object", "null"],
    "description": "a typed cellcal error: class name in cellcal.devices.errors, message, attributes",
    "properties": {"type": {"type": "string"}, "message": {"type": "string"}, "attrs": {"type": "object"}},
}
_XYZ = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}}
_MODEL = {
    "type": "object",
    "description": "the camera's measurement model (MeasurementModel.to_dict: kind, SI values, source, settings); "
                   "absent: unknown",
    "properties": {"kind": {"type": "string", "enum": ["tof", "stereo", "structured_light", "unknown"]},
                   "source": {"type": "string"}, "settings": {"type": "object"}},
}

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
                       "measurement_model": _MODEL, "default_timeout_s": {"type": "number"}},
    },
    "cellcal.Capture": {
        "title": "cellcal.Capture", "type": "object",
        "properties": {"event": {"type": "integer"}, "capture": {"type": "integer"},
                       "timeout_s": {"type": "number"}, "duration_s": {"type": "number"},
                       "frame": {"type": ["object", "null"], "properties": {
                           "timestamp": {"type": "number"}, "sequence": {"type": "integer"},
                           "intrinsics": {"type": "object"}, "measurement": _MODEL,
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


# ---------------------------------------------------------------- scene channels (ADR 0020)
TOPIC_POINTS = "/camera/points"
TOPIC_PLANE = "/cellcal/plane"
TOPIC_TF = "/tf"
TOPIC_DRIFT = "/cellcal/drift"
TOPIC_TRACK = "/cellcal/track"

_POSE = {"type": "object", "properties": {
    "position": _XYZ, "orientation": {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}}}}
_COLOR = {"type": "object", "properties": {k: {"type": "number"} for k in "rgba"}}
_NUM = {"type": "number"}

#: JSON schemas of the scene messages: the Foxglove ones by their names, and cellcal's drift values.
SCENE_SCHEMAS: dict[str, dict[str, Any]] = {
    "foxglove.PointCloud": {
        "title": "foxglove.PointCloud", "type": "object",
        "properties": {"timestamp": _TIME, "frame_id": {"type": "string"}, "pose": _POSE,
                       "point_stride": {"type": "integer"},
                       "fields": {"type": "array", "items": {"type": "object", "properties": {
                           "name": {"type": "string"}, "offset": {"type": "integer"}, "type": {"type": "integer"}}}},
                       "data": {"type": "string", "contentEncoding": "base64"}},
    },
    "foxglove.SceneUpdate": {
        "title": "foxglove.SceneUpdate", "type": "object",
        "properties": {"deletions": {"type": "array", "items": {"type": "object"}},
                       "entities": {"type": "array", "items": {"type": "object", "properties": {
                           "timestamp": _TIME, "frame_id": {"type": "string"}, "id": {"type": "string"},
                           "cubes": {"type": "array", "items": {"type": "object", "properties": {
                               "pose": _POSE, "size": _XYZ, "color": _COLOR}}},
                           "arrows": {"type": "array", "items": {"type": "object", "properties": {
                               "pose": _POSE, "shaft_length": _NUM, "shaft_diameter": _NUM,
                               "head_length": _NUM, "head_diameter": _NUM, "color": _COLOR}}}}}}},
    },
    "foxglove.FrameTransforms": {
        "title": "foxglove.FrameTransforms", "type": "object",
        "properties": {"transforms": {"type": "array", "items": {"type": "object", "properties": {
            "timestamp": _TIME, "parent_frame_id": {"type": "string"}, "child_frame_id": {"type": "string"},
            "translation": _XYZ, "rotation": {"type": "object", "properties": {k: _NUM for k in "xyzw"}}}}}},
    },
    "cellcal.Drift": {
        "title": "cellcal.Drift", "type": "object",
        "description": "drift of a monitored camera's plane from its baseline (radians, metres)",
        "properties": {"timestamp": _TIME, "frame_id": {"type": "string"}, "label": {"type": "string"},
                       "phase": {"type": "string"}, "tilt_deviation_rad": {"type": ["number", "null"]},
                       "height_deviation_m": {"type": ["number", "null"]},
                       "tilt_threshold_rad": {"type": ["number", "null"]},
                       "height_threshold_m": {"type": ["number", "null"]},
                       "tilt_x_rad": _NUM, "tilt_y_rad": _NUM, "height_m": _NUM},
    },
    "cellcal.Track": {
        "title": "cellcal.Track", "type": "object",
        "description": "cellcal track: one frame's outcome, the tracked mount (flange frame, metres, degrees) and "
                       "the change event of that frame, if any",
        "properties": {"timestamp": _TIME, "frame_id": {"type": "string"}, "t_s": _NUM,
                       "outcome": {"type": "string"}, "chi2": {"type": ["number", "null"]},
                       "mount_translation_m": _XYZ, "mount_rpy_deg": _XYZ,
                       "change_open": {"type": "boolean"},
                       "event": {"type": ["object", "null"]}},
    },
}
#: Scene topics of a recording (registered when the first scene is logged) and of the live view.
SCENE_CHANNELS: dict[str, str] = {
    TOPIC_POINTS: "foxglove.PointCloud",
    TOPIC_PLANE: "foxglove.SceneUpdate",
    TOPIC_TF: "foxglove.FrameTransforms",
}
#: What the live view of a monitor adds: the drift values.
DRIFT_CHANNELS: dict[str, str] = {TOPIC_DRIFT: "cellcal.Drift"}
#: What the live view of ``cellcal track`` adds: each frame's outcome, the mount and the change events.
TRACK_CHANNELS: dict[str, str] = {TOPIC_TRACK: "cellcal.Track"}


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

