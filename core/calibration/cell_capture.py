"""The cell's other cameras captured at every pose of a plan, together where the devices allow (issue #40).

``calibrate`` and ``handeye`` drive one camera on the flange (the configuration's). With
``[[cameras]]`` the others are connected too and, at each pose, once the arm is at rest, the cameras
whose ``capture = "together"`` start capturing at the same time as the driven camera, each through
its own deadline guard in its own worker thread (:meth:`OtherCameras.begin`, the calibrator's
:class:`~cellcal.core.calibration.calibrator.PoseCompanion` hook); the observer call
(:meth:`OtherCameras.__call__`) joins them, then each ``capture = "alone"`` camera captures in turn
(a ToF or structured-light camera whose light would disturb the others'). A capture that fails or
overruns is that camera's error at that pose; Ctrl-C propagates. Each frame says when its capture
started and ended after the pose's settle (seconds) and its own ``timestamp``.

A camera on the flange sees the plane from ``reported flange @ its mount``, a fixed camera from its
``[cameras.pose]``. Each frame's plane is the full-frame fit's, searched near ``[reference]`` seen
from that camera; the poses' planes make each camera's consensus plane in the base frame with its
interval, as the driven camera's (``summarize_poses``). Each camera's result is
``DIR/result-NAME.json`` (ADR 0061).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import threading
import time
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from cellcal.core.calibration.calibrator import GUARD_GRACE_S, PoseObserver, connect_guarded
from cellcal.core.calibration.config import CellConfig
from cellcal.core.calibration.record import PoseRecord
from cellcal.core.calibration.report import summarize_poses, write_json_atomic
from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe import FullFrameResult
from cellcal.core.methods.fullframe.points import ExpectedPlane
from cellcal.core.methods.measure import full_frame_document, measure_full_frame
from cellcal.devices.arm_model import ArmModel
from cellcal.devices.blocking import DeadlineGuard
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import BackendOverrunError, CalibrationError, CellcalError
from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame
from cellcal.devices.version import cellcal_version

__all__ = ["CAMERA_RESULT_SCHEMA", "JOIN_MARGIN_S", "OtherCameras", "camera_result_filename"]

#: Schema of ``DIR/result-NAME.json``.
CAMERA_RESULT_SCHEMA = "cellcal.camera-result/1"
#: How far a camera's plane may lie from ``[reference]`` seen from its configured place.
SEARCH_ANGLE_RAD = math.radians(10.0)
SEARCH_OFFSET_M = 0.05
#: Seconds a capture worker may take beyond its guard's allowance (timeout + grace) before it is abandoned.
JOIN_MARGIN_S = 0.5


def camera_result_filename(name: str) -> str:
    """The result file of camera ``name`` beside the driven camera's ``result.json``."""
    return f"result-{name}.json"


@dataclasses.dataclass
class _Capture:
    """One camera's capture at one pose: its frame or error, and when it ran (``time.perf_counter()`` s)."""

    name: str
    mode: str
    started: float = math.nan
    ended: float = math.nan
    frame: Frame | None = None
    error: BaseException | None = None
    thread: threading.Thread | None = None


class OtherCameras:
    """The cameras of the cell other than the driven one, captured at every pose (a ``PoseObserver`` and
    the calibrator's ``PoseCompanion``).

    Args:
        config: The configuration the run drives (its ``cameras`` name every camera and its ``capture``).
        cameras: The other cameras by name (unconnected; :meth:`connect` connects them).
    """

    def __init__(self, config: CellConfig, cameras: Mapping[str, Camera3D]) -> None:
        self.config = config
        self.cameras = dict(cameras)
        entries = {e.name: e for e in config.cameras}
        self.places: dict[str, tuple[str, Pose]] = {}
        for name in self.cameras:
            placement = entries[name].placement()  # parsed with the configuration (parse_cameras)
            if placement is None:
                raise CalibrationError(f"camera {name!r} has no configured place")
            self.places[name] = (placement.on, placement.pose)
        #: Each camera's capture mode, the driven camera's among them (``"together"`` or ``"alone"``).
        self.modes = {e.name: e.capture for e in config.cameras if e.name in self.cameras or
                      e.name == config.camera_name}
        self.driven_together = self.modes.get(config.camera_name, "together") == "together"
        self.guards = {name: DeadlineGuard(f"camera backend '{cam.backend_name}' ({name})", GUARD_GRACE_S)
                       for name, cam in self.cameras.items()}
        #: Per camera, the pose entries measured (``index``, poses, ``full_frame`` or ``error``; ``capture``
        #: mode, ``started_s``/``ended_s`` after the settle, ``timestamp``, ``fit_s``: seconds).
        self.poses: dict[str, list[dict[str, Any]]] = {name: [] for name in self.cameras}
        self._pending: dict[str, _Capture] = {}
        self._settled = math.nan
        #: Per camera, a pose observer shown each of its frames with its own plane (e.g. the live view's),
        #: called on the run's thread; the record is the driven camera's with its measurements left out.
        self.observers: dict[str, PoseObserver] = {}

    def connect(self, stack: contextlib.ExitStack) -> None:
        """Connect every other camera, closed by ``stack`` (each under its deadline, as the calibrator's)."""
        for name, cam in self.cameras.items():
            connect_guarded(stack, self.guards[name], cam)

    # ------------------------------------------------------------------ the companion hook
    def begin(self, index: int) -> None:
        """The arm is at rest at pose ``index``: the ``together`` cameras start (with the driven one if it is too)."""
        self.end()  # nothing of an earlier pose is left running
        self._settled = time.perf_counter()
        if self.driven_together:
            self._start_together()

    def end(self) -> None:
        """Join the captures still running (each within its deadline), their results dropped; never raises."""
        for capture in self._pending.values():
            self._join(capture)
        self._pending = {}

    def _start_together(self) -> None:
        for name in self.cameras:
            if self.modes[name] == "together":
                capture = _Capture(name, "together")
                capture.thread = threading.Thread(target=self._capture, args=(capture,), daemon=True,
                                                  name=f"cellcal capture ({name})")
                self._pending[name] = capture
                capture.started = time.perf_counter()  # its deadline runs from here
                capture.thread.start()

    def _capture(self, capture: _Capture) -> None:
        """One frame of camera ``capture.name`` under its own guard (in a worker, or in place for ``alone``)."""
        t = self.config.plan.capture_timeout_s
        cam = self.cameras[capture.name]
        if not math.isfinite(capture.started):
            capture.started = time.perf_counter()
        try:
            capture.frame = self.guards[capture.name].call(lambda: cam.capture(t), t, f"capture(timeout={t:g} s)")
        except BaseException as exc:  # kept for the pose's observer: a failure is said, Ctrl-C re-raised there
            capture.error = exc
        finally:
            capture.ended = time.perf_counter()

    def _join(self, capture: _Capture) -> None:
        """Wait for ``capture``'s worker until its guard's allowance is spent; a worker still alive is abandoned."""
        thread = capture.thread
        if thread is None:
            return
        allowed = self.config.plan.capture_timeout_s + self.guards[capture.name].grace_s + JOIN_MARGIN_S
        thread.join(max(0.0, capture.started + allowed - time.perf_counter()))
        if thread.is_alive():  # the guard returns within its allowance: only a stalled interpreter gets here
            capture.error = BackendOverrunError(f"camera {capture.name!r}: capture did not return within "
                                                f"{allowed:g} s")
            capture.ended = time.perf_counter()

    # ------------------------------------------------------------------ the observer
    def __call__(self, record: PoseRecord, frames: Sequence[Frame], result: object) -> None:
        """After the driven camera (the arm at rest): collect the ``together`` cameras, capture each ``alone``
        camera in turn, fit each frame's plane.

        Raises:
            KeyboardInterrupt: A capture was interrupted (after every worker of the pose was joined).
        """
        if not self.driven_together:  # the driven camera captured alone: the together cameras now
            self._start_together()
        captures = dict(self._pending)
        self.end()
        for capture in captures.values():
            if capture.error is not None and not isinstance(capture.error, Exception):
                raise capture.error  # Ctrl-C (or a SystemExit) in a worker ends the run as on the main thread
        for name in self.cameras:
            if self.modes[name] == "alone":
                captures[name] = _Capture(name, "alone")
                self._capture(captures[name])
                error = captures[name].error
                if error is not None and not isinstance(error, Exception):
                    raise error
        for name in self.cameras:
            self.poses[name].append(self._entry(name, record, captures[name]))

    def _entry(self, name: str, record: PoseRecord, capture: _Capture) -> dict[str, Any]:
        """One pose's entry of camera ``name``: its plane (or why none), where it stood, when it captured."""
        on, pose = self.places[name]
        camera_pose = record.reported @ pose if on == "flange" else pose
        started, ended = capture.started - self._settled, capture.ended - self._settled
        entry: dict[str, Any] = {"index": record.index, "reported_flange_pose": record.reported.to_dict(),
                                 "camera_pose": camera_pose.to_dict(), "capture": capture.mode,
                                 "started_s": started, "ended_s": ended, "after_s": ended}
        if capture.frame is None:
            exc = capture.error
            text = str(exc) if isinstance(exc, CellcalError) else f"{type(exc).__name__}: {exc}"
            entry["error"] = f"capture failed: {text}"
            return entry
        frame = capture.frame
        entry["timestamp"] = float(frame.timestamp)
        ref = self.config.reference
        search = None
        if ref is not None:
            seen = Plane.from_point_normal(ref.plane_point_m, ref.plane_normal).transformed(camera_pose.inv())
            search = ExpectedPlane(seen.oriented_toward_origin(), SEARCH_ANGLE_RAD, SEARCH_OFFSET_M)
        t0 = time.perf_counter()
        fit: FullFrameResult | None = None
        try:
            _row, fit = measure_full_frame([frame], self.config.full_frame, expected_plane=search)
        except CalibrationError as exc:  # this camera at this pose: said in its result, the run goes on
            entry["error"] = str(exc)
        finally:
            entry["fit_s"] = time.perf_counter() - t0  # the plane fit's wall time, seconds
        observer = self.observers.get(name)
        if observer is not None:  # its own plane only: not the driven camera's measurements
            observer(dataclasses.replace(record, measurements=[]), [frame], fit)
        if fit is not None:
            entry["full_frame"] = full_frame_document(fit, camera_pose, None, expected_plane=search)
        return entry

    def capture_document(self) -> dict[str, Any]:
        """The result files' ``capture`` field: which cameras captured together, which alone, in what order."""
        names = [e.name for e in self.config.cameras if e.name in self.modes]
        together = [n for n in names if self.modes[n] == "together"]
        alone = [n for n in names if self.modes[n] == "alone"]
        return {
            "driven": self.config.camera_name, "together": together, "alone": alone,
            "order": ("at each pose, once the arm is at rest: the 'together' cameras at the same time"
                      + ("" if self.driven_together else ", after the driven camera")
                      + ", then each 'alone' camera in turn"),
            "times": "started_s, ended_s: seconds after the pose's settle; timestamp: the frame's own",
        }

    def write(self, out_dir: str | Path, reference: Plane | None, arm: ArmModel | None) -> list[Path]:
        """Write each camera's ``DIR/result-NAME.json`` atomically; returns the paths written."""
        written = []
        for name, entries in self.poses.items():
            on, pose = self.places[name]
            fitted = [e for e in entries if "full_frame" in e]
            document = {
                "schema": CAMERA_RESULT_SCHEMA, "cellcal_version": cellcal_version(),
                "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                "config_source": self.config.source, "camera": name, "on": on,
                ("mount" if on == "flange" else "camera_base"): pose.to_dict(),
                "poses": entries, "failed_poses": [e["index"] for e in entries if "error" in e],
                "summary": summarize_poses(fitted, reference, arm=arm) if fitted else None,
                "capture": self.capture_document(),
            }
            written.append(write_json_atomic(Path(out_dir) / camera_result_filename(name), document))
        return written
