"""What the replay backends of one recording share: the parsed file and the arm's progress through the moves."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from cellcal.devices.base import BackendContext
from cellcal.devices.errors import RecordingError, RecordingFileError
from cellcal.devices.recording import Recording, read_recording

T = TypeVar("T")

#: Key of the parsed recordings in :attr:`BackendContext.shared`.
SHARED_KEY = "replay.recordings"
#: Key of the :class:`ReplayState` of each recording in :attr:`BackendContext.shared`.
SHARED_STATE_KEY = "replay.state"


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


def decoded(recording: Recording, fn: Callable[[], T]) -> T:
    """Run a decoder; a malformed entry is a corrupt file (one line naming it).

    Raises:
        RecordingFileError: Naming the recording, for any error of the decoder.
    """
    try:
        return fn()
    except RecordingFileError:
        raise
    except RecordingError as exc:
        raise RecordingFileError(str(exc), source=str(recording.path)) from None
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise RecordingFileError(f"recorded entry is malformed: {type(exc).__name__}: {exc}",
                                 source=str(recording.path)) from None
