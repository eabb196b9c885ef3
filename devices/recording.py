"""Session recording to MCAP, and reading a recording back (ADR 0009).

A :class:`SessionRecorder` owns one MCAP file. Its wrappers —
:class:`RecordingCamera` and :class:`RecordingArm` — forward every call to the
wrapped device unchanged and log it: the configuration document, device identity
and intrinsics at connect, every captured frame with its exact array bytes, and
every arm call with its arguments, its result (or typed error) and its duration.
:func:`read_recording` parses such a file into a :class:`Recording`, which the
``replay`` backends (:mod:`cellcal.drivers.replay.backends`) play back bit-exactly.

Layout (all channels ``json`` message encoding with ``jsonschema`` schemas, so
Foxglove and ``mcap cat --json`` read them)::

    /cellcal/session     cellcal.Session            config document (+ TOML text), versions
    /cellcal/result      cellcal.Result             the calibration result or the run's error
    /camera/info         cellcal.DeviceInfo         identity + exact intrinsics, per connect
    /camera/calibration  foxglove.CameraCalibration intrinsics for Foxglove's panels
    /camera/capture      cellcal.Capture            every capture: exact frame arrays or error
    /camera/depth        foxglove.RawImage          distance image (32FC1, metres) for viewing
    /arm/info            cellcal.DeviceInfo         identity, per connect
    /arm/call            cellcal.ArmCall            every arm call: method, args, result/error
    /arm/flange_pose     foxglove.PoseInFrame       every pose read back, for Foxglove's 3D panel

Every message's MCAP ``sequence`` is one session-wide event counter, the order the
replay follows. ``mcap`` is an optional dependency (extra ``record``), imported
only when a recorder is created or a file is read.
"""

from __future__ import annotations

import base64
import contextlib
import json
import math
import os
import tempfile
import threading
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from types import TracebackType
from typing import Any, Self

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from . import errors as _errors
from .arm import RobotArm
from .camera import Camera3D
from .errors import (
    CellcalError,
    DeviceError,
    MissingDependencyError,
    RecordingError,
    RecordingFileError,
)
from .jsonsafe import json_safe
from .pose import Pose
from .types import ArmStatus, DeviceInfo, Frame, Intrinsics

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

#: Frame ids used in the Foxglove messages.
CAMERA_FRAME_ID = "camera"
BASE_FRAME_ID = "base"

#: Arrays of a :class:`Frame` stored per capture (``confidence`` only when present).
FRAME_ARRAYS = ("distance", "xyz", "amplitude", "valid", "confidence")

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


def _import_mcap() -> tuple[Any, Any]:
    """The ``mcap`` writer and reader modules, or :class:`MissingDependencyError`."""
    try:
        import mcap.reader as reader
        import mcap.writer as writer
    except ImportError:
        raise MissingDependencyError("mcap (needed to record and replay sessions)", "record") from None
    return writer, reader


def _package_version() -> str:
    try:
        return version("cellcal")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree
        return "unknown"


# ---------------------------------------------------------------------------- codecs
def _dumps(payload: Mapping[str, Any]) -> bytes:
    return json.dumps(json_safe(payload), separators=(",", ":"), allow_nan=False).encode("utf-8")


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
    if dtype.kind not in "biuf" or any(n < 0 for n in shape) or len(raw) != math.prod(shape) * dtype.itemsize:
        raise RecordingError(f"recorded array '{what}' ({dtype.str}, shape {shape}) holds {len(raw)} bytes")
    arr = np.frombuffer(raw, dtype=dtype).reshape(shape)
    return arr.astype(dtype.newbyteorder("="), copy=True)


def encode_frame(frame: Frame) -> dict[str, Any]:
    """JSON form of a frame that decodes to identical bits (arrays, timestamp, sequence)."""
    arrays = {name: encode_array(getattr(frame, name)) for name in FRAME_ARRAYS
              if getattr(frame, name) is not None}
    return {"timestamp": float(frame.timestamp), "sequence": int(frame.sequence),
            "intrinsics": frame.intrinsics.to_dict(), "arrays": arrays}


def decode_frame(data: Mapping[str, Any]) -> Frame:
    """Inverse of :func:`encode_frame`.

    Raises:
        RecordingError: If the recorded frame is malformed or inconsistent.
    """
    try:
        arrays = data["arrays"]
        intrinsics = Intrinsics(**data["intrinsics"])
        kwargs = {name: decode_array(arrays[name], name) for name in FRAME_ARRAYS if name in arrays}
        return Frame(intrinsics=intrinsics, timestamp=float(data["timestamp"]), sequence=int(data["sequence"]),
                     **kwargs)
    except RecordingError:
        raise
    except (CellcalError, KeyError, TypeError, ValueError) as exc:
        raise RecordingError(f"recorded frame is malformed: {type(exc).__name__}: {exc}") from None


def encode_pose(pose: Pose) -> dict[str, Any]:
    """JSON form of a pose: translation (m) and the rotation's stored quaternion."""
    return {"translation_m": [float(v) for v in pose.translation],
            "quaternion_xyzw": [float(v) for v in pose.rotation.as_quat()]}


def decode_pose(data: Mapping[str, Any]) -> Pose:
    """Inverse of :func:`encode_pose`, bit-exact: the quaternion is not renormalised.

    Raises:
        RecordingError: If the entry is malformed or the quaternion is not unit length.
    """
    try:
        q = np.asarray(data["quaternion_xyzw"], dtype=np.float64)
        t = np.asarray(data["translation_m"], dtype=np.float64)
        if q.shape != (4,) or not np.all(np.isfinite(q)) or abs(float(np.linalg.norm(q)) - 1.0) > 1e-9:
            raise ValueError(f"quaternion {q.tolist()} is not a unit quaternion")
        # Rotation.from_quat always renormalises, which can change the last bit; the
        # constructor with normalize=False keeps the recorded quaternion exactly.
        return Pose(Rotation(q, normalize=False), t)
    except (KeyError, TypeError, ValueError, CellcalError) as exc:
        raise RecordingError(f"recorded pose is malformed: {exc}") from None


def encode_error(exc: CellcalError) -> dict[str, Any]:
    """JSON form of a typed error: class name, message and simple attributes."""
    attrs = {k: v for k, v in vars(exc).items() if isinstance(v, (str, int, float, bool)) or v is None}
    return {"type": type(exc).__name__, "message": str(exc), "attrs": attrs}


def decode_error(data: Mapping[str, Any]) -> CellcalError:
    """Rebuild a recorded error with its class (from :mod:`cellcal.devices.errors`), message and attributes.

    An unknown class becomes a :class:`DeviceError` whose message names it.
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


def _info_payload(info: DeviceInfo) -> dict[str, Any]:
    return asdict(info)


def decode_info(data: Mapping[str, Any]) -> DeviceInfo:
    """The :class:`DeviceInfo` of an ``/camera/info`` or ``/arm/info`` message."""
    names = {f.name for f in fields(DeviceInfo)}
    try:
        return DeviceInfo(**{k: v for k, v in data.items() if k in names})
    except TypeError as exc:
        raise RecordingError(f"recorded device info is malformed: {exc}") from None


def _ns(seconds: float | None) -> int:
    """Nanoseconds of a time in seconds; 0 for None, non-finite or non-positive times."""
    return round(seconds * 1e9) if seconds is not None and math.isfinite(seconds) and seconds > 0 else 0


def _stamp(seconds: float) -> dict[str, int]:
    ns = _ns(seconds)
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _foxglove_calibration(intr: Intrinsics, stamp: dict[str, int]) -> dict[str, Any]:
    rational = any(getattr(intr, k) != 0.0 for k in ("k4", "k5", "k6"))
    d = [intr.k1, intr.k2, intr.p1, intr.p2, intr.k3] + ([intr.k4, intr.k5, intr.k6] if rational else [])
    return {"timestamp": stamp, "frame_id": CAMERA_FRAME_ID, "width": intr.width, "height": intr.height,
            "distortion_model": "rational_polynomial" if rational else "plumb_bob", "D": d,
            "K": intr.camera_matrix.ravel().tolist(), "R": np.eye(3).ravel().tolist(),
            "P": np.hstack([intr.camera_matrix, np.zeros((3, 1))]).ravel().tolist()}


def _foxglove_depth(frame: Frame) -> dict[str, Any]:
    h, w = frame.shape
    data = np.ascontiguousarray(frame.distance, dtype="<f4").tobytes()
    return {"timestamp": _stamp(frame.timestamp), "frame_id": CAMERA_FRAME_ID, "width": w, "height": h,
            "encoding": "32FC1", "step": 4 * w, "data": base64.b64encode(data).decode("ascii")}


def _foxglove_pose(pose: Pose, seconds: float) -> dict[str, Any]:
    x, y, z = (float(v) for v in pose.translation)
    qx, qy, qz, qw = (float(v) for v in pose.rotation.as_quat())
    return {"timestamp": _stamp(seconds), "frame_id": BASE_FRAME_ID,
            "pose": {"position": {"x": x, "y": y, "z": z}, "orientation": {"x": qx, "y": qy, "z": qz, "w": qw}}}


# ---------------------------------------------------------------------------- writing
class SessionRecorder:
    """Writes one session to an MCAP file; wrap the devices with :meth:`camera` and :meth:`arm`.

    The file is written under a temporary name in the destination directory and
    renamed to ``path`` by :meth:`close`; :meth:`abort` (and leaving the ``with``
    block on an exception) deletes it, so ``path`` never holds a partial recording.

    Args:
        path: Destination ``.mcap`` file.
        config_document: The cell configuration document (stored as JSON).
        config_source: Where the configuration came from (for humans).
        config_text: The configuration's TOML text, if available (for humans).
        keep_on_error: When leaving the ``with`` block on a :class:`CellcalError` that
            is not a :class:`RecordingError` (e.g. a device fault during the run), finish
            the file (with the error logged) instead of discarding it.
        compression: ``"zstd"`` (default), ``"lz4"`` or ``"none"`` for the MCAP chunks.

    Raises:
        MissingDependencyError: If ``mcap`` (extra ``record``) is not installed.
        RecordingError: If the file cannot be created.
    """

    def __init__(self, path: str | Path, *, config_document: Mapping[str, Any] | None = None,
                 config_source: str | None = None, config_text: str | None = None,
                 keep_on_error: bool = False, compression: str = "zstd") -> None:
        writer_mod, _ = _import_mcap()
        kinds = {"zstd": writer_mod.CompressionType.ZSTD, "lz4": writer_mod.CompressionType.LZ4,
                 "none": writer_mod.CompressionType.NONE}
        if compression not in kinds:
            raise RecordingError(f"compression must be one of {', '.join(kinds)}, got {compression!r}")
        self.path = Path(path)
        self.keep_on_error = keep_on_error
        self._lock = threading.RLock()
        self._event = 0
        self._result_logged = False
        self.message_counts: dict[str, int] = dict.fromkeys(CHANNELS, 0)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent)
        except OSError as exc:
            raise RecordingError(f"cannot write {self.path}: {exc.strerror or exc}") from None
        self._tmp: Path | None = Path(tmp)
        self._fh = os.fdopen(fd, "wb")
        try:
            self._writer = writer_mod.Writer(self._fh, compression=kinds[compression])
            cellcal_version = _package_version()
            self._writer.start(profile=MCAP_PROFILE, library=f"cellcal {cellcal_version}")
            schema_ids = {name: self._writer.register_schema(name=name, encoding="jsonschema",
                                                             data=json.dumps(schema).encode("utf-8"))
                          for name, schema in SCHEMAS.items()}
            self._channels = {topic: self._writer.register_channel(topic=topic, message_encoding="json",
                                                                   schema_id=schema_ids[schema])
                              for topic, schema in CHANNELS.items()}
            self._writer.add_metadata("cellcal", {"format": RECORDING_FORMAT, "cellcal_version": cellcal_version})
            self.log(TOPIC_SESSION, {
                "format": RECORDING_FORMAT, "cellcal_version": cellcal_version,
                "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                "config_source": config_source,
                "config": None if config_document is None else dict(config_document),
                "config_toml": config_text,
            })
        except BaseException:
            self.abort()
            raise

    # ------------------------------------------------------------ wrapping
    def camera(self, camera: Camera3D) -> RecordingCamera:
        """``camera`` behind a recording wrapper (drive its life cycle through the wrapper)."""
        return RecordingCamera(camera, self)

    def arm(self, arm: RobotArm) -> RecordingArm:
        """``arm`` behind a recording wrapper; put any :class:`SafeArm` *around* it."""
        return RecordingArm(arm, self)

    # ------------------------------------------------------------ logging
    @property
    def closed(self) -> bool:
        """Whether the file has been finished or discarded."""
        return self._tmp is None

    def next_event(self) -> int:
        """Reserve the next session-wide event number (the replay order)."""
        with self._lock:
            self._event += 1
            return self._event

    def log(self, topic: str, payload: Mapping[str, Any], *, event: int | None = None,
            publish_time_s: float | None = None) -> None:
        """Write one JSON message on ``topic`` (log time: now).

        Raises:
            RecordingError: If the recorder is closed or the write fails.
        """
        now = time.time_ns()
        publish = _ns(publish_time_s) or now
        with self._lock:
            if self._tmp is None:
                raise RecordingError(f"recorder for {self.path} is closed; nothing more can be logged")
            seq = self.next_event() if event is None else event
            data = _dumps({**payload, "event": seq} if "event" in SCHEMAS[CHANNELS[topic]]["properties"]
                          else payload)
            try:
                self._writer.add_message(channel_id=self._channels[topic], log_time=now, data=data,
                                         publish_time=publish, sequence=seq)
            except OSError as exc:
                raise RecordingError(f"cannot write {self.path}: {exc.strerror or exc}") from None
            self.message_counts[topic] += 1

    def log_result(self, document: Mapping[str, Any] | None, error: CellcalError | None = None) -> None:
        """Store the run's outcome: the calibration result document, or the error it ended with."""
        self.log(TOPIC_RESULT, {"ok": error is None, "result": None if document is None else dict(document),
                                "error": None if error is None else encode_error(error)})
        self._result_logged = True

    # ------------------------------------------------------------ finishing
    def close(self) -> Path:
        """Finish the file and move it to :attr:`path`; returns the path. Idempotent.

        Raises:
            RecordingError: If finishing or renaming fails (the temporary file is removed).
        """
        with self._lock:
            if self._tmp is None:
                return self.path
            try:
                self._writer.finish()
                self._fh.flush()
                os.fsync(self._fh.fileno())
                self._fh.close()
                umask = os.umask(0)
                os.umask(umask)
                os.chmod(self._tmp, 0o666 & ~umask)  # mkstemp made it private; give it normal permissions
                os.replace(self._tmp, self.path)
            except BaseException as exc:
                self.abort()
                if isinstance(exc, OSError):
                    raise RecordingError(f"cannot write {self.path}: {exc.strerror or exc}") from None
                raise
            self._tmp = None
        return self.path

    def abort(self) -> None:
        """Discard the recording: close and delete the temporary file. Idempotent."""
        with self._lock:
            tmp, self._tmp = self._tmp, None
            if tmp is None:
                return
            with contextlib.suppress(OSError):
                self._fh.close()
            tmp.unlink(missing_ok=True)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc is None:
            self.close()
        elif self.keep_on_error and isinstance(exc, CellcalError) and not isinstance(exc, RecordingError):
            try:
                if not self._result_logged:
                    self.log_result(None, exc)
                self.close()
            except BaseException:
                self.abort()
                raise
        else:
            self.abort()


class RecordingCamera(Camera3D):
    """A :class:`Camera3D` that forwards to ``inner`` and logs identity, intrinsics and every capture.

    Args:
        inner: The camera to record; its life cycle is driven through this wrapper.
        recorder: Where to log.
    """

    def __init__(self, inner: Camera3D, recorder: SessionRecorder) -> None:
        super().__init__()
        self.inner = inner
        self.recorder = recorder
        self.backend_name = inner.backend_name  # type: ignore[misc]
        self.default_timeout_s = inner.default_timeout_s
        self._captures = 0

    def _connect(self, timeout: float) -> None:
        self.inner.connect(timeout)
        info, intr = self.inner.info(), self.inner.intrinsics
        self.recorder.log(TOPIC_CAMERA_INFO, {**_info_payload(info), "intrinsics": intr.to_dict(),
                                              "default_timeout_s": self.inner.default_timeout_s})
        self.recorder.log(TOPIC_CAMERA_CALIBRATION, _foxglove_calibration(intr, _stamp(time.time())))

    def _close(self) -> None:
        self.inner.close()

    def _info(self) -> DeviceInfo:
        return self.inner.info()

    def _intrinsics(self) -> Intrinsics:
        return self.inner.intrinsics

    def _capture(self, timeout: float) -> Frame:
        index, started = self._captures, time.perf_counter()
        self._captures += 1
        record: dict[str, Any] = {"capture": index, "timeout_s": timeout}
        event = self.recorder.next_event()
        try:
            frame = self.inner.capture(timeout)
        except CellcalError as exc:
            self.recorder.log(TOPIC_CAPTURE, {**record, "duration_s": time.perf_counter() - started,
                                              "frame": None, "error": encode_error(exc)}, event=event)
            raise
        self.recorder.log(TOPIC_CAPTURE, {**record, "duration_s": time.perf_counter() - started,
                                          "frame": encode_frame(frame), "error": None},
                          event=event, publish_time_s=frame.timestamp)
        self.recorder.log(TOPIC_DEPTH, _foxglove_depth(frame), publish_time_s=frame.timestamp)
        return frame


def _encode_result(result: Any) -> Any:
    if isinstance(result, Pose):
        return encode_pose(result)
    if isinstance(result, ArmStatus):
        return asdict(result)
    if isinstance(result, np.ndarray):
        return [float(v) for v in result]
    return None


class RecordingArm(RobotArm):
    """A :class:`RobotArm` that forwards to ``inner`` and logs every call with arguments and result.

    Wrap the *backend* arm with it and put the :class:`~cellcal.devices.safety.SafeArm`
    around the wrapper, so the recording holds exactly what the backend was asked.

    Args:
        inner: The arm to record; its life cycle is driven through this wrapper.
        recorder: Where to log.
    """

    def __init__(self, inner: RobotArm, recorder: SessionRecorder) -> None:
        super().__init__()
        self.inner = inner
        self.recorder = recorder
        self.backend_name = inner.backend_name  # type: ignore[misc]
        self.default_timeout_s = inner.default_timeout_s
        self.default_motion_timeout_s = inner.default_motion_timeout_s
        self._calls = 0

    def _call(self, method: str, args: dict[str, Any], fn: Any) -> Any:
        index, started = self._calls, time.perf_counter()
        self._calls += 1
        event = self.recorder.next_event()
        record: dict[str, Any] = {"call": index, "method": method, "args": args}
        try:
            result = fn()
        except CellcalError as exc:
            self.recorder.log(TOPIC_ARM_CALL, {**record, "result": None, "error": encode_error(exc),
                                               "duration_s": time.perf_counter() - started}, event=event)
            raise
        self.recorder.log(TOPIC_ARM_CALL, {**record, "result": _encode_result(result), "error": None,
                                           "duration_s": time.perf_counter() - started}, event=event)
        if isinstance(result, Pose):
            self.recorder.log(TOPIC_FLANGE_POSE, _foxglove_pose(result, time.time()))
        return result

    def _connect(self, timeout: float) -> None:
        self.inner.connect(timeout)
        self.recorder.log(TOPIC_ARM_INFO, {**_info_payload(self.inner.info()), "intrinsics": None,
                                           "default_timeout_s": self.inner.default_timeout_s})

    def _close(self) -> None:
        self.inner.close()

    def _info(self) -> DeviceInfo:
        return self.inner.info()

    def _get_pose(self, timeout: float) -> Pose:
        pose: Pose = self._call("get_pose", {"timeout_s": timeout}, lambda: self.inner.get_pose(timeout))
        return pose

    def _move_linear(self, pose: Pose, speed: float, acceleration: float, timeout: float) -> None:
        args = {"target": encode_pose(pose), "speed_m_s": speed, "acceleration_m_s2": acceleration,
                "timeout_s": timeout}
        self._call("move_linear", args, lambda: self.inner.move_linear(
            pose, speed=speed, acceleration=acceleration, timeout=timeout))

    def _stop(self, timeout: float) -> None:
        self._call("stop", {"timeout_s": timeout}, lambda: self.inner.stop(timeout))

    def _joint_positions(self, timeout: float) -> NDArray[np.float64]:
        q: NDArray[np.float64] = self._call("joint_positions", {"timeout_s": timeout},
                                            lambda: self.inner.joint_positions(timeout))
        return q

    def _status(self, timeout: float) -> ArmStatus:
        status: ArmStatus = self._call("status", {"timeout_s": timeout}, lambda: self.inner.status(timeout))
        return status

    def _clear_errors(self, timeout: float) -> None:
        self._call("clear_errors", {"timeout_s": timeout}, lambda: self.inner.clear_errors(timeout))


# ---------------------------------------------------------------------------- reading
@dataclass
class Recording:
    """A parsed recording, in event order.

    Attributes:
        path: The file it was read from.
        session: The ``/cellcal/session`` payload (format, versions, config document).
        camera_infos: ``/camera/info`` payloads, one per connect.
        arm_infos: ``/arm/info`` payloads, one per connect.
        captures: ``/camera/capture`` payloads (``frame`` still encoded; see :func:`decode_frame`).
        arm_calls: ``/arm/call`` payloads.
        result: The last ``/cellcal/result`` payload, or None.
        message_counts: Messages per topic, as stored.
    """

    path: Path
    session: dict[str, Any]
    camera_infos: list[dict[str, Any]] = field(default_factory=list)
    arm_infos: list[dict[str, Any]] = field(default_factory=list)
    captures: list[dict[str, Any]] = field(default_factory=list)
    arm_calls: list[dict[str, Any]] = field(default_factory=list)
    result: dict[str, Any] | None = None
    message_counts: dict[str, int] = field(default_factory=dict)

    @property
    def config_document(self) -> dict[str, Any] | None:
        """The recorded configuration document, or None when none was recorded."""
        doc = self.session.get("config")
        return doc if isinstance(doc, dict) else None

    @property
    def config_source(self) -> str | None:
        """Where the recorded configuration came from."""
        src = self.session.get("config_source")
        return src if isinstance(src, str) else None


_TOPIC_LISTS = {TOPIC_CAMERA_INFO: "camera_infos", TOPIC_ARM_INFO: "arm_infos", TOPIC_CAPTURE: "captures",
                TOPIC_ARM_CALL: "arm_calls"}


def read_recording(path: str | Path) -> Recording:
    """Read and check a recording written by :class:`SessionRecorder`.

    Raises:
        MissingDependencyError: If ``mcap`` (extra ``record``) is not installed.
        RecordingFileError: If the file is missing, unreadable, not MCAP, truncated,
            corrupt (CRC), or not a cellcal recording of a supported format — one line
            naming the file.
    """
    _, reader_mod = _import_mcap()
    p = Path(path)
    source = str(p)
    if not p.is_file():
        raise RecordingFileError("recording not found" if not p.exists() else "not a file", source=source)
    by_topic: dict[str, list[tuple[int, dict[str, Any]]]] = {}
    try:
        fh = p.open("rb")
    except OSError as exc:
        raise RecordingFileError(f"cannot read: {exc.strerror or exc}", source=source) from None
    try:
        with fh:
            if fh.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
                raise RecordingFileError("not an MCAP file (it does not start with the MCAP magic bytes)",
                                         source=source)
            fh.seek(0)
            reader = reader_mod.make_reader(fh, validate_crcs=True)
            for _schema, channel, message in reader.iter_messages(log_time_order=False):
                payload = json.loads(message.data)
                if not isinstance(payload, dict):
                    raise ValueError(f"message on {channel.topic} is not a JSON object")
                by_topic.setdefault(channel.topic, []).append((int(message.sequence), payload))
    except RecordingFileError:
        raise
    except Exception as exc:  # mcap, zstd, json, struct, seek past the start ... all mean one thing here
        detail = str(exc).splitlines()[0][:200] if str(exc) else ""
        raise RecordingFileError(f"not a readable MCAP recording (truncated or corrupt?): "
                                 f"{type(exc).__name__}{': ' + detail if detail else ''}", source=source) from None
    sessions = by_topic.get(TOPIC_SESSION, [])
    if not sessions:
        raise RecordingFileError(f"MCAP file has no {TOPIC_SESSION} message: not a cellcal recording", source=source)
    session = sessions[0][1]
    if session.get("format") != RECORDING_FORMAT:
        raise RecordingFileError(f"recording format {session.get('format')!r} is not supported "
                                 f"(this cellcal reads {RECORDING_FORMAT!r})", source=source)
    rec = Recording(path=p, session=session,
                    message_counts={topic: len(msgs) for topic, msgs in by_topic.items()})
    for topic, attr in _TOPIC_LISTS.items():
        setattr(rec, attr, [payload for _, payload in sorted(by_topic.get(topic, []), key=lambda m: m[0])])
    results = sorted(by_topic.get(TOPIC_RESULT, []), key=lambda m: m[0])
    rec.result = results[-1][1] if results else None
    return rec
