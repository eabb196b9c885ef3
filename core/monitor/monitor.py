"""Live drift monitor: per-frame plane fit, drift detection with hysteresis.

Two layers:

* :class:`DriftDetector` — pure logic, no I/O. It takes one :class:`PlaneSample` per
  frame (the measuring plane's tilt about the camera's x and y axes, rad, and the
  height along the optical axis, m, all in the camera frame), compares it with a
  :class:`Baseline`, and emits :class:`DriftEvent` s (``drift_started`` /
  ``drift_cleared``).
* :class:`Monitor` — captures from one or more cameras with explicit timeouts, fits
  the plane per frame, feeds one detector per camera and reports a
  :class:`MonitorStatus` per frame through a callback. It runs in the caller's thread
  (:meth:`Monitor.run`, which also turns Ctrl-C into a clean stop) or in one
  background thread (:meth:`Monitor.start` / :meth:`Monitor.stop`, which joins it).
  Cameras are connected on start and always closed on the way out.

Detection rule (settings: :class:`~cellcal.core.calibration.config.MonitorSection`):

* **baseline** — the mean of the first ``baseline_frames`` frames, or given explicitly
  (e.g. from the monitor's own baseline file or a calibration's plane in the base frame
  at the arm's current pose). Those frames also measure the frame-to-frame noise
  (sample standard deviation; per-axis RMS for the tilt).
* **deviation** — tilt: ``hypot(tilt_x - base_x, tilt_y - base_y)`` (close to the angle
  between the normals for small angles); height: ``|height - base|``.
* **thresholds** — ``max(configured, noise_sigmas * measured noise)``: plain noise
  cannot flag whatever the configured value.
* **drift starts** when the median deviation over the last ``window_frames`` frames
  exceeds its threshold (tilt or height): a step is flagged on the
  ``window_frames // 2 + 1``-th frame after it, a single wild frame never is;
* **drift clears** only after both medians have stayed at or below
  ``hysteresis_ratio`` times their thresholds for ``clear_s`` seconds of frame time.

Times are the frames' timestamps (seconds since the epoch), so the detector is
deterministic and independent of the machine's speed.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from cellcal.core.calibration.config import MonitorSection
from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe import FullFrameSettings, check_gates, fit_full_frame
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import CalibrationError, CellcalError, ConfigError, DeviceTimeoutError, MonitorError
from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame

Phase = Literal["baseline", "ok", "drift"]
EventKind = Literal["drift_started", "drift_cleared"]

#: Schema tag of the monitor's baseline file (``cellcal monitor --save-baseline``).
BASELINE_SCHEMA = "cellcal.monitor-baseline/1"

__all__ = [
    "BASELINE_SCHEMA",
    "Baseline",
    "CameraSummary",
    "DetectorStatus",
    "DriftDetector",
    "DriftEvent",
    "Monitor",
    "MonitorError",
    "MonitorStatus",
    "MonitorSummary",
    "MonitoredCamera",
    "PlaneSample",
    "plane_sample",
]


# ---------------------------------------------------------------------- data
@dataclass(frozen=True)
class PlaneSample:
    """The measuring plane seen in one frame, camera (optical) frame.

    Attributes:
        timestamp: Frame time, seconds since the epoch.
        tilt_x_rad: Camera tilt about its x axis (:meth:`Plane.tilt_about_x_rad`), rad.
        tilt_y_rad: Camera tilt about its y axis (:meth:`Plane.tilt_about_y_rad`), rad.
        height_m: Distance from the optical centre to the plane along the optical axis, m.
    """

    timestamp: float
    tilt_x_rad: float
    tilt_y_rad: float
    height_m: float

    def __post_init__(self) -> None:
        values = (self.timestamp, self.tilt_x_rad, self.tilt_y_rad, self.height_m)
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
            raise CalibrationError(f"plane sample values must be finite numbers, got {values!r}")

    @classmethod
    def from_plane(cls, plane: Plane, timestamp: float) -> PlaneSample:
        """The sample of a plane given in the camera frame.

        Raises:
            CalibrationError: If the optical axis does not meet the plane in front of the camera.
        """
        return cls(float(timestamp), plane.tilt_about_x_rad(), plane.tilt_about_y_rad(),
                   plane.distance_along_optical_axis_m())


@dataclass(frozen=True)
class Baseline:
    """The plane as it should look from the camera (camera frame), and optionally its noise.

    Attributes:
        tilt_x_rad: Expected tilt about the camera's x axis, rad.
        tilt_y_rad: Expected tilt about the camera's y axis, rad.
        height_m: Expected height along the optical axis, m.
        tilt_noise_rad: Frame-to-frame 1-sigma of a tilt (per axis), rad; None if unknown.
        height_noise_m: Frame-to-frame 1-sigma of the height, m; None if unknown.
    """

    tilt_x_rad: float
    tilt_y_rad: float
    height_m: float
    tilt_noise_rad: float | None = None
    height_noise_m: float | None = None

    def __post_init__(self) -> None:
        for name in ("tilt_x_rad", "tilt_y_rad", "height_m", "tilt_noise_rad", "height_noise_m"):
            v = getattr(self, name)
            optional = "noise" in name
            if v is None and optional:
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise CalibrationError(f"baseline {name} must be a finite number, got {v!r}")
            if (optional or name == "height_m") and v < 0:
                raise CalibrationError(f"baseline {name} must be >= 0, got {v!r}")

    @property
    def has_noise(self) -> bool:
        """Whether both noise figures are known."""
        return self.tilt_noise_rad is not None and self.height_noise_m is not None

    @classmethod
    def from_plane(cls, plane_camera: Plane) -> Baseline:
        """The baseline of a plane given in the camera frame (no noise figures)."""
        s = PlaneSample.from_plane(plane_camera.oriented_toward_origin(), 0.0)
        return cls(s.tilt_x_rad, s.tilt_y_rad, s.height_m)

    @classmethod
    def from_plane_in_base(cls, plane_base: Plane, camera_pose: Pose) -> Baseline:
        """The baseline of a plane known in the robot base frame, seen from ``camera_pose``.

        Args:
            plane_base: The measuring plane, base frame.
            camera_pose: ``T_base_camera`` (e.g. the arm's flange pose @ the mount).
        """
        return cls.from_plane(plane_base.transformed(camera_pose.inv()))

    def to_dict(self) -> dict[str, float | None]:
        """JSON form (SI units)."""
        return {"tilt_x_rad": self.tilt_x_rad, "tilt_y_rad": self.tilt_y_rad, "height_m": self.height_m,
                "tilt_noise_rad": self.tilt_noise_rad, "height_noise_m": self.height_noise_m}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, source: str | None = None) -> Baseline:
        """Inverse of :meth:`to_dict`.

        Raises:
            ConfigError: Naming the missing or malformed key.
        """
        if not isinstance(data, Mapping):
            raise ConfigError(f"baseline must be a table, got {type(data).__name__}", source=source)
        kwargs: dict[str, Any] = {}
        for key in ("tilt_x_rad", "tilt_y_rad", "height_m", "tilt_noise_rad", "height_noise_m"):
            if key not in data:
                if key.endswith(("noise_rad", "noise_m")):
                    continue
                raise ConfigError("missing baseline value", source=source, key=key)
            kwargs[key] = data[key]
        try:
            return cls(**kwargs)
        except CalibrationError as exc:
            raise ConfigError(str(exc), source=source) from None


@dataclass(frozen=True)
class DriftEvent:
    """A change of drift state.

    Attributes:
        kind: ``"drift_started"`` or ``"drift_cleared"``.
        timestamp: Time of the frame that caused it, seconds since the epoch.
        tilt_deviation_rad: Median tilt deviation over the window at that frame, rad.
        height_deviation_m: Median height deviation over the window at that frame, m.
        tilt_threshold_rad: Effective tilt threshold, rad.
        height_threshold_m: Effective height threshold, m.
        causes: Which quantities exceeded their threshold (``"tilt"``, ``"height"``);
            empty for ``drift_cleared``.
        label: The camera's label ("" for a bare detector).
    """

    kind: EventKind
    timestamp: float
    tilt_deviation_rad: float
    height_deviation_m: float
    tilt_threshold_rad: float
    height_threshold_m: float
    causes: tuple[str, ...] = ()
    label: str = ""

    def to_dict(self) -> dict[str, Any]:
        """JSON form (SI units)."""
        return {"kind": self.kind, "timestamp": self.timestamp, "label": self.label, "causes": list(self.causes),
                "tilt_deviation_rad": self.tilt_deviation_rad, "height_deviation_m": self.height_deviation_m,
                "tilt_threshold_rad": self.tilt_threshold_rad, "height_threshold_m": self.height_threshold_m}


@dataclass(frozen=True)
class DetectorStatus:
    """What the detector made of one sample.

    Attributes:
        sample: The sample.
        phase: ``"baseline"`` while the baseline/noise frames are collected, then ``"ok"``
            or ``"drift"``.
        tilt_deviation_rad: This frame's tilt deviation (None in the baseline phase), rad.
        height_deviation_m: This frame's height deviation (None in the baseline phase), m.
        tilt_median_rad: Median tilt deviation over the window (None until it is full), rad.
        height_median_m: Median height deviation over the window (None until it is full), m.
        event: The event this frame caused, if any.
    """

    sample: PlaneSample
    phase: Phase
    tilt_deviation_rad: float | None = None
    height_deviation_m: float | None = None
    tilt_median_rad: float | None = None
    height_median_m: float | None = None
    event: DriftEvent | None = None


# ---------------------------------------------------------------------- detector
class DriftDetector:
    """Flags persistent drift of tilt or height with hysteresis (pure logic, no I/O).

    Args:
        settings: Thresholds, window, hysteresis; default :class:`MonitorSection` ().
        baseline: Expected plane; None takes the mean of the first
            ``settings.baseline_frames`` samples. A baseline without noise figures still
            uses those frames to measure the noise.
        label: Copied into the events.
    """

    def __init__(self, settings: MonitorSection | None = None, baseline: Baseline | None = None,
                 label: str = "") -> None:
        self.settings = settings or MonitorSection()
        self.label = label
        self._given = baseline
        self._baseline: Baseline | None = None
        self._warmup: list[PlaneSample] = []
        n = self.settings.window_frames
        self._tilt_window: deque[float] = deque(maxlen=n)
        self._height_window: deque[float] = deque(maxlen=n)
        self._tilt_thr = math.nan
        self._height_thr = math.nan
        self._drifting = False
        self._below_since: float | None = None
        self.events: list[DriftEvent] = []
        if baseline is not None and baseline.has_noise:
            self._establish(baseline)

    # -------------------------------------------------------------- state
    @property
    def baseline(self) -> Baseline | None:
        """The baseline in use with its noise figures, once established."""
        return self._baseline

    @property
    def tilt_threshold_rad(self) -> float | None:
        """Effective tilt threshold, rad (None before the baseline is established)."""
        return None if self._baseline is None else self._tilt_thr

    @property
    def height_threshold_m(self) -> float | None:
        """Effective height threshold, m (None before the baseline is established)."""
        return None if self._baseline is None else self._height_thr

    @property
    def drifting(self) -> bool:
        """Whether drift is flagged now."""
        return self._drifting

    @property
    def phase(self) -> Phase:
        """Current phase."""
        if self._baseline is None:
            return "baseline"
        return "drift" if self._drifting else "ok"

    # -------------------------------------------------------------- update
    def update(self, sample: PlaneSample) -> DetectorStatus:
        """Take one frame's sample and return the detector's verdict.

        Raises:
            CalibrationError: If ``sample`` is not a :class:`PlaneSample`.
        """
        if not isinstance(sample, PlaneSample):
            raise CalibrationError(f"DriftDetector.update needs a PlaneSample, got {type(sample).__name__}")
        if self._baseline is None:
            self._warmup.append(sample)
            if len(self._warmup) < self.settings.baseline_frames:
                return DetectorStatus(sample, "baseline")
            self._establish(self._from_warmup())
            for s in self._warmup[-self.settings.window_frames:]:
                self._push(s)
            self._warmup = []
            return DetectorStatus(sample, "baseline")
        dev_t, dev_h = self._push(sample)
        med_t, med_h = self._medians()
        event = None if med_t is None or med_h is None else self._transition(sample.timestamp, med_t, med_h)
        return DetectorStatus(sample, self.phase, dev_t, dev_h, med_t, med_h, event)

    def _from_warmup(self) -> Baseline:
        s = self._warmup
        tx = np.array([x.tilt_x_rad for x in s])
        ty = np.array([x.tilt_y_rad for x in s])
        h = np.array([x.height_m for x in s])
        tilt_noise = math.sqrt((float(np.var(tx, ddof=1)) + float(np.var(ty, ddof=1))) / 2.0)
        height_noise = float(np.std(h, ddof=1))
        g = self._given
        if g is not None:
            return Baseline(g.tilt_x_rad, g.tilt_y_rad, g.height_m, tilt_noise, height_noise)
        return Baseline(float(tx.mean()), float(ty.mean()), float(h.mean()), tilt_noise, height_noise)

    def _establish(self, baseline: Baseline) -> None:
        cfg = self.settings
        assert baseline.tilt_noise_rad is not None and baseline.height_noise_m is not None
        self._baseline = baseline
        self._tilt_thr = max(cfg.tilt_threshold_rad, cfg.noise_sigmas * baseline.tilt_noise_rad)
        self._height_thr = max(cfg.height_threshold_m, cfg.noise_sigmas * baseline.height_noise_m)

    def _push(self, s: PlaneSample) -> tuple[float, float]:
        b = self._baseline
        assert b is not None
        dev_t = math.hypot(s.tilt_x_rad - b.tilt_x_rad, s.tilt_y_rad - b.tilt_y_rad)
        dev_h = abs(s.height_m - b.height_m)
        self._tilt_window.append(dev_t)
        self._height_window.append(dev_h)
        return dev_t, dev_h

    def _medians(self) -> tuple[float | None, float | None]:
        if len(self._tilt_window) < self.settings.window_frames:
            return None, None
        return float(np.median(self._tilt_window)), float(np.median(self._height_window))

    def _transition(self, t: float, med_t: float, med_h: float) -> DriftEvent | None:
        cfg = self.settings
        if not self._drifting:
            causes = tuple(name for name, over in (("tilt", med_t > self._tilt_thr),
                                                   ("height", med_h > self._height_thr)) if over)
            if not causes:
                return None
            self._drifting = True
            self._below_since = None
            return self._emit("drift_started", t, med_t, med_h, causes)
        if med_t <= cfg.hysteresis_ratio * self._tilt_thr and med_h <= cfg.hysteresis_ratio * self._height_thr:
            if self._below_since is None:
                self._below_since = t
            if t - self._below_since >= cfg.clear_s:
                self._drifting = False
                self._below_since = None
                return self._emit("drift_cleared", t, med_t, med_h, ())
        else:
            self._below_since = None
        return None

    def _emit(self, kind: EventKind, t: float, med_t: float, med_h: float, causes: tuple[str, ...]) -> DriftEvent:
        event = DriftEvent(kind, t, med_t, med_h, self._tilt_thr, self._height_thr, causes, self.label)
        self.events.append(event)
        return event


# ---------------------------------------------------------------------- per-frame fit
def plane_sample(frame: Frame, fit_settings: FullFrameSettings | None = None) -> PlaneSample:
    """Fit the measuring plane of one frame (:func:`fit_full_frame`) and return its tilt and height.

    Args:
        frame: A camera frame.
        fit_settings: The ``[full_frame]`` settings (fit and quality gates); None: defaults.

    Raises:
        CalibrationQualityError: If the fit fails a quality gate (too few valid pixels,
            too few inliers, residuals too large, poor coverage).
        CalibrationError: If no plane is found or the optical axis misses it.
    """
    result = fit_full_frame(frame, fit_settings)
    check_gates(result)
    return PlaneSample(float(frame.timestamp), result.tilt_x_rad, result.tilt_y_rad, result.height_m)


# ---------------------------------------------------------------------- monitor
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


class _Watch:
    """Run-time state of one camera."""

    def __init__(self, spec: MonitoredCamera) -> None:
        self.spec = spec
        self.detector = DriftDetector(spec.settings, spec.baseline, spec.label)
        self.summary = CameraSummary(spec.label)
        self.index = 0
        self.consecutive_errors = 0
        self.next_due = 0.0

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
                    stack.callback(w.spec.camera.close)
                    w.spec.camera.connect(w.spec.settings.connect_timeout_s)
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
        try:
            frame = spec.camera.capture(spec.settings.capture_timeout_s)
            sample = self._fit(frame, spec.fit_settings)
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
