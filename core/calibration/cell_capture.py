"""The cell's other cameras captured at every pose of ``calibrate``'s plan, one after the other (issue #40).

``calibrate`` drives one camera on the flange (the configuration's). With ``[[cameras]]`` the
others are connected too and, at each pose, once the driven camera has captured and the arm is at
rest, each captures one frame in turn (the capture's time after the pose's is said per frame):
a camera on the flange sees the plane from ``reported flange @ its mount``, a fixed camera from
its ``[cameras.pose]``. Each frame's plane is the full-frame fit's, searched near ``[reference]``
seen from that camera; the poses' planes make each camera's consensus plane in the base frame
with its interval, as the driven camera's (``summarize_poses``). Each camera's result is
``DIR/result-NAME.json`` (ADR 0061).
"""

from __future__ import annotations

import contextlib
import functools
import math
import time
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from cellcal.core.calibration.calibrator import GUARD_GRACE_S, connect_guarded
from cellcal.core.calibration.config import CellConfig
from cellcal.core.calibration.record import PoseRecord
from cellcal.core.calibration.report import summarize_poses, write_json_atomic
from cellcal.core.calibration.sections import MountSection
from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe.points import ExpectedPlane
from cellcal.core.methods.measure import full_frame_document, measure_full_frame
from cellcal.devices.arm_model import ArmModel
from cellcal.devices.blocking import DeadlineGuard
from cellcal.devices.camera import Camera3D
from cellcal.devices.config import parse_section
from cellcal.devices.errors import CalibrationError
from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame
from cellcal.devices.version import cellcal_version

__all__ = ["CAMERA_RESULT_SCHEMA", "OtherCameras", "camera_result_filename"]

#: Schema of ``DIR/result-NAME.json``.
CAMERA_RESULT_SCHEMA = "cellcal.camera-result/1"
#: How far a camera's plane may lie from ``[reference]`` seen from its configured place.
SEARCH_ANGLE_RAD = math.radians(10.0)
SEARCH_OFFSET_M = 0.05


def camera_result_filename(name: str) -> str:
    """The result file of camera ``name`` beside the driven camera's ``result.json``."""
    return f"result-{name}.json"


class OtherCameras:
    """The cameras of the cell other than the driven one, captured at every pose (a ``PoseObserver``).

    Args:
        config: The configuration the run drives (its ``cameras`` name every camera).
        cameras: The other cameras by name (unconnected; :meth:`connect` connects them).
    """

    def __init__(self, config: CellConfig, cameras: Mapping[str, Camera3D]) -> None:
        self.config = config
        self.cameras = dict(cameras)
        entries = {e.name: e for e in config.cameras}
        self.places: dict[str, tuple[str, Pose]] = {}
        for i, (name, _camera) in enumerate(self.cameras.items()):
            entry = entries[name]
            if entry.on == "base" and entry.pose_base is not None:
                self.places[name] = ("base", entry.pose_base)
            else:
                mount = parse_section(MountSection, entry.mount, where=f"cameras[{i}].mount", source=config.source)
                self.places[name] = ("flange", mount.pose())
        self.guards = {name: DeadlineGuard(f"camera backend '{cam.backend_name}' ({name})", GUARD_GRACE_S)
                       for name, cam in self.cameras.items()}
        #: Per camera, the pose entries measured (``index``, poses, ``full_frame`` or ``error``, ``after_s``).
        self.poses: dict[str, list[dict[str, Any]]] = {name: [] for name in self.cameras}

    def connect(self, stack: contextlib.ExitStack) -> None:
        """Connect every other camera, closed by ``stack`` (each under its deadline, as the calibrator's)."""
        for name, cam in self.cameras.items():
            connect_guarded(stack, self.guards[name], cam)

    def __call__(self, record: PoseRecord, frames: Sequence[Frame], result: object) -> None:
        """At a measured pose (the arm at rest): capture each other camera in turn and fit its plane."""
        started = time.perf_counter()
        for name, cam in self.cameras.items():
            t = self.config.plan.capture_timeout_s
            frame = self.guards[name].call(functools.partial(cam.capture, t), t, f"capture(timeout={t:g} s)")
            self.poses[name].append(self._entry(name, record, frame, time.perf_counter() - started))

    def _entry(self, name: str, record: PoseRecord, frame: Frame, after_s: float) -> dict[str, Any]:
        """One pose's entry of camera ``name``: its plane (or why none), where it stood, when it captured."""
        on, pose = self.places[name]
        camera_pose = record.reported @ pose if on == "flange" else pose
        entry: dict[str, Any] = {"index": record.index, "reported_flange_pose": record.reported.to_dict(),
                                 "camera_pose": camera_pose.to_dict(), "after_s": after_s,
                                 "timestamp": float(frame.timestamp)}
        ref = self.config.reference
        search = None
        if ref is not None:
            seen = Plane.from_point_normal(ref.plane_point_m, ref.plane_normal).transformed(camera_pose.inv())
            search = ExpectedPlane(seen.oriented_toward_origin(), SEARCH_ANGLE_RAD, SEARCH_OFFSET_M)
        try:
            _row, fit = measure_full_frame([frame], self.config.full_frame, expected_plane=search)
        except CalibrationError as exc:  # this camera at this pose: said in its result, the run goes on
            entry["error"] = str(exc)
            return entry
        entry["full_frame"] = full_frame_document(fit, camera_pose, None, expected_plane=search)
        return entry

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
                "capture": "one after the other, after the driven camera at each pose (after_s: seconds later)",
            }
            written.append(write_json_atomic(Path(out_dir) / camera_result_filename(name), document))
        return written
