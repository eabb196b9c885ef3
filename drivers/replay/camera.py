"""The ``replay`` camera: the frames of a recorded session, in order (ADR 0009)."""

from __future__ import annotations

import bisect
import threading
from dataclasses import dataclass, field

from cellcal.devices.base import BackendContext
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import RecordingFileError, ReplayExhaustedError, ReplayMismatchError
from cellcal.devices.measurement import UNKNOWN_MODEL, MeasurementModel
from cellcal.devices.recording import decode_error, decode_frame, decode_info, decode_model
from cellcal.devices.types import DeviceInfo, Frame, Intrinsics

from .state import decoded, load_recording, replay_state


@dataclass(frozen=True)
class ReplayCameraConfig:
    """Config of the ``replay`` camera backend."""

    file: str = field(metadata={"doc": "recorded session (.mcap); relative to the config file's directory"})


class ReplayCamera(Camera3D):
    """Camera that returns the frames of a recorded session, in order.

    Each capture is the exact recorded frame, or the recorded error of a failed capture,
    with the recorded device info and intrinsics. Asking for more captures than were
    recorded raises :class:`ReplayExhaustedError`; asking for a frame after another
    number of moves than it was recorded after raises :class:`ReplayMismatchError`.
    The capture position carries over a close/connect (a recording of a reconnect
    replays as one stream); :meth:`rewind` starts over.

    The camera states the measurement model the recorded camera stated at its first
    connect, with the source it had (the device, the backend, a ``[camera.model]``
    table: a replay is that camera again; ADR 0032), and each replayed frame carries
    the model it was recorded with. A recording of format 1 (none recorded) replays as
    ``unknown``; a malformed recorded model is a :class:`RecordingFileError` naming the
    file and the key, raised when the backend is built.

    Config (``[camera]`` table): ``backend = "replay"``, ``file = "session.mcap"``
    (relative to the configuration file's directory).
    """

    backend_name = "replay"
    Config = ReplayCameraConfig

    def __init__(self, config: ReplayCameraConfig, context: BackendContext | None = None) -> None:
        super().__init__()
        self.config = config
        self.recording = load_recording(config.file, context)
        self.state = replay_state(self.recording, context)
        self._lock = threading.Lock()
        self._next = 0
        self._device_info: DeviceInfo | None = None
        self._intr: Intrinsics | None = None
        events = sorted(int(c.get("event", 0)) for c in self.recording.arm_calls if c.get("method") == "move_linear")
        #: Moves recorded before each capture.
        self._moves_before = [bisect.bisect_left(events, int(c.get("event", 0))) for c in self.recording.captures]
        infos = self.recording.camera_infos
        recorded = infos[0].get("measurement_model") if infos else None
        self._model = (UNKNOWN_MODEL if recorded is None else
                       decoded(self.recording, lambda: decode_model(recorded, "camera_info.measurement_model")))

    @property
    def remaining(self) -> int:
        """Captures left to replay."""
        return len(self.recording.captures) - self._next

    def rewind(self) -> None:
        """Start the replay over from the first recorded capture."""
        with self._lock:
            self._next = 0

    def _connect(self, timeout: float) -> None:
        # nothing to open (the file was read when the backend was built): check it has a camera
        if not self.recording.camera_infos:
            raise RecordingFileError("the recording has no camera (it was not connected while recording)",
                                     source=str(self.recording.path))
        first = self.recording.camera_infos[0]
        self._device_info = decoded(self.recording, lambda: decode_info(first))
        self._intr = decoded(self.recording, lambda: Intrinsics(**first["intrinsics"]))

    def _close(self) -> None:
        pass

    def _measurement_model(self) -> MeasurementModel:
        return self._model

    def _info(self) -> DeviceInfo:
        assert self._device_info is not None  # set by _connect
        return self._device_info

    def _intrinsics(self) -> Intrinsics:
        assert self._intr is not None  # set by _connect
        return self._intr

    def _configured_intrinsics(self) -> Intrinsics | None:
        infos = self.recording.camera_infos       # what the recorded camera stated at its first connect
        if not infos:
            return None
        return decoded(self.recording, lambda: Intrinsics(**infos[0]["intrinsics"]))

    def _capture(self, timeout: float) -> Frame:
        with self._lock:
            index = self._next
            if index >= len(self.recording.captures):
                raise ReplayExhaustedError(
                    f"replay {self.recording.path.name}: capture {index + 1} asked for, but the recording "
                    f"holds only {len(self.recording.captures)} captures")
            moves = self.state.moves
            if moves is not None and moves != self._moves_before[index]:
                raise ReplayMismatchError(
                    f"replay {self.recording.path.name}: capture {index + 1} was recorded after move "
                    f"{self._moves_before[index]}, but is asked for after move {moves} (the plan captures "
                    "differently from the recording)")
            self._next += 1
        record = self.recording.captures[index]
        if record.get("error"):
            raise decode_error(record["error"])
        return decoded(self.recording, lambda: decode_frame(record["frame"]))
