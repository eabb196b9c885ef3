"""Drift detection with hysteresis on per-frame plane samples: pure logic, no I/O (ADR 0013)."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from cellcal.core.calibration.sections import MonitorSection
from cellcal.core.monitor.samples import Baseline, PlaneSample
from cellcal.devices.errors import CalibrationError

__all__ = ["DetectorStatus", "DriftDetector", "DriftEvent", "EventKind", "Phase"]

Phase = Literal["baseline", "ok", "drift"]
EventKind = Literal["drift_started", "drift_cleared"]


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
        """The baseline with noise figures from the warm-up frames (the given plane, if any, is kept)."""
        s = self._warmup
        tx = np.array([x.tilt_x_rad for x in s])
        ty = np.array([x.tilt_y_rad for x in s])
        h = np.array([x.height_m for x in s])
        # tilt noise: RMS over both axes of the per-axis sample variances, rad
        tilt_noise = math.sqrt((float(np.var(tx, ddof=1)) + float(np.var(ty, ddof=1))) / 2.0)
        # height noise: sample standard deviation, m
        height_noise = float(np.std(h, ddof=1))
        g = self._given
        if g is not None:
            return Baseline(g.tilt_x_rad, g.tilt_y_rad, g.height_m, tilt_noise, height_noise)
        return Baseline(float(tx.mean()), float(ty.mean()), float(h.mean()), tilt_noise, height_noise)

    def _establish(self, baseline: Baseline) -> None:
        """Adopt ``baseline`` (with noise figures) and set the effective thresholds."""
        cfg = self.settings
        assert baseline.tilt_noise_rad is not None and baseline.height_noise_m is not None
        self._baseline = baseline
        # never below noise_sigmas x the measured noise: plain noise cannot flag drift
        self._tilt_thr = max(cfg.tilt_threshold_rad, cfg.noise_sigmas * baseline.tilt_noise_rad)
        self._height_thr = max(cfg.height_threshold_m, cfg.noise_sigmas * baseline.height_noise_m)

    def _push(self, s: PlaneSample) -> tuple[float, float]:
        """Add one sample's deviations (tilt rad, height m) to the windows and return them."""
        b = self._baseline
        assert b is not None
        # tilt deviation: close to the angle between the normals for small angles, rad
        dev_t = math.hypot(s.tilt_x_rad - b.tilt_x_rad, s.tilt_y_rad - b.tilt_y_rad)
        dev_h = abs(s.height_m - b.height_m)  # m
        self._tilt_window.append(dev_t)
        self._height_window.append(dev_h)
        return dev_t, dev_h

    def _medians(self) -> tuple[float | None, float | None]:
        """Median tilt (rad) and height (m) deviation over the window; None until it is full."""
        if len(self._tilt_window) < self.settings.window_frames:
            return None, None
        return float(np.median(self._tilt_window)), float(np.median(self._height_window))

    def _transition(self, t: float, med_t: float, med_h: float) -> DriftEvent | None:
        """Start or clear drift from the window medians at frame time ``t`` (s); the event, if any."""
        cfg = self.settings
        if not self._drifting:  # start: either median above its threshold
            causes = tuple(name for name, over in (("tilt", med_t > self._tilt_thr),
                                                   ("height", med_h > self._height_thr)) if over)
            if not causes:
                return None
            self._drifting = True
            self._below_since = None
            return self._emit("drift_started", t, med_t, med_h, causes)
        # clear: both medians at or below hysteresis_ratio x threshold for clear_s seconds of frame time
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
