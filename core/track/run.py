"""``cellcal track``'s loop: read the arm (never move it), pair each frame, fit, feed the tracker, write.

Design: docs/adr/0041-track-command.md.
"""

from __future__ import annotations

import collections
import contextlib
import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any

import numpy as np

from cellcal.core.calibration.config import CellConfig
from cellcal.core.geometry.consistency import noise_plane_covariance, noise_shifts
from cellcal.core.geometry.view_follows import ViewFollowsArm, ViewSample
from cellcal.core.handeye.estimator import ArmAccuracy
from cellcal.core.handeye.model import PlaneObservation
from cellcal.core.handeye.run import reference_plane
from cellcal.core.methods.fullframe import FullFrameResult, check_gates, fit_full_frame
from cellcal.core.track.decimate import auto_decimation, decimated
from cellcal.core.track.estimator import Tracker
from cellcal.core.track.pairing import PoseHistory, Skip
from cellcal.core.track.result import fixed_track_document, frame_row, track_document, track_filenames, write_track_json
from cellcal.core.track.state import TrackSettings, TrackState, TrackStep
from cellcal.devices.arm import RobotArm
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import CalibrationError, CalibrationQualityError, OutputError, SafetyError
from cellcal.devices.forwarding import ForwardingArm, ForwardingCamera
from cellcal.devices.interrupts import interrupts_held
from cellcal.devices.jsonsafe import json_safe
from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame
from cellcal.devices.version import cellcal_version

#: A frame stamped more than this outside the arm reads around it is on another clock: the reads' midpoint is used, s.
CLOCK_MISMATCH_S = 0.5
#: Rows written to ``track.jsonl`` between flushes.
FLUSH_EVERY = 30
#: Frames a fixed camera keeps after a change before restarting: its one view never tells its pose from the
#: plane, so waiting for the arm's work (``TrackSettings.change_window``) would not help.
FIXED_CHANGE_FRAMES = 30

StepCallback = Callable[["TrackProgress"], None]


@dataclass
class TrackProgress:
    """What one frame did, for a printer or a live view.

    Attributes:
        index: Frame number from 0.
        t_s: Frame time since the first frame, s.
        outcome: ``"accepted"``, ``"held out"``, ``"skipped: <reason>"``, ``"refused: <gate>"``, ``"no plane"``.
        step: The tracker's step for fitted frames, else None.
        flange: The frame's flange pose (paired), or None.
        fit: The plane fit, or None.
        frame: The frame (for a live view), or None.
    """

    index: int
    t_s: float
    outcome: str
    step: TrackStep | None = None
    flange: Pose | None = None
    fit: FullFrameResult | None = None
    frame: Frame | None = None


@dataclass
class TrackOutcome:
    """The end of a run: the ``track.json`` document and how the run ended."""

    document: dict[str, Any]
    state: TrackState
    counters: dict[str, int] = field(default_factory=dict)
    interrupted: bool = False


def track_settings(config: CellConfig, arm: RobotArm | None = None) -> TrackSettings:
    """The tracker's settings: the arm's read-back noise from ``[handeye]`` and stated accuracy, the rest as documented.

    ``arm``: its :meth:`~cellcal.devices.arm.RobotArm.arm_model` gives the accuracy the intervals carry (None: none).
    """
    he = config.handeye
    model = getattr(arm, "arm_model", None)
    stated = model() if callable(model) else None
    accuracy = None if stated is None else ArmAccuracy(stated.accuracy_m, stated.accuracy_rad, stated.source)
    return TrackSettings(arm_translation_sigma_m=he.arm_translation_sigma_m,
                         arm_rotation_sigma_rad=math.radians(he.arm_rotation_sigma_deg), confidence=he.confidence,
                         arm_accuracy=accuracy)


def fixed_settings(settings: TrackSettings) -> TrackSettings:
    """A fixed camera's tracker settings: no arm in its observations, and a short wait after a change."""
    return replace(settings, arm_translation_sigma_m=0.0, arm_rotation_sigma_rad=0.0, arm_accuracy=None,
                   change_window=FIXED_CHANGE_FRAMES)


def observation(fit: FullFrameResult, flange: Pose) -> PlaneObservation:
    """The tracker's observation of a plane fit (camera frame) made at ``flange`` (base frame).

    Its covariance is the fit's noise alone (ADR 0055, "Poses combined"): the camera's systematic error is
    common to the frames, so it weighs no frame and does not deafen the change detector.
    """
    cov = noise_plane_covariance(fit)
    return PlaneObservation(flange, np.asarray(fit.plane.normal, dtype=np.float64), float(fit.plane.offset_m), cov)


class ReadOnlyArm(ForwardingArm):
    """The cell's arm as ``cellcal track`` sees it: poses, joints and status read; every command refused.

    The cell's own program moves the arm; a move, a stop or an error reset from cellcal
    would fight it, so each is a :class:`SafetyError` and nothing is sent.
    """

    def _refuse(self, what: str) -> SafetyError:
        return SafetyError(f"cellcal track reads the arm and never commands it: {what} refused, nothing sent")

    def _move_linear(self, pose: Pose, speed: float, acceleration: float, timeout: float) -> None:
        raise self._refuse("move_linear")

    def _stop(self, timeout: float) -> None:
        raise self._refuse("stop")

    def _clear_errors(self, timeout: float) -> None:
        raise self._refuse("clear_errors")


class FrameClock(ForwardingCamera):
    """A camera whose frames' own stamps are the clock (:meth:`now`): a recorded session's time.

    Before the first frame :meth:`now` is NaN (:class:`TrackRun` reads the arm only after the
    first capture); after a capture it is that frame's time. On a simulated cell this is the simulated clock
    itself, so a replayed session pairs its frames exactly as it did live.
    """

    def __init__(self, inner: Camera3D) -> None:
        super().__init__(inner)
        self._last = math.nan

    def _capture(self, timeout: float) -> Frame:
        frame = self.inner.capture(timeout)
        self._last = float(frame.timestamp)
        return frame

    def now(self) -> float:
        """The last frame's time, s since the epoch."""
        return self._last


def device_clock(camera: Camera3D) -> Callable[[], float]:
    """The clock the frames are stamped with: a simulated camera's world clock, else the host's (epoch s)."""
    world = getattr(camera, "world", None)
    clock = getattr(world, "clock", None)
    now = getattr(clock, "now", None)
    return now if callable(now) else time.time


class TrackRun:
    """One ``cellcal track`` session over connected devices.

    Args:
        config: The cell (``[mount]``, ``[reference]``, ``[full_frame]``, ``[handeye]`` noise).
        camera: A connected camera.
        arm: A connected arm: only ``get_pose`` is called.
        out_dir: Where ``track.json`` / ``track.jsonl`` go (None: nowhere).
        now: The clock frames are stamped with (:func:`device_clock`).
        on_progress: Called after every frame.
        settings: The tracker's settings (default :func:`track_settings`).
        decimation: Fit every k-th pixel in each direction (:func:`~.decimate.decimated`; 1: all; None: chosen
            from the first frame by :func:`~.decimate.auto_decimation`, then kept).
        name: The camera's name in ``[[cameras]]`` when it is tracked with others (in ``meta``); None: one camera.
        filenames: Its document and rows (:func:`~.result.track_filenames`); default ``track.json``, ``track.jsonl``.
        fixed_pose: A camera fixed in the base frame: its configured ``T_base_camera``. The arm is not read
            for its frames; its tracker takes them at the identity flange pose (``Tracker(fixed=True)``).
    """

    def __init__(self, config: CellConfig, camera: Camera3D, arm: RobotArm, *, out_dir: str | Path | None,
                 now: Callable[[], float], on_progress: StepCallback | None = None,
                 settings: TrackSettings | None = None, decimation: int | None = None, name: str | None = None,
                 filenames: tuple[str, str] | None = None, fixed_pose: Pose | None = None) -> None:
        self.config = config
        self.camera = camera
        self.arm = arm
        self.out_dir = None if out_dir is None else Path(out_dir)
        self.now = now
        self.on_progress = on_progress
        self.decimation = decimation
        self.name = name
        self.fixed_pose = fixed_pose
        self.filenames = filenames or track_filenames(None)
        settings = settings or track_settings(config, arm)
        plane = reference_plane(config, "cellcal track")
        #: Whether the camera's view follows the arm's work, until a pair of frames decides it (ADR 0045).
        self.view_check: ViewFollowsArm | None = None
        if fixed_pose is not None:
            self.tracker = Tracker(fixed_pose, plane, fixed_settings(settings), fixed=True)
        else:
            self.tracker = Tracker(config.mount.pose(), plane, settings)
            self.view_check = ViewFollowsArm(config.mount.pose(),
                                             arm_translation_sigma_m=settings.arm_translation_sigma_m,
                                             arm_rotation_sigma_rad=settings.arm_rotation_sigma_rad, what="frames at")
        self.history = PoseHistory()
        self.counters: collections.Counter[str] = collections.Counter()
        #: Whether the last failure was the arm's (a run over several cameras then stops: the arm is shared).
        self.arm_failed = False
        self._t0: float | None = None
        self._rows: IO[str] | None = None
        self._written = 0

    # ------------------------------------------------------------------ the loop
    def run(self, duration_s: float | None = None, max_frames: int | None = None) -> TrackOutcome:
        """Track until ``duration_s`` seconds of frames, ``max_frames`` frames, or Ctrl-C; then write.

        Raises:
            CellcalError: A device failed (the files written so far stay valid).
        """
        interrupted = False
        self.start()
        try:
            index = 0
            while max_frames is None or index < max_frames:
                t_s = self.frame(index)
                index += 1
                if duration_s is not None and t_s >= duration_s:
                    break
        except KeyboardInterrupt:
            interrupted = True
        except BaseException:
            self.abandon()  # a failed run: the earlier track.json / track.jsonl stay as they were
            raise
        return self.finish(interrupted)

    # ------------------------------------------------------------------ steps (a run over several cameras)
    def start(self) -> None:
        """Open the frame rows (``track.jsonl.partial``)."""
        self._open_rows()

    def frame(self, index: int) -> float:
        """Track one frame (:meth:`run`'s step); returns its time since the first frame, s.

        Raises:
            CellcalError: The camera or the arm failed (:attr:`arm_failed` says which).
        """
        if self.fixed_pose is not None:
            return self._fixed_frame(index)
        return self._frame(index)

    def abandon(self) -> None:
        """A failed run: close the rows unrenamed; earlier files stay as they were."""
        self._abandon_rows()

    def finish(self, interrupted: bool, failure: str | None = None) -> TrackOutcome:
        """Close the rows and write the document; ``failure``: why the camera stopped early (kept in ``meta``)."""
        self._close_rows()
        return self._finish(interrupted, failure)

    @property
    def t0(self) -> float | None:
        """The time of the first frame (s since the epoch) the frames' ``t_s`` count from, or None."""
        return self._t0

    @t0.setter
    def t0(self, value: float) -> None:
        """Count from ``value`` (a run over several cameras: one origin for all), before the first frame."""
        self._t0 = value

    def _read_arm(self) -> Pose:
        """The flange pose now; a failure marks :attr:`arm_failed` and is raised as it is."""
        try:
            return self.arm.get_pose()
        except BaseException:
            self.arm_failed = True
            raise

    def _frame(self, index: int) -> float:
        """Read the arm, capture, read the arm, pair, fit, update; returns the frame's time, s."""
        timeout = self.camera.default_timeout_s
        t_before = self.now()
        if index > 0:  # before the first frame the clock may not run yet (a replay's is the frames' own)
            self.history.add(t_before, self._read_arm())
        frame = self.camera.capture(timeout)
        t_after = self.now()
        self.history.add(t_after, self._read_arm())
        t_frame = self._frame_time(frame, t_before, t_after)
        if self._t0 is None:
            self._t0 = t_frame
        t_s = t_frame - self._t0
        paired = self.history.at(t_frame)
        if isinstance(paired, Skip):
            return self._skip(index, t_s, f"skipped: {paired.reason}")
        return self._update(index, t_s, frame, paired, time.perf_counter())

    def _fixed_frame(self, index: int) -> float:
        """A fixed camera's frame: capture, fit, update at the identity flange pose (the arm is not read)."""
        t_before = self.now()
        frame = self.camera.capture(self.camera.default_timeout_s)
        t_frame = self._frame_time(frame, t_before, self.now())
        if self._t0 is None:
            self._t0 = t_frame
        return self._update(index, t_frame - self._t0, frame, Pose.identity(), time.perf_counter())

    def _update(self, index: int, t_s: float, frame: Frame, paired: Pose, started: float) -> float:
        """Fit a paired frame's plane and feed the tracker; its row and progress."""
        try:
            if self.decimation is None:
                self.decimation = auto_decimation(frame)
            fit = fit_full_frame(decimated(frame, self.decimation), self.config.full_frame)
            check_gates(fit)
        except CalibrationQualityError as exc:
            return self._skip(index, t_s, f"refused: gate {exc.gate}", flange=paired)
        except CalibrationError:
            return self._skip(index, t_s, "no plane", flange=paired)
        seen = observation(fit, paired)
        if self.view_check is not None:
            # a camera whose view does not follow the arm ends the run (CalibrationQualityError, view_follows_arm)
            self.view_check.add(ViewSample(f"{t_s:.1f} s", paired, seen.normal, seen.offset_m, seen.covariance))
        step = self.tracker.update(t_s, seen, noise_shifts(fit))
        outcome = "accepted" if step.accepted else "held out"
        self._row(frame_row(step, t_s, index=index, fit_ms=round((time.perf_counter() - started) * 1e3, 2)), outcome)
        if self.on_progress is not None:
            self.on_progress(TrackProgress(index, t_s, outcome, step, paired, fit, frame))
        return t_s

    def _frame_time(self, frame: Frame, t_before: float, t_after: float) -> float:
        """The frame's own stamp when it lies between the two arm reads (one clock), else their midpoint."""
        stamp = float(frame.timestamp)
        first = t_before if math.isfinite(t_before) else t_after
        if math.isfinite(stamp) and first - CLOCK_MISMATCH_S <= stamp <= t_after + CLOCK_MISMATCH_S:
            return stamp
        self.counters["frame time from the host clock"] += 1
        return 0.5 * (first + t_after)

    def _skip(self, index: int, t_s: float, outcome: str, *, flange: Pose | None = None) -> float:
        self._row({"t_s": t_s, "index": index, "accepted": False, "note": outcome}, outcome)
        if self.on_progress is not None:
            self.on_progress(TrackProgress(index, t_s, outcome, flange=flange))
        return t_s

    # ------------------------------------------------------------------ files
    def _open_rows(self) -> None:
        """``track.jsonl`` is written as ``track.jsonl.partial`` and renamed at the end: an earlier one stays whole."""
        if self.out_dir is None:
            return
        path = self.out_dir / (self.filenames[1] + ".partial")
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            self._rows = path.open("w", encoding="utf-8")
        except OSError as exc:
            raise OutputError(f"cannot write {path}: {exc.strerror or exc}", errno=exc.errno) from None

    def _row(self, row: dict[str, Any], outcome: str) -> None:
        """Count the frame and its outcome and write its row: the counters and the rows always agree.

        Ctrl-C is held over the count and the write (delivered right after), so that an
        interruption never lands between them and leaves one more count than rows.
        """
        line = None if self._rows is None else json.dumps(json_safe(row), allow_nan=False) + "\n"
        with interrupts_held():
            self.counters["frames"] += 1
            self.counters[outcome] += 1
            if self._rows is None or line is None:
                return
            try:
                self._rows.write(line)
            except OSError as exc:
                raise OutputError(f"cannot write {self._rows.name}: {exc.strerror or exc}",
                                  errno=exc.errno) from None
        self._written += 1
        if self._written % FLUSH_EVERY == 0:
            self._rows.flush()

    def _abandon_rows(self) -> None:
        """Close ``track.jsonl.partial`` without renaming it (what the failed run saw, for a look)."""
        rows, self._rows = self._rows, None
        if rows is not None:
            with contextlib.suppress(OSError):
                rows.close()

    def _close_rows(self) -> None:
        rows, self._rows = self._rows, None
        if rows is None or self.out_dir is None:
            return
        try:
            rows.flush()
            os.fsync(rows.fileno())
            rows.close()
            os.replace(self.out_dir / (self.filenames[1] + ".partial"), self.out_dir / self.filenames[1])
        except OSError as exc:
            rows.close()
            raise OutputError(f"cannot write {self.out_dir / self.filenames[1]}: {exc.strerror or exc}",
                              errno=exc.errno) from None

    def _finish(self, interrupted: bool, failure: str | None = None) -> TrackOutcome:
        state = self.tracker.state
        meta: dict[str, Any] = {
            "cellcal_version": cellcal_version(), "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
            "config_source": self.config.source, "camera": self.config.camera_section.get("backend"),
            "arm": self.config.arm_section.get("backend"), "interrupted": interrupted, "decimation": self.decimation,
            "duration_s": None if self._t0 is None else round(self.now() - self._t0, 6)}
        if self.name is not None:  # a camera of [[cameras]] tracked with others: which, where, whether it failed
            meta.update(camera_name=self.name, place="base" if self.fixed_pose is not None else "flange",
                        failed=failure)
        counters = dict(self.counters)
        if self.fixed_pose is not None:
            document = fixed_track_document(self.tracker, self.fixed_pose, counters, meta)
        else:
            document = track_document(state, counters, meta)
        if self.out_dir is not None:
            write_track_json(self.out_dir, document, self.filenames[0])
        return TrackOutcome(document, state, counters, interrupted)


__all__ = ["FIXED_CHANGE_FRAMES", "FrameClock", "ReadOnlyArm", "TrackOutcome", "TrackProgress", "TrackRun",
           "device_clock", "fixed_settings", "observation", "track_settings"]
