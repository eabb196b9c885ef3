"""``replay`` camera and arm backends: play back a session recorded to MCAP.

A recording made by :class:`cellcal.devices.recording.SessionRecorder` (``cellcal
record``) holds every frame and every arm call of a session. These backends answer
the same calls from it, so a calibration recorded on a real cell re-runs anywhere,
bit-exactly:

* :class:`ReplayCamera` returns the recorded captures in order — the exact frames,
  or the recorded error of a failed capture — with the recorded device info and
  intrinsics. Asking for more captures than were recorded raises
  :class:`~cellcal.devices.recording.ReplayExhaustedError`.
* :class:`ReplayArm` answers ``get_pose``, ``status``, ``joint_positions`` ... with
  the recorded results and checks every ``move_linear`` against the recorded command
  (target within ``position_tolerance_m`` / ``angle_tolerance_rad``, same speed and
  acceleration). A different plan raises
  :class:`~cellcal.devices.recording.ReplayMismatchError` naming the move; it never
  answers with data from another pose. With ``strict = true`` (default) the calls
  must come in the recorded order; with ``strict = false`` only the moves must, and
  queries are answered from the recorded calls made after the same move.

Config (``[camera]`` / ``[arm]`` tables)::

    backend = "replay"
    file = "session.mcap"     # relative to the configuration file's directory

Both backends built from one configuration share one parsed recording.
"""

from __future__ import annotations

import bisect
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.arm import RobotArm
from cellcal.devices.base import BackendContext
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import RecordingError, RecordingFileError, ReplayExhaustedError, ReplayMismatchError
from cellcal.devices.pose import Pose
from cellcal.devices.recording import Recording, decode_error, decode_frame, decode_info, decode_pose, read_recording
from cellcal.devices.safety import format_pose
from cellcal.devices.types import ArmStatus, DeviceInfo, Frame, Intrinsics

T = TypeVar("T")

#: Key of the parsed recordings in :attr:`BackendContext.shared`.
SHARED_KEY = "replay.recordings"
SHARED_STATE_KEY = "replay.state"


@dataclass(frozen=True)
class ReplayCameraConfig:
    """Config of the ``replay`` camera backend."""

    file: str = field(metadata={"doc": "recorded session (.mcap); relative to the config file's directory"})


@dataclass(frozen=True)
class ReplayArmConfig:
    """Config of the ``replay`` arm backend."""

    file: str = field(metadata={"doc": "recorded session (.mcap); relative to the config file's directory"})
    strict: bool = field(default=True, metadata={"doc": "calls must come in the recorded order"})
    position_tolerance_m: float = field(default=1e-6, metadata={"ge": 0.0, "le": 0.1,
                                                                "doc": "max distance commanded vs recorded target, m"})
    angle_tolerance_rad: float = field(default=1e-6, metadata={"ge": 0.0, "le": 0.1,
                                                               "doc": "max angle commanded vs recorded target, rad"})


class ReplayState:
    """What the replay backends of one recording share: the arm's progress through the moves.

    The camera checks against it that each frame is replayed after as many moves as it
    was recorded after, so a plan that captures more or fewer frames per pose fails
    at the first misplaced frame instead of measuring a frame from another pose.

    Attributes:
        moves: Moves replayed by a connected :class:`ReplayArm`, or None without one.
    """

    def __init__(self) -> None:
        self.moves: int | None = None


def replay_state(recording: Recording, context: BackendContext | None) -> ReplayState:
    """The :class:`ReplayState` of ``recording`` shared through ``context`` (a private one without)."""
    if context is None:
        return ReplayState()
    states: dict[str, ReplayState] = context.shared.setdefault(SHARED_STATE_KEY, {})
    return states.setdefault(str(recording.path), ReplayState())


def load_recording(file: str, context: BackendContext | None) -> Recording:
    """The parsed recording ``file`` (resolved from the config's directory), shared per context.

    Raises:
        RecordingFileError: If the file is missing, unreadable or not a cellcal recording.
    """
    path = Path(file)
    if not path.is_absolute():
        path = (context.base_dir if context is not None else Path.cwd()) / path
    path = path.resolve()
    cache: dict[str, Recording] = context.shared.setdefault(SHARED_KEY, {}) if context is not None else {}
    if str(path) not in cache:
        cache[str(path)] = read_recording(path)
    return cache[str(path)]


def _decoded(recording: Recording, fn: Callable[[], T]) -> T:
    """Run a decoder; a malformed entry is a corrupt file (one line naming it)."""
    try:
        return fn()
    except RecordingFileError:
        raise
    except RecordingError as exc:
        raise RecordingFileError(str(exc), source=str(recording.path)) from None
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise RecordingFileError(f"recorded entry is malformed: {type(exc).__name__}: {exc}",
                                 source=str(recording.path)) from None


class ReplayCamera(Camera3D):
    """Camera that returns the frames of a recorded session, in order.

    The capture position carries over a close/connect (a recording of a reconnect
    replays as one stream); :meth:`rewind` starts over.
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
        self._device_info = _decoded(self.recording, lambda: decode_info(first))
        self._intr = _decoded(self.recording, lambda: Intrinsics(**first["intrinsics"]))

    def _close(self) -> None:
        pass

    def _info(self) -> DeviceInfo:
        assert self._device_info is not None  # set by _connect
        return self._device_info

    def _intrinsics(self) -> Intrinsics:
        assert self._intr is not None  # set by _connect
        return self._intr

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
        return _decoded(self.recording, lambda: decode_frame(record["frame"]))


class ReplayArm(RobotArm):
    """Arm that answers from a recorded session and checks every move against it."""

    backend_name = "replay"
    Config = ReplayArmConfig

    def __init__(self, config: ReplayArmConfig, context: BackendContext | None = None) -> None:
        super().__init__()
        self.config = config
        self.recording = load_recording(config.file, context)
        self.state = replay_state(self.recording, context)
        self._device_info: DeviceInfo | None = None
        self._calls: list[dict[str, Any]] = self.recording.arm_calls
        self._lock = threading.Lock()
        self._cursor = 0  # strict: next call; lenient: first call after the last replayed move
        self._moves = 0

    @property
    def name(self) -> str:
        """Short name for messages."""
        return f"replay {self.recording.path.name}"

    def rewind(self) -> None:
        """Start the replay over from the first recorded call."""
        with self._lock:
            self._cursor = 0
            self._moves = 0
            if self.state.moves is not None:
                self.state.moves = 0

    # ------------------------------------------------------------ matching
    def _take(self, method: str) -> dict[str, Any] | None:
        """The recorded call that answers this ``method`` call (None: a lenient no-op)."""
        with self._lock:
            if self.config.strict:
                return self._take_strict(method)
            return self._take_lenient(method)

    def _take_strict(self, method: str) -> dict[str, Any]:
        i = self._cursor
        if i >= len(self._calls):
            raise ReplayExhaustedError(f"{self.name}: arm call {i + 1} ({method}) asked for, but the recording "
                                       f"ends after {len(self._calls)} arm calls")
        recorded = self._calls[i].get("method")
        if recorded != method:
            raise ReplayMismatchError(f"{self.name}: arm call {i + 1} is {method}, but the recorded session "
                                      f"called {recorded} there (the program or plan differs from the recording)")
        self._cursor += 1
        return self._calls[i]

    def _take_lenient(self, method: str) -> dict[str, Any] | None:
        calls: list[dict[str, Any]] = self._calls
        start = self._cursor
        if method == "move_linear":
            for i in range(start, len(calls)):
                if calls[i].get("method") == method:
                    self._cursor = i + 1
                    return calls[i]
            raise ReplayExhaustedError(f"{self.name}: move {self._moves + 1} asked for, but the recording "
                                       f"holds only {self._moves} moves after this point")
        end = next((i for i in range(start, len(calls)) if calls[i].get("method") == "move_linear"), len(calls))
        order = list(range(start, end)) + list(range(start - 1, -1, -1))  # after the last move, else before it
        for i in order:
            if calls[i].get("method") == method:
                return calls[i]
        if method in ("stop", "clear_errors"):
            return None
        raise ReplayMismatchError(f"{self.name}: {method} asked for, but the recording holds no {method} call")

    def _replay(self, method: str, decode: Callable[[Any], T]) -> T | None:
        record = self._take(method)
        if record is None:
            return None
        if record.get("error"):
            raise decode_error(record["error"])
        return _decoded(self.recording, lambda: decode(record.get("result")))

    # ------------------------------------------------------------ backend hooks
    def _connect(self, timeout: float) -> None:
        # nothing to open (the file was read when the backend was built): check it has an arm
        if not self.recording.arm_infos:
            raise RecordingFileError("the recording has no arm (it was not connected while recording)",
                                     source=str(self.recording.path))
        first = self.recording.arm_infos[0]
        self._device_info = _decoded(self.recording, lambda: decode_info(first))
        self.state.moves = self._moves

    def _close(self) -> None:
        self.state.moves = None

    def _info(self) -> DeviceInfo:
        assert self._device_info is not None  # set by _connect
        return self._device_info

    def _get_pose(self, timeout: float) -> Pose:
        pose = self._replay("get_pose", decode_pose)
        assert pose is not None  # only stop/clear_errors may be lenient no-ops
        return pose

    def _move_linear(self, pose: Pose, speed: float, acceleration: float, timeout: float) -> None:
        record = self._take("move_linear")
        assert record is not None
        self._moves += 1
        self.state.moves = self._moves
        args = record.get("args") or {}
        target = _decoded(self.recording, lambda: decode_pose(args.get("target") or {}))
        d, a = pose.distance_to(target), pose.angle_to(target)
        if d > self.config.position_tolerance_m or a > self.config.angle_tolerance_rad:
            raise ReplayMismatchError(
                f"{self.name}: move {self._moves} goes to {format_pose(pose)}, but the recorded session moved to "
                f"{format_pose(target)} ({d * 1e3:.3f} mm, {math.degrees(a):.4f} deg apart): the plan differs "
                "from the recording")
        for what, value, unit in (("speed_m_s", speed, "m/s"), ("acceleration_m_s2", acceleration, "m/s^2")):
            recorded = args.get(what)
            if not isinstance(recorded, (int, float)) or not math.isclose(value, recorded, rel_tol=1e-9):
                raise ReplayMismatchError(f"{self.name}: move {self._moves} at {what.split('_')[0]} {value:.6g} "
                                          f"{unit}, but the recorded session used {recorded!r}: the plan differs "
                                          "from the recording")
        if record.get("error"):
            raise decode_error(record["error"])

    def _stop(self, timeout: float) -> None:
        self._replay("stop", lambda _: None)

    def _joint_positions(self, timeout: float) -> NDArray[np.float64]:
        q = self._replay("joint_positions", lambda r: np.asarray(r, dtype=np.float64))
        assert q is not None
        return q

    def _status(self, timeout: float) -> ArmStatus:
        status = self._replay("status", lambda r: ArmStatus(**r))
        assert status is not None
        return status

    def _clear_errors(self, timeout: float) -> None:
        self._replay("clear_errors", lambda _: None)
