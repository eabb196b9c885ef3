"""Exact JSON forms of what a recording stores: arrays, frames, poses, errors, device info, call results,
measurement models.

Every ``decode_*`` inverts its ``encode_*`` bit for bit (ADR 0009, "Exactness rules").
"""

from __future__ import annotations

import base64
import contextlib
import json
import math
from collections.abc import Mapping
from dataclasses import asdict, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.devices import errors as _errors
from cellcal.devices.errors import CellcalError, ConfigError, DeviceError, RecordingError
from cellcal.devices.jsonsafe import json_safe
from cellcal.devices.measurement import UNKNOWN_MODEL, MeasurementModel
from cellcal.devices.pose import Pose
from cellcal.devices.types import ArmStatus, DeviceInfo, Frame, Intrinsics

#: Arrays of a :class:`Frame` stored per capture (``confidence`` only when present).
FRAME_ARRAYS = ("distance", "xyz", "amplitude", "valid", "confidence")


def dumps(payload: Mapping[str, Any]) -> bytes:
    """Compact UTF-8 JSON of a message payload (shortest round-trip floats; NaN/inf rejected)."""
    return json.dumps(json_safe(payload), separators=(",", ":"), allow_nan=False).encode("utf-8")


def seconds_to_ns(seconds: float | None) -> int:
    """Nanoseconds of a time in seconds; 0 for None, non-finite or non-positive times."""
    return round(seconds * 1e9) if seconds is not None and math.isfinite(seconds) and seconds > 0 else 0


def encode_array(array: NDArray[Any]) -> dict[str, Any]:
    """JSON form of an array: dtype string, shape, and its exact C-order bytes in base64."""
    arr = np.ascontiguousarray(array)
    return {"dtype": arr.dtype.str, "shape": list(arr.shape), "data": base64.b64encode(arr.tobytes()).decode("ascii")}


def decode_array(data: Mapping[str, Any], what: str) -> NDArray[Any]:
    """Inverse of :func:`encode_array` (a fresh, writeable, native-byte-order array).

    Raises:
        RecordingError: If the entry is malformed or its byte count disagrees with the shape.
    """
    try:
        dtype = np.dtype(str(data["dtype"]))
        shape = tuple(int(n) for n in data["shape"])
        raw = base64.b64decode(data["data"], validate=True)
    except (KeyError, TypeError, ValueError) as exc:
        raise RecordingError(f"recorded array '{what}' is malformed: {exc}") from None
    # only plain numeric dtypes, and exactly prod(shape) * itemsize bytes
    if dtype.kind not in "biuf" or any(n < 0 for n in shape) or len(raw) != math.prod(shape) * dtype.itemsize:
        raise RecordingError(f"recorded array '{what}' ({dtype.str}, shape {shape}) holds {len(raw)} bytes")
    arr = np.frombuffer(raw, dtype=dtype).reshape(shape)
    return arr.astype(dtype.newbyteorder("="), copy=True)


def encode_model(model: MeasurementModel) -> dict[str, Any]:
    """JSON form of a camera's measurement model (:meth:`MeasurementModel.to_dict`, settings JSON-cleaned)."""
    return json_safe(model.to_dict())  # type: ignore[no-any-return]


def decode_model(data: Any, what: str) -> MeasurementModel:
    """Inverse of :func:`encode_model`; None (a recording of format 1, an unknown model) is ``unknown``.

    A recorded model that names no source keeps ``source = "recording"``; otherwise its source is
    kept as recorded (who stated it: the device, the backend, the config; ADR 0032).

    Args:
        data: The recorded JSON object, or None.
        what: Where it was recorded, for messages (``"frame.measurement"``).

    Raises:
        RecordingError: One line naming ``what``, the key and what was wrong.
    """
    if data is None:
        return UNKNOWN_MODEL
    if not isinstance(data, Mapping):
        raise RecordingError(f"recorded {what} is a {type(data).__name__}, not an object")
    try:
        model = MeasurementModel.from_dict(data, where=what)
    except ConfigError as exc:
        raise RecordingError(f"recorded measurement model is malformed: {exc}") from None
    return model.with_source("recording") if model.known and "source" not in data else model


def encode_frame(frame: Frame) -> dict[str, Any]:
    """JSON form of a frame that decodes to identical bits (arrays, timestamp, sequence, metadata, model)."""
    arrays = {name: encode_array(getattr(frame, name)) for name in FRAME_ARRAYS
              if getattr(frame, name) is not None}
    doc = {"timestamp": float(frame.timestamp), "sequence": int(frame.sequence),
           "intrinsics": frame.intrinsics.to_dict(), "arrays": arrays}
    if frame.metadata:  # vendor facts per frame (device clock, measurement block); JSON data only
        doc["metadata"] = json_safe(frame.metadata)
    if frame.measurement.known:  # format 2: the model the frame was measured with (none: unknown)
        doc["measurement"] = encode_model(frame.measurement)
    return doc


def decode_frame(data: Mapping[str, Any]) -> Frame:
    """Inverse of :func:`encode_frame`.

    Raises:
        RecordingError: If the recorded frame is malformed or inconsistent.
    """
    try:
        arrays = data["arrays"]
        intrinsics = Intrinsics(**data["intrinsics"])
        kwargs: dict[str, Any] = {name: decode_array(arrays[name], name) for name in FRAME_ARRAYS if name in arrays}
        metadata = data.get("metadata", {})
        if not isinstance(metadata, dict):
            raise RecordingError(f"recorded frame metadata is a {type(metadata).__name__}, not an object")
        measurement = decode_model(data.get("measurement"), "frame.measurement")
        return Frame(intrinsics=intrinsics, timestamp=float(data["timestamp"]), sequence=int(data["sequence"]),
                     metadata=dict(metadata), measurement=measurement, **kwargs)
    except RecordingError:
        raise
    except (CellcalError, KeyError, TypeError, ValueError) as exc:
        raise RecordingError(f"recorded frame is malformed: {type(exc).__name__}: {exc}") from None


def encode_pose(pose: Pose) -> dict[str, Any]:
    """JSON form of a pose: translation (m), quaternion (for viewers) and the exact rotation matrix."""
    return {"translation_m": [float(v) for v in pose.translation],
            "quaternion_xyzw": [float(v) for v in pose.rotation.as_quat()],
            "rotation_matrix": [float(v) for v in pose.rotation_matrix.ravel()]}


def decode_pose(data: Mapping[str, Any]) -> Pose:
    """Inverse of :func:`encode_pose`, bit-exact: the recorded rotation matrix as it is (a recording
    without one: its quaternion, not renormalised).

    Raises:
        RecordingError: If the entry is malformed or the quaternion is not unit length.
    """
    try:
        t = np.asarray(data["translation_m"], dtype=np.float64)
        if "rotation_matrix" in data:  # the pose's own matrix: bit-exact (Pose keeps a rotation to 1e-12 as is)
            return Pose.from_rotation_matrix(np.asarray(data["rotation_matrix"], dtype=np.float64).reshape(3, 3), t)
        from scipy.spatial.transform import Rotation  # a recording without the matrix

        q = np.asarray(data["quaternion_xyzw"], dtype=np.float64)
        # a unit quaternion within 1e-9 (what as_quat wrote), all finite
        if q.shape != (4,) or not np.all(np.isfinite(q)) or abs(float(np.linalg.norm(q)) - 1.0) > 1e-9:
            raise ValueError(f"quaternion {q.tolist()} is not a unit quaternion")
        # Rotation.from_quat always renormalises, which can change the last bit; the
        # constructor with normalize=False keeps the recorded quaternion exactly.
        return Pose(Rotation(q, normalize=False), t)
    except (KeyError, TypeError, ValueError, CellcalError) as exc:
        raise RecordingError(f"recorded pose is malformed: {exc}") from None


#: The JSON form of a Ctrl-C (KeyboardInterrupt) that cut a call or the whole session short.
INTERRUPTED: Mapping[str, Any] = {"type": "KeyboardInterrupt", "message": "interrupted (Ctrl-C)", "attrs": {}}


def encode_error(exc: CellcalError | KeyboardInterrupt) -> dict[str, Any]:
    """JSON form of a typed error (class name, message and simple attributes), or of a Ctrl-C."""
    if isinstance(exc, KeyboardInterrupt):
        return {**INTERRUPTED, "attrs": {}}
    attrs = {k: v for k, v in vars(exc).items() if isinstance(v, (str, int, float, bool)) or v is None}
    return {"type": type(exc).__name__, "message": str(exc), "attrs": attrs}


def decode_error(data: Mapping[str, Any]) -> CellcalError:
    """Rebuild a recorded error with its class (from :mod:`cellcal.devices.errors`), message and attributes.

    An unknown class (and a recorded Ctrl-C) becomes a :class:`DeviceError` whose message names it.
    """
    name, message = str(data.get("type", "")), str(data.get("message", ""))
    cls = getattr(_errors, name, None)
    if not (isinstance(cls, type) and issubclass(cls, CellcalError)):
        return DeviceError(f"{name}: {message}")
    exc = cls.__new__(cls)
    Exception.__init__(exc, message)  # the exact recorded message, whatever the class's __init__ adds
    for key, value in dict(data.get("attrs") or {}).items():
        with contextlib.suppress(AttributeError, TypeError):
            setattr(exc, str(key), value)
    return exc


def encode_info(info: DeviceInfo) -> dict[str, Any]:
    """JSON form of a :class:`DeviceInfo` (its fields)."""
    return asdict(info)


def decode_info(data: Mapping[str, Any]) -> DeviceInfo:
    """The :class:`DeviceInfo` of an ``/camera/info`` or ``/arm/info`` message."""
    names = {f.name for f in fields(DeviceInfo)}
    try:
        return DeviceInfo(**{k: v for k, v in data.items() if k in names})
    except TypeError as exc:
        raise RecordingError(f"recorded device info is malformed: {exc}") from None


def encode_result(result: Any) -> Any:
    """JSON form of an arm call's result: a pose, a status, joint angles (rad), or None for anything else."""
    if isinstance(result, Pose):
        return encode_pose(result)
    if isinstance(result, ArmStatus):
        return asdict(result)
    if isinstance(result, np.ndarray):
        return [float(v) for v in result]
    return None
