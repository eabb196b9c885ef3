"""Tracking and monitoring as the service's activities: ``cellcal track`` and ``cellcal monitor`` inside the service.

Per cell, one tracking session (:class:`~cellcal.core.track.cell.CellTrack` over the cell's cameras, the
library's :class:`~cellcal.core.track.run.TrackRun` each, as ``cellcal track`` runs them: the arm read,
never moved) or one monitoring session (:class:`~cellcal.core.monitor.Monitor`, drift of the plane
against a baseline), each in one thread of its own (:mod:`.watch_sessions`). A session holds the cell
as a run does: the cell's lock ``OUT/<cell>/.cellcal.lock`` from its start to its end, so a run asked
meanwhile is refused (409), and a session asked while a run (or the other session) has the cell is
refused the same way. Nothing is paused: the cell does one thing at a time.

Its state (``starting``, ``running``, ``stopping``, then ``stopped`` or ``failed``), frames, the
current estimate with its intervals and the open changes are kept in an :class:`Activity` that the
session's thread updates (at most every :data:`SNAPSHOT_EVERY_S` of wall time, and at every change);
the faces read it. Events on the service's bus: ``track.state`` / ``monitor.state`` (the activity),
``track.change`` (a change detected, told apart, resolved), ``track.camera_failed``,
``monitor.drift`` (drift started or cleared) and one ``drift.<kind>`` per drift (``mount``, ``plane``
or ``mount_or_plane`` once the tracker has told the change apart; ``monitor`` when the monitor flags
drift), which the metrics count and the history keeps.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping
from typing import Any

from cellcal.core.service.activity import (
    ACTIVITIES,
    ACTIVITY_STATES,
    MAX_DURATION_S,
    MAX_FRAMES,
    SNAPSHOT_EVERY_S,
    STOP_WAIT_S,
    Activity,
    WatchOptions,
    idle_state,
    now_utc,
)
from cellcal.core.service.errors import BusyError, NotFoundError
from cellcal.core.service.hosts import CellHost, ServiceHost
from cellcal.core.service.watch_sessions import session_target

__all__ = ["ACTIVITIES", "ACTIVITY_STATES", "MAX_DURATION_S", "MAX_FRAMES", "SNAPSHOT_EVERY_S", "STOP_WAIT_S",
           "Activity", "WatchOptions", "Watches", "watch_values"]

class Watches:
    """The service's tracking and monitoring sessions: at most one per cell, the latest of each kind remembered.

    Args:
        service: The service (its cells, bus and metrics).
    """

    def __init__(self, service: ServiceHost) -> None:
        self.service = service
        self._latest: dict[tuple[str, str], Activity] = {}
        self._lock = threading.Lock()

    def _kind(self, kind: str) -> str:
        if kind not in ACTIVITIES:
            raise NotFoundError(f"no activity {kind!r} (activities: {', '.join(ACTIVITIES)})")
        return kind

    def latest(self, cell: str, kind: str) -> Activity | None:
        """The cell's latest session of ``kind`` (running or ended), or None."""
        self.service.cell(cell)
        with self._lock:
            return self._latest.get((cell, self._kind(kind)))

    def state(self, cell: str, kind: str) -> dict[str, Any]:
        """JSON form of the cell's latest session of ``kind`` (``idle`` before the first)."""
        found = self.latest(cell, kind)
        return idle_state(kind, cell) if found is None else found.to_dict()

    def start(self, cell: str, kind: str, options: Mapping[str, Any] | None = None) -> Activity:
        """Start a session of ``kind`` on ``cell`` in a thread of its own; the activity (``starting``).

        Raises:
            NotFoundError: Unknown cell, activity or camera.
            RequestError: Bad options.
            BusyError: The cell runs something already (a run, a session; or another process holds its lock).
        """
        if self.service.closed:
            raise BusyError("the service is shutting down")
        target = self.service.cell(cell)
        parsed = WatchOptions.from_dict(options)
        cameras = [parsed.camera] if parsed.camera is not None else list(target.configs)
        for name in cameras:
            target.camera_config(name)  # NotFoundError naming the cell's cameras
        activity = Activity(self._kind(kind), cell, cameras, parsed)
        lock = target.occupy(activity, f"{kind}ing")
        thread = threading.Thread(target=self._work, args=(activity, target, lock, session_target(kind)),
                                  name=f"cellcal-{kind}-{cell}", daemon=True)
        with self._lock:
            self._latest[(cell, kind)] = activity
        try:
            thread.start()
        except BaseException:
            target.vacate(activity, lock)
            with activity.lock:
                activity.state, activity.error = "failed", "its thread could not be started"
            activity.done.set()
            raise
        return activity

    def _work(self, activity: Activity, cell: CellHost, lock: Any, body: Any) -> None:
        """The session's thread: its body to its end; the cell freed before the end is shown."""
        error: str | None = None
        try:
            body(activity, cell, self.service, self.publish_state)
        except BaseException as exc:  # a device's failure or a bug: the session fails with one line
            error = str(exc).replace("\n", " ") or type(exc).__name__
            if not isinstance(exc, Exception):
                error = f"{type(exc).__name__}: {error}"
        finally:
            cell.vacate(activity, lock)
            with activity.lock:
                activity.state = "failed" if error is not None else "stopped"
                activity.error, activity.finished_utc = error, now_utc()
            activity.done.set()
            self.publish_state(activity)

    def publish_state(self, activity: Activity) -> None:
        """Publish ``<kind>.state`` with the session (without its estimates: its state, frames and changes)."""
        data = activity.summary()
        data["options"] = activity.options.to_dict()
        self.service.bus.publish(f"{activity.kind}.state", data)

    def stop(self, cell: str, kind: str, wait_s: float = STOP_WAIT_S) -> dict[str, Any]:
        """Ask the cell's session of ``kind`` to stop and wait for it (at most ``wait_s``); its state.

        Tracking stops before its next frame (its files written, as on Ctrl-C), monitoring after the frame in
        progress. A session still ``stopping`` after ``wait_s`` ends on its own within its device's deadline.

        Raises:
            NotFoundError: Unknown cell or activity. BusyError: No session of ``kind`` runs on the cell.
        """
        found = self.latest(cell, kind)
        if found is None or found.final:
            raise BusyError(f"cell {cell!r} is not {'tracking' if kind == 'track' else 'monitoring'}: nothing to stop")
        with found.lock:
            if not found.final:
                found.state = "stopping"
        found.request_stop()
        self.publish_state(found)
        found.done.wait(wait_s)
        return found.to_dict()

    def close(self, wait_s: float = STOP_WAIT_S) -> None:
        """Stop every session (the service is closing) and wait for them, at most ``wait_s`` in all."""
        with self._lock:
            running = [a for a in self._latest.values() if not a.final]
        for activity in running:
            activity.request_stop()
        deadline = time.monotonic() + wait_s
        for activity in running:
            activity.done.wait(max(0.0, deadline - time.monotonic()))


def watch_values(watches: Watches, cell: str, camera: str) -> dict[str, Any]:
    """A camera's tracking and monitoring values as the OPC UA face publishes them (no null).

    ``TrackState`` and ``MonitorState`` (:data:`ACTIVITY_STATES`), ``TrackFrames``, ``ChangeOpen``,
    ``DriftEvents`` (tracking and monitoring summed, this session of each) and ``LastDrift`` (one line).
    """
    values: dict[str, Any] = {"TrackState": "idle", "MonitorState": "idle", "TrackFrames": 0, "ChangeOpen": False,
                              "DriftEvents": 0, "LastDrift": ""}
    drift, last = 0, ("", "")
    for kind in ACTIVITIES:
        found = watches.latest(cell, kind)
        if found is None:
            continue
        with found.lock:
            values[f"{kind.capitalize()}State"] = found.state
            mine = found.cameras.get(camera)
            if mine is None:
                continue
            drift += int(mine["drift_events"])
            if mine["last_drift"] and str(mine.get("last_drift_utc", "")) >= last[0]:
                last = (str(mine.get("last_drift_utc", "")), str(mine["last_drift"]))
            if kind == "track":
                values["TrackFrames"], values["ChangeOpen"] = int(mine["frames"]), bool(mine["change_open"])
    values["DriftEvents"], values["LastDrift"] = drift, last[1]
    return values
