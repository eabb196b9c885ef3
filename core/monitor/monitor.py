"""The live drift monitor: capture from cameras, fit the plane per frame, feed one detector each.

Runs in the caller's thread (:meth:`Monitor.run`) or in one background thread
(:meth:`Monitor.start` / :meth:`Monitor.stop`); cameras are always closed on the way
out. Detection rule and design: ADR 0013.
"""

from __future__ import annotations

import contextlib
import functools
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from cellcal.core.calibration.sections import MonitorSection
from cellcal.core.methods.fullframe import FullFrameSettings
from cellcal.core.monitor.detector import DetectorStatus, DriftDetector, DriftEvent, Phase
from cellcal.core.monitor.samples import Baseline, PlaneSample, plane_sample
from cellcal.devices.blocking import DeadlineGuard
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import (
    BackendOverrunError,
    CalibrationError,
    CellcalError,
    ConfigError,
    DeviceTimeoutError,
    MonitorError,
)
from cellcal.devices.types import Frame

__all__ = ["CameraSummary", "FrameFit", "Monitor", "MonitorStatus", "MonitorSummary", "MonitoredCamera",
           "StatusCallback"]


@dataclass
class MonitoredCamera:
    """One camera under watch.

    Attributes:
        label: Name used in statuses and events (unique within a monitor).
        camera: The camera (connected by the monitor if it is not already; always
            closed by it).
        settings: Monitor settings (``[monitor]``).
        fit_settings: Full-frame fit settings (``[full_frame]``); None: defaults.
        baseline: Expected plane; None measures it from the first frames.
    """

    label: str
    camera: Camera3D
    settings: MonitorSection = field(default_factory=MonitorSection)
    fit_settings: FullFrameSettings | None = None
    baseline: Baseline | None = None


@dataclass(frozen=True)
class MonitorStatus:
    """One frame of one camera.

    Attributes:
        label: The camera's label.
        index: 0-based number of this capture attempt for this camera.
        detector: The detector's verdict, or None when the capture or the fit failed.
        error: One-line reason of a failed capture or fit, else None.
    """

    label: str
    index: int
    detector: DetectorStatus | None
    error: str | None = None

    @property
    def phase(self) -> Phase | None:
        """The detector's phase (None on a failed frame)."""
        return None if self.detector is None else self.detector.phase

    @property
    def event(self) -> DriftEvent | None:
        """The event this frame caused, if any."""
        return None if self.detector is None else self.detector.event


@dataclass
class CameraSummary:
    """What happened to one camera during a run.

    Attributes:
        label: The camera's label.
        frames: Frames fitted and fed to the detector.
        errors: Captures or fits that failed (timeouts, quality gates).
        events: Drift events, in order.
        drifting: Whether drift was flagged when the run ended.
        baseline: The baseline in use (None if it was never established).
        tilt_threshold_rad: Effective tilt threshold, rad (None without baseline).
        height_threshold_m: Effective height threshold, m (None without baseline).
        max_tilt_deviation_rad: Largest per-frame tilt deviation after the baseline, rad.
        max_height_deviation_m: Largest per-frame height deviation after the baseline, m.
    """

    label: str
    frames: int = 0
    errors: int = 0
    events: list[DriftEvent] = field(default_factory=list)
    drifting: bool = False
    baseline: Baseline | None = None
    tilt_threshold_rad: float | None = None
    height_threshold_m: float | None = None
    max_tilt_deviation_rad: float = 0.0
    max_height_deviation_m: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """JSON form (SI units)."""
        return {"label": self.label, "frames": self.frames, "errors": self.errors, "drifting": self.drifting,
                "events": [e.to_dict() for e in self.events],
                "baseline": None if self.baseline is None else self.baseline.to_dict(),
                "tilt_threshold_rad": self.tilt_threshold_rad, "height_threshold_m": self.height_threshold_m,
                "max_tilt_deviation_rad": self.max_tilt_deviation_rad,
                "max_height_deviation_m": self.max_height_deviation_m}


@dataclass
class MonitorSummary:
    """The outcome of :meth:`Monitor.run`.

    Attributes:
        cameras: One summary per camera, in the monitor's order.
        interrupted: Whether the run ended on Ctrl-C (KeyboardInterrupt).
        elapsed_s: Wall time of the run, seconds.
    """

    cameras: list[CameraSummary]
    interrupted: bool = False
    elapsed_s: float = 0.0

    @property
    def drift_detected(self) -> bool:
        """Whether any camera flagged drift at any time during the run."""
        return any(e.kind == "drift_started" for c in self.cameras for e in c.events)


StatusCallback = Callable[[MonitorStatus], None]
FrameFit = Callable[[Frame, FullFrameSettings | None], PlaneSample]


#: Seconds a camera call may run beyond its own timeout before the monitor gives up on the camera.
MONITOR_GRACE_S = 2.0
#: Seconds a camera's close() may take (it has no timeout) before it is abandoned.
CLOSE_ALLOWANCE_S = 3.0


def _close(guard: DeadlineGuard, camera: Camera3D) -> None:
    """Close ``camera``, abandoning a close() that hangs (raising here would hide why the run ended)."""
    with contextlib.suppress(CellcalError):
        guard.call(camera.close, CLOSE_ALLOWANCE_S - guard.grace_s, "close()")


class _Watch:
    """Run-time state of one camera."""

    def __init__(self, spec: MonitoredCamera) -> None:
        self.spec = spec
        self.detector = DriftDetector(spec.settings, spec.baseline, spec.label)
        self.summary = CameraSummary(spec.label)
        self.index = 0
        self.consecutive_errors = 0
        self.next_due = 0.0
        #: Bounds every call into the camera's backend: its timeout + MONITOR_GRACE_S (ADR 0022).
        self.guard = DeadlineGuard(f"camera backend '{spec.camera.backend_name}' ({spec.label})", MONITOR_GRACE_S)

    def refresh(self) -> None:
        d, s = self.detector, self.summary
        s.events = list(d.events)
        s.drifting = d.drifting
        s.baseline = d.baseline
        s.tilt_threshold_rad = d.tilt_threshold_rad
        s.height_threshold_m = d.height_threshold_m


class Monitor:
    """Watches cameras for drift of the measuring plane.

    Args:
        cameras: The cameras, each with its label, settings and optional baseline.
        on_status: Called with a :class:`MonitorStatus` after every frame (in the
            thread that runs the monitor); an exception it raises ends the run (the
            cameras are still closed).
        max_consecutive_errors: A camera failing this many captures/fits in a row ends
            the run with the last error.
        fit: ``(frame, fit_settings) -> PlaneSample``; default :func:`plane_sample`.

    Raises:
        ConfigError: With no camera or with two cameras of the same label.
    """

    def __init__(self, cameras: Sequence[MonitoredCamera], on_status: StatusCallback | None = None, *,
                 max_consecutive_errors: int = 10, fit: FrameFit = plane_sample) -> None:
        if not cameras:
            raise ConfigError("the monitor needs at least one camera")
        labels = [c.label for c in cameras]
        dupes = sorted({x for x in labels if labels.count(x) > 1})
        if dupes:
            raise ConfigError(f"two monitored cameras share the label {dupes[0]!r}")
        self._watches = [_Watch(c) for c in cameras]
        self.on_status = on_status
        self.max_consecutive_errors = max(1, int(max_consecutive_errors))
        self._fit = fit
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._result: MonitorSummary | None = None
        self._error: BaseException | None = None

    # -------------------------------------------------------------- control
    def request_stop(self) -> None:
        """Ask a running monitor to stop after the frame in progress (any thread)."""
        self._stop.set()

    @property
    def stop_requested(self) -> bool:
        """Whether :meth:`request_stop` was called."""
        return self._stop.is_set()

    def summary(self) -> MonitorSummary:
        """The per-camera summary so far."""
        for w in self._watches:
            w.refresh()
        return MonitorSummary([w.summary for w in self._watches])

    def start(self, duration_s: float | None = None, max_frames: int | None = None) -> Monitor:
        """Run in one background thread; :meth:`stop` ends and joins it.

        Raises:
            CellcalError: If it is already running.
        """
        if self._thread is not None:
            raise CellcalError("monitor is already running")
        self._thread = threading.Thread(target=self._run_in_thread, args=(duration_s, max_frames),
                                        name="cellcal-monitor", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 10.0) -> MonitorSummary:
        """Stop the background run, join its thread, and return the summary.

        Args:
            timeout: Seconds to wait for the thread (a capture in progress finishes
                within its own timeout first).

        Raises:
            DeviceTimeoutError: If the thread does not end within ``timeout``.
            CellcalError: The error that ended the background run, if any.
        """
        self.request_stop()
        thread = self._thread
        if thread is not None:
            thread.join(timeout)
            if thread.is_alive():
                raise DeviceTimeoutError(f"monitor thread did not stop within {timeout} s")
            self._thread = None
        if self._error is not None:
            error, self._error = self._error, None
            raise error
        return self._result if self._result is not None else self.summary()

    def _run_in_thread(self, duration_s: float | None, max_frames: int | None) -> None:
        try:
            self._result = self.run(duration_s, max_frames)
        except BaseException as exc:  # handed to stop(); the thread itself must not die noisily
            self._error = exc

    # -------------------------------------------------------------- the loop
    def run(self, duration_s: float | None = None, max_frames: int | None = None) -> MonitorSummary:
        """Connect the cameras, watch them until stopped, close them; returns the summary.

        Stops on :meth:`request_stop`, after ``duration_s`` seconds of wall time, once
        every camera has taken ``max_frames`` capture attempts, or on Ctrl-C
        (KeyboardInterrupt in this thread: the summary then has ``interrupted=True``).

        Raises:
            DeviceConnectionError, DeviceTimeoutError: If a camera cannot be connected.
            MonitorError: ``max_consecutive_errors`` failed frames in a row on one camera.
            CellcalError: A device failure other than a capture timeout.
        """
        t0 = time.monotonic()
        interrupted = False
        with contextlib.ExitStack() as stack:
            try:
                for w in self._watches:
                    stack.callback(_close, w.guard, w.spec.camera)
                    t = w.spec.settings.connect_timeout_s
                    w.guard.call(functools.partial(w.spec.camera.connect, t), t, f"connect(timeout={t:g} s)")
                    w.next_due = time.monotonic()
                self._loop(t0, duration_s, max_frames)
            except KeyboardInterrupt:
                interrupted = True
        result = self.summary()
        result.interrupted = interrupted
        result.elapsed_s = time.monotonic() - t0
        return result

    def _loop(self, t0: float, duration_s: float | None, max_frames: int | None) -> None:
        def done(w: _Watch) -> bool:
            return max_frames is not None and w.index >= max_frames

        while not self._stop.is_set():
            now = time.monotonic()
            if duration_s is not None and now - t0 >= duration_s:
                return
            active = [w for w in self._watches if not done(w)]
            if not active:
                return
            for w in active:
                if self._stop.is_set():
                    return
                if time.monotonic() >= w.next_due:
                    w.next_due = time.monotonic() + w.spec.settings.period_s
                    self._step(w)
            wait = min(w.next_due for w in active) - time.monotonic()
            if duration_s is not None:
                wait = min(wait, t0 + duration_s - time.monotonic())
            if wait > 0:
                self._stop.wait(wait)

    def _step(self, w: _Watch) -> None:
        spec = w.spec
        index = w.index
        w.index += 1
        t = spec.settings.capture_timeout_s
        try:
            frame = w.guard.call(lambda: spec.camera.capture(t), t, f"capture(timeout={t:g} s)")
            sample = self._fit(frame, spec.fit_settings)
        except BackendOverrunError:
            raise                                  # a backend that ignores its timeout ends the run
        except (DeviceTimeoutError, CalibrationError) as exc:
            w.summary.errors += 1
            w.consecutive_errors += 1
            if w.consecutive_errors >= self.max_consecutive_errors:
                raise MonitorError(f"{spec.label}: {w.consecutive_errors} failed frames in a row; last: {exc}") from exc
            self._report(MonitorStatus(spec.label, index, None, str(exc)))
            return
        w.consecutive_errors = 0
        status = w.detector.update(sample)
        w.summary.frames += 1
        if status.tilt_deviation_rad is not None and status.height_deviation_m is not None:
            s = w.summary
            s.max_tilt_deviation_rad = max(s.max_tilt_deviation_rad, status.tilt_deviation_rad)
            s.max_height_deviation_m = max(s.max_height_deviation_m, status.height_deviation_m)
        self._report(MonitorStatus(spec.label, index, status))

    def _report(self, status: MonitorStatus) -> None:
        if self.on_status is not None:
            self.on_status(status)
