"""The ``replay`` arm: answers from a recorded session and checks every move against it (ADR 0009)."""

from __future__ import annotations

import dataclasses
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.arm import RobotArm
from cellcal.devices.arm_model import UNSTATED_ARM_MODEL, ArmModel
from cellcal.devices.base import BackendContext
from cellcal.devices.errors import RecordingFileError, ReplayExhaustedError, ReplayMismatchError
from cellcal.devices.pose import Pose
from cellcal.devices.recording import decode_error, decode_info, decode_pose
from cellcal.devices.safety import format_pose
from cellcal.devices.types import ArmStatus, DeviceInfo

from .state import decoded, load_recording, replay_state

T = TypeVar("T")


@dataclass(frozen=True)
class ReplayArmConfig:
    """Config of the ``replay`` arm backend."""

    file: str = field(metadata={"doc": "recorded session (.mcap); relative to the config file's directory"})
    strict: bool = field(default=True, metadata={"doc": "calls must come in the recorded order"})
    position_tolerance_m: float = field(default=1e-6, metadata={"ge": 0.0, "le": 0.1,
                                                                "doc": "max distance commanded vs recorded target, m"})
    angle_tolerance_rad: float = field(default=1e-6, metadata={"ge": 0.0, "le": 0.1,
                                                               "doc": "max angle commanded vs recorded target, rad"})


class ReplayArm(RobotArm):
    """Arm that answers from a recorded session and checks every move against it.

    Queries (``get_pose``, ``status``, ``joint_positions`` ...) get the recorded results.
    Every ``move_linear`` must match the recorded command (target within
    ``position_tolerance_m`` / ``angle_tolerance_rad``, same speed and acceleration), or
    it raises :class:`ReplayMismatchError` naming the move: it never answers with data
    from another pose. With ``strict = true`` (default) the calls must come in the
    recorded order; with ``strict = false`` only the moves must, and queries are answered
    from the recorded calls made after the same move.

    Config (``[arm]`` table): ``backend = "replay"``, ``file = "session.mcap"`` and the
    keys of :class:`ReplayArmConfig`.
    """

    backend_name = "replay"
    Config = ReplayArmConfig
    verifies_arrival = False  # moves nothing; the recorded arm checked each arrival (ADR 0016)

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
        infos = self.recording.arm_infos
        # what the recorded arm stated (issue #39), its source kept: a replay reproduces the run's result
        recorded = infos[0].get("arm_model") if infos else None
        self._model = UNSTATED_ARM_MODEL if recorded is None else decoded(self.recording, lambda: dataclasses.replace(
            ArmModel.from_dict({k: v for k, v in recorded.items() if k != "source"}, where="arm_info.arm_model"),
            source=str(recorded.get("source", "unstated"))[:64]))

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
        return decoded(self.recording, lambda: decode(record.get("result")))

    # ------------------------------------------------------------ backend hooks
    def _connect(self, timeout: float) -> None:
        # nothing to open (the file was read when the backend was built): check it has an arm
        if not self.recording.arm_infos:
            raise RecordingFileError("the recording has no arm (it was not connected while recording)",
                                     source=str(self.recording.path))
        first = self.recording.arm_infos[0]
        self._device_info = decoded(self.recording, lambda: decode_info(first))
        self.state.moves = self._moves

    def _close(self) -> None:
        self.state.moves = None

    def _arm_model(self) -> ArmModel:
        """What the recorded arm stated (the recording's arm info), else unstated (an older recording)."""
        return self._model

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
        target = decoded(self.recording, lambda: decode_pose(args.get("target") or {}))
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
