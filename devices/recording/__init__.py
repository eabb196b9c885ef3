"""Session recording to MCAP and reading it back (ADR 0009): schema, codec, Foxglove adapters,
:class:`SessionRecorder` with its device wrappers, and :func:`read_recording`; the 3D :class:`Scene`
of a frame and its ROS 2 bag (subpackage ``ros2``, ADR 0020)."""

from cellcal.devices.recording.codec import (
    decode_array,
    decode_error,
    decode_frame,
    decode_info,
    decode_model,
    decode_pose,
    encode_array,
    encode_error,
    encode_frame,
    encode_model,
    encode_pose,
)
from cellcal.devices.recording.reader import Recording, read_recording
from cellcal.devices.recording.scene import Scene
from cellcal.devices.recording.schema import CHANNELS, READABLE_FORMATS, RECORDING_FORMAT, SCHEMAS
from cellcal.devices.recording.wrappers import RecordingArm, RecordingCamera
from cellcal.devices.recording.writer import SessionRecorder

__all__ = [
    "CHANNELS",
    "READABLE_FORMATS",
    "RECORDING_FORMAT",
    "SCHEMAS",
    "Recording",
    "RecordingArm",
    "RecordingCamera",
    "Scene",
    "SessionRecorder",
    "decode_array",
    "decode_error",
    "decode_frame",
    "decode_info",
    "decode_model",
    "decode_pose",
    "encode_array",
    "encode_error",
    "encode_frame",
    "encode_model",
    "encode_pose",
    "read_recording",
]
