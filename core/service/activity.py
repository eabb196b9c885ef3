"""A cell's tracking or monitoring session as the faces see it: :class:`Activity` and what it may be asked
(:class:`WatchOptions`); the sessions themselves are :mod:`.watch` and :mod:`.watch_sessions`."""

from __future__ import annotations

import math
import threading
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from cellcal.core.service.errors import RequestError

__all__ = ["ACTIVITIES", "ACTIVITY_STATES", "MAX_DURATION_S", "MAX_FRAMES", "SNAPSHOT_EVERY_S", "STOP_WAIT_S",
           "Activity", "WatchOptions", "idle_state", "now_utc"]

#: The activities a cell can run besides its runs.
ACTIVITIES = ("track", "monitor")
#: An activity's states; the last two are final (``idle``: none started yet).
ACTIVITY_STATES = ("idle", "starting", "running", "stopping", "stopped", "failed")
#: Seconds of wall time between two snapshots of a session's estimate (and at every change).
SNAPSHOT_EVERY_S = 0.5
#: Seconds :meth:`Watches.stop` waits for a session to end (a device call in progress ends within its deadline).
STOP_WAIT_S = 15.0
#: Largest ``duration_s`` and ``max_frames`` a request may ask (a session without either runs until stopped).
MAX_DURATION_S = 30 * 86400.0
MAX_FRAMES = 10**9


def now_utc() -> str:
    """Now, ISO 8601 UTC to the millisecond."""
    return datetime.now(UTC).isoformat(timespec="milliseconds")


@dataclass(frozen=True)
class WatchOptions:
    """What a tracking or monitoring session may be asked.

    Attributes:
        camera: Track or monitor this camera only (None: every camera of the cell).
        duration_s: Stop after this many seconds (tracking: of frame time, as ``cellcal track --duration``;
            monitoring: of wall time, as ``cellcal monitor --duration``); None: until stopped.
        max_frames: Stop after this many frames (tracking: rounds of every camera); None: until stopped.
        baseline: Monitoring only: ``frames`` (the mean of the first frames, ``cellcal monitor``'s default) or
            ``calibration`` (the camera's current calibrated plane, seen from the arm's pose read at the start).
    """

    camera: str | None = None
    duration_s: float | None = None
    max_frames: int | None = None
    baseline: str = "frames"

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> WatchOptions:
        """From a request's body (None or {}: the defaults).

        Raises:
            RequestError: An unknown key or a value of the wrong type or out of range.
        """
        data = dict(data or {})
        unknown = sorted(set(data) - {"camera", "duration_s", "max_frames", "baseline"})
        if unknown:
            raise RequestError(f"unknown option {unknown[0]!r} (known: baseline, camera, duration_s, max_frames)")
        camera, duration, frames = data.get("camera"), data.get("duration_s"), data.get("max_frames")
        if camera is not None and (not isinstance(camera, str) or not camera):
            raise RequestError("camera must be a camera's name")
        if duration is not None and (isinstance(duration, bool) or not isinstance(duration, (int, float))
                                     or not math.isfinite(duration) or not 0 < duration <= MAX_DURATION_S):
            raise RequestError(f"duration_s must be a number of seconds in (0, {MAX_DURATION_S:g}]")
        if frames is not None and (isinstance(frames, bool) or not isinstance(frames, int)
                                   or not 1 <= frames <= MAX_FRAMES):
            raise RequestError(f"max_frames must be an integer from 1 to {MAX_FRAMES}")
        if data.get("baseline", "frames") not in ("frames", "calibration"):
            raise RequestError("baseline must be 'frames' or 'calibration'")
        return cls(camera, None if duration is None else float(duration), frames, data.get("baseline", "frames"))

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {"camera": self.camera, "duration_s": self.duration_s, "max_frames": self.max_frames,
                "baseline": self.baseline}


class Activity:
    """One tracking or monitoring session of a cell: where it stands and what it has seen (under ``lock``).

    Changed by its thread; read by anyone through :meth:`to_dict` and :meth:`summary`.

    Attributes:
        kind: ``track`` or ``monitor``.
        cell: The cell's name; cameras: the cameras it watches, in order.
        options: What was asked.
        state: One of :data:`ACTIVITY_STATES`.
        error: The one-line reason of a ``failed`` session.
        cameras: Per camera: ``frames``, ``place`` and the latest ``estimate`` (tracking: the ``track.json``
            document's figures; monitoring: the camera's summary), ``changes`` (tracking: the change events),
            ``change_open``, ``drift_events``, ``last_drift`` (one line), ``failed`` (one line or None).
        files: Tracking: the files written per camera at the end.
    """

    def __init__(self, kind: str, cell: str, cameras: list[str], options: WatchOptions) -> None:
        self.kind = kind
        self.cell = cell
        self.options = options
        self.id = uuid.uuid4().hex[:16]
        self.state = "starting"
        self.error: str | None = None
        self.created_utc = now_utc()
        self.finished_utc: str | None = None
        self.cameras: dict[str, dict[str, Any]] = {
            name: {"frames": 0, "place": None, "estimate": None, "changes": [], "change_open": False,
                   "drift_events": 0, "last_drift": "", "failed": None} for name in cameras}
        self.files: dict[str, list[str]] = {}
        self.lock = threading.Lock()
        self.stop_requested = threading.Event()
        #: Called (any thread) after ``stop_requested`` is set, when the session needs telling (a monitor).
        self.stopper: Callable[[], None] | None = None
        self.done = threading.Event()

    def request_stop(self) -> None:
        """Ask the session to stop (tracking: before its next capture; monitoring: after its frame)."""
        self.stop_requested.set()
        stopper = self.stopper
        if stopper is not None:
            stopper()

    @property
    def final(self) -> bool:
        """Whether the session has ended (stopped or failed)."""
        return self.state in ACTIVITY_STATES[-2:]

    def to_dict(self) -> dict[str, Any]:
        """JSON form: the session, and per camera its frames, estimate, changes and drift."""
        with self.lock:
            return {"id": self.id, "kind": self.kind, "cell": self.cell, "state": self.state, "error": self.error,
                    "options": self.options.to_dict(), "created_utc": self.created_utc,
                    "finished_utc": self.finished_utc, "stop_requested": self.stop_requested.is_set(),
                    "cameras": {name: {**values, "changes": list(values["changes"])}
                                for name, values in self.cameras.items()},
                    "files": dict(self.files)}

    def summary(self) -> dict[str, Any]:
        """The session in short, with no null (XML-RPC): state, frames, open changes and drift, summed over cameras."""
        with self.lock:
            cams = self.cameras.values()
            last = next((c["last_drift"] for c in reversed(list(cams)) if c["last_drift"]), "")
            return {"id": self.id, "kind": self.kind, "cell": self.cell, "state": self.state,
                    "error": self.error or "", "frames": sum(int(c["frames"]) for c in cams),
                    "change_open": any(c["change_open"] for c in cams),
                    "drift_events": sum(int(c["drift_events"]) for c in cams), "last_drift": last,
                    "cameras": sorted(self.cameras)}


def idle_state(kind: str, cell: str) -> dict[str, Any]:
    return {"id": "", "kind": kind, "cell": cell, "state": "idle", "error": None, "options": None,
            "created_utc": None, "finished_utc": None, "stop_requested": False, "cameras": {}, "files": {}}
