"""The bodies of the service's tracking and monitoring sessions (:mod:`.watch`), each on its session's thread.

Tracking runs :class:`~cellcal.core.track.cell.CellTrack` over one
:class:`~cellcal.core.track.run.TrackRun` per camera, exactly as ``cellcal track`` does (one camera
built by the cell's builder; several by :func:`~cellcal.core.calibration.build.build_cell`, one arm
read by all), with the arm behind :class:`~cellcal.core.track.run.ReadOnlyArm` (read, never moved).
Every device call is bounded by a :class:`~cellcal.devices.blocking.DeadlineGuard` (its own timeout +
:data:`GRACE_S`), and a stop is seen before the next capture, where :class:`WatchStopped` (a
``KeyboardInterrupt``) ends the session as Ctrl-C ends ``cellcal track``: every camera's files written.
Monitoring runs :class:`~cellcal.core.monitor.Monitor` (its own deadline guard) and stops through
:meth:`~cellcal.core.monitor.Monitor.request_stop`.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from cellcal.core.service.activity import Activity
from cellcal.core.service.errors import NotFoundError, RequestError
from cellcal.core.service.hosts import CellHost, ServiceHost
from cellcal.core.track.run import ReadOnlyArm
from cellcal.devices.blocking import DeadlineGuard
from cellcal.devices.errors import CellcalError, DeviceError
from cellcal.devices.forwarding import ForwardingCamera
from cellcal.devices.jsonsafe import json_safe

if TYPE_CHECKING:
    from cellcal.core.track.run import TrackProgress, TrackRun
    from cellcal.core.track.state import ChangeEvent
    from cellcal.devices.arm import RobotArm
    from cellcal.devices.camera import Camera3D
    from cellcal.devices.pose import Pose
    from cellcal.devices.types import Frame

__all__ = ["GRACE_S", "WatchStopped", "session_target"]

#: Seconds a device call may run beyond its own timeout before it is abandoned (as the monitor's).
GRACE_S = 2.0
#: Seconds a device's close() may take.
CLOSE_S = 3.0

Publish = Callable[["Activity"], None]


class WatchStopped(KeyboardInterrupt):
    """Raised before a capture once a stop was asked: the tracking loop ends as on Ctrl-C (its files written)."""


def _bounded_close(guard: DeadlineGuard, close: Callable[[], None]) -> None:
    with contextlib.suppress(CellcalError):
        guard.call(close, CLOSE_S - guard.grace_s, "close()")


class _BoundedCamera(ForwardingCamera):
    """A camera whose every call is under its deadline, and that stops the session before a capture."""

    def __init__(self, inner: Camera3D, stop: Any) -> None:
        super().__init__(inner)
        self.stop_requested = stop
        self.guard = DeadlineGuard(f"camera backend '{inner.backend_name}'", GRACE_S)

    def _connect(self, timeout: float) -> None:
        self.guard.call(lambda: self.inner.connect(timeout), timeout, f"connect(timeout={timeout:g} s)")

    def _capture(self, timeout: float) -> Frame:
        if self.stop_requested.is_set():
            raise WatchStopped
        return self.guard.call(lambda: self.inner.capture(timeout), timeout, f"capture(timeout={timeout:g} s)")

    def _close(self) -> None:
        _bounded_close(self.guard, self.inner.close)


class _BoundedArm(ReadOnlyArm):
    """The cell's arm read under its deadline; every command refused (:class:`ReadOnlyArm`)."""

    def __init__(self, inner: RobotArm) -> None:
        super().__init__(inner)
        self.guard = DeadlineGuard(f"arm backend '{inner.backend_name}'", GRACE_S)

    def _connect(self, timeout: float) -> None:
        self.guard.call(lambda: self.inner.connect(timeout), timeout, f"connect(timeout={timeout:g} s)")

    def _get_pose(self, timeout: float) -> Pose:
        return self.guard.call(lambda: self.inner.get_pose(timeout), timeout, f"get_pose(timeout={timeout:g} s)")

    def _close(self) -> None:
        _bounded_close(self.guard, self.inner.close)


def _drift_kind(event: ChangeEvent) -> str:
    """The metrics' kind of a told-apart change: ``mount``, ``plane`` or ``mount_or_plane``."""
    return event.kind.replace(" ", "_")


class _TrackFeed:
    """One camera's progress callback: frames counted, changes published, the estimate snapshotted."""

    def __init__(self, activity: Activity, name: str, service: ServiceHost, publish: Publish) -> None:
        self.activity, self.name, self.service, self.publish = activity, name, service, publish
        self.session: TrackRun | None = None
        self._stages: dict[float, str] = {}  # a change (its detection time) -> its last stage published
        self._counted: set[float] = set()  # the changes counted as drift
        self._next = 0.0

    def __call__(self, progress: TrackProgress) -> None:
        metrics = self.service.metrics
        if metrics is not None and progress.outcome in ("accepted", "held out"):
            metrics.fitted.labels(self.activity.cell, self.name).inc()
        elif metrics is not None and progress.outcome.startswith("refused: gate "):
            metrics.refused.labels(self.activity.cell, self.name, progress.outcome[len("refused: gate "):]).inc()
        with self.activity.lock:
            self.activity.cameras[self.name]["frames"] = progress.index + 1
        event = None if progress.step is None else progress.step.event
        if event is not None:
            self._change(event, progress.t_s)
        if event is not None or time.monotonic() >= self._next:
            self.snapshot()

    def snapshot(self) -> None:
        """The camera's current estimate, intervals and changes, as its ``track.json`` would hold them now."""
        from cellcal.core.track.result import fixed_track_document, track_document

        session = self.session
        if session is None:
            return
        self._next = time.monotonic() + 0.5
        counters = dict(session.counters)
        if session.fixed_pose is not None:
            doc = fixed_track_document(session.tracker, session.fixed_pose, counters, {})
        else:
            doc = track_document(session.tracker.state, counters, {})
        doc.pop("meta", None)
        doc = json_safe(doc)
        with self.activity.lock:
            mine = self.activity.cameras[self.name]
            mine["estimate"], mine["changes"], mine["change_open"] = doc, doc["events"], doc["change_unresolved"]

    def _change(self, event: ChangeEvent, t_s: float) -> None:
        from cellcal.core.track.detector import KIND_EITHER
        from cellcal.core.track.words import event_line

        session = self.session
        fixed = session is not None and session.fixed_pose is not None
        before = self._stages.get(event.detected_at_s)
        stage = "detected" if before is None else ("resolved" if event.resolved_at_s is not None else "told apart")
        self._stages[event.detected_at_s] = stage
        line = event_line(event, final=False, fixed=fixed)
        cell, name = self.activity.cell, self.name
        self.service.bus.publish("track.change", {"cell": cell, "camera": name, "stage": stage, "t_s": t_s,
                                                  "event": json_safe(event.to_dict()), "text": line})
        decided = before is not None or event.kind != KIND_EITHER or event.resolved_at_s is not None
        if decided and event.detected_at_s not in self._counted:  # once per change: when it is told apart
            self._counted.add(event.detected_at_s)
            with self.activity.lock:
                mine = self.activity.cameras[name]
                mine["drift_events"] += 1
                mine["last_drift"], mine["last_drift_utc"] = line, _utc()
            self.service.bus.publish(f"drift.{_drift_kind(event)}", {
                "cell": cell, "camera": name, "source": "track", "event": json_safe(event.to_dict()), "text": line})
        self.publish(self.activity)


def _utc() -> str:
    from datetime import UTC, datetime

    return datetime.now(UTC).isoformat(timespec="milliseconds")


def track_session(activity: Activity, cell: CellHost, service: ServiceHost, publish: Publish) -> None:
    """Track the activity's cameras until stopped, its duration or frames, or every camera failed.

    Raises:
        CellcalError: The arm failed, a file could not be written, or no camera could be connected.
    """
    from cellcal.core.track.cell import CameraTrack, CellTrack
    from cellcal.core.track.result import track_filenames
    from cellcal.core.track.run import TrackRun, device_clock

    names = list(activity.cameras)
    configs = {name: cell.camera_config(name) for name in names}
    if len(names) == 1:
        camera, arm = cell.builder(configs[names[0]])
        built = {names[0]: camera}
    else:
        from cellcal.core.calibration.build import build_cell

        built, arm = build_cell(configs[names[0]])  # one world, one arm read by every camera (cellcal track)
    reader = _BoundedArm(arm)
    with contextlib.ExitStack() as stack:
        stack.enter_context(reader)
        tracks, feeds = [], []
        for name in names:
            config = configs[name]
            entry = config.camera_entry
            camera = _BoundedCamera(built[name], activity.stop_requested)
            now = device_clock(built[name])  # the backend's own clock, before the wrapper hides it
            stack.enter_context(camera)
            fixed = entry.pose_base if entry.on == "base" else None
            feed = _TrackFeed(activity, name, service, publish)
            session = TrackRun(config, camera, reader, out_dir=cell.directory / name, now=now, on_progress=feed,
                               name=name if len(names) > 1 else None, fixed_pose=fixed,
                               filenames=track_filenames(None))
            feed.session = session
            feeds.append(feed)
            tracks.append(CameraTrack(name, entry.on, session))
            with activity.lock:
                activity.cameras[name]["place"] = entry.on
        _running(activity, publish)

        def failed(failure: Any) -> None:
            with activity.lock:
                activity.cameras[failure.name]["failed"] = failure.message
            service.bus.publish("track.camera_failed", {"cell": activity.cell, "camera": failure.name,
                                                        "t_s": failure.t_s, "message": failure.message})

        options = activity.options
        outcome = CellTrack(tracks, on_failure=failed).run(options.duration_s, options.max_frames)
    for feed in feeds:
        feed.snapshot()
    with activity.lock:
        activity.files = {name: [str(cell.directory / name / f) for f in files]
                          for name, files in outcome.files.items()}
    if len(outcome.failures) == len(names):
        raise DeviceError(f"every camera failed: {'; '.join(f'{f.name}: {f.message}' for f in outcome.failures)}")


def _running(activity: Activity, publish: Publish) -> None:
    with activity.lock:
        if activity.state == "starting":
            activity.state = "running"
    publish(activity)


def monitor_session(activity: Activity, cell: CellHost, service: ServiceHost, publish: Publish) -> None:
    """Monitor the activity's cameras for drift of the plane until stopped, its duration or frames.

    Raises:
        CellcalError: A camera that cannot be connected, too many failed frames in a row, or no calibration for a
            ``calibration`` baseline.
    """
    from cellcal.core.monitor import Monitor, MonitoredCamera

    specs = []
    for name in activity.cameras:
        config = cell.camera_config(name)
        camera, arm = cell.builder(config)
        baseline = _calibrated_baseline(cell, name, config, arm) if activity.options.baseline == "calibration" \
            else None
        specs.append(MonitoredCamera(name, camera, config.monitor, config.full_frame, baseline))
        with activity.lock:
            activity.cameras[name]["place"] = config.camera_entry.on
    feed = _MonitorFeed(activity, service, publish)
    monitor = Monitor(specs, feed)
    feed.monitor = monitor
    activity.stopper = monitor.request_stop
    if activity.stop_requested.is_set():
        return
    summary = monitor.run(activity.options.duration_s, activity.options.max_frames)
    feed.snapshot(force=True)
    del summary


def _calibrated_baseline(cell: CellHost, name: str, config: Any, arm: RobotArm) -> Any:
    """The camera's calibrated plane seen from the arm's pose read now (nothing moves): the monitor's baseline."""
    from cellcal.core.monitor import Baseline

    if config.camera_entry.on != "flange":
        raise RequestError(f"baseline 'calibration' needs a camera on the flange; {name!r} is fixed")
    calibration = cell.calibration(name)
    if calibration is None:
        raise NotFoundError(f"camera {name!r} has no calibration yet: no 'calibration' baseline (run calibrate)")
    reader = _BoundedArm(arm)
    t = config.monitor.connect_timeout_s
    with reader.connect(t):
        flange = reader.get_pose(t)
    model = calibration.model
    return Baseline.from_plane_in_base(model.plane, flange @ model.mount)


class _MonitorFeed:
    """The monitor's status callback: frames counted, drift published, the summary snapshotted; sees a stop."""

    def __init__(self, activity: Activity, service: ServiceHost, publish: Publish) -> None:
        self.activity, self.service, self.publish = activity, service, publish
        self.monitor: Any = None
        self._next = 0.0
        self._started = False

    def __call__(self, status: Any) -> None:
        if not self._started:
            self._started = True
            _running(self.activity, self.publish)
        if self.activity.stop_requested.is_set() and self.monitor is not None:
            self.monitor.request_stop()
        event = status.event
        if event is not None:
            self._drift(status.label, event)
        self.snapshot(force=event is not None)

    def snapshot(self, force: bool = False) -> None:
        if self.monitor is None or not (force or time.monotonic() >= self._next):
            return
        self._next = time.monotonic() + 0.5
        cameras = {c.label: json_safe(c.to_dict()) for c in self.monitor.summary().cameras}
        with self.activity.lock:
            for name, summary in cameras.items():
                mine = self.activity.cameras[name]
                mine["frames"], mine["estimate"] = summary["frames"], summary
                mine["change_open"] = summary["drifting"]

    def _drift(self, name: str, event: Any) -> None:
        data = json_safe(event.to_dict())
        started = event.kind == "drift_started"
        line = (f"{'drift started' if started else 'drift cleared'}"
                f"{' (' + ' and '.join(event.causes) + ')' if event.causes else ''}: tilt "
                f"{event.tilt_deviation_rad:.6f} rad (threshold {event.tilt_threshold_rad:.6f}), height "
                f"{event.height_deviation_m:.6f} m (threshold {event.height_threshold_m:.6f})")
        self.service.bus.publish("monitor.drift", {"cell": self.activity.cell, "camera": name, "event": data,
                                                   "text": line})
        if started:
            with self.activity.lock:
                mine = self.activity.cameras[name]
                mine["drift_events"] += 1
                mine["last_drift"], mine["last_drift_utc"] = line, _utc()
            self.service.bus.publish("drift.monitor", {"cell": self.activity.cell, "camera": name,
                                                       "source": "monitor", "event": data, "text": line})
        self.publish(self.activity)


def session_target(kind: str) -> Callable[[Activity, CellHost, ServiceHost, Publish], None]:
    """The body of a session of ``kind`` (``track`` or ``monitor``)."""
    return track_session if kind == "track" else monitor_session
