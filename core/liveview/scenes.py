"""The scenes of a calibration pose, a monitored frame and a tracked one: core results in the viewers' plain form."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from cellcal.core.calibration.calibrator import PoseRecord
from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe import FullFrameResult
from cellcal.core.monitor import MonitorStatus
from cellcal.devices.pose import Pose
from cellcal.devices.recording.scene import CAMERA_FRAME_ID, Scene
from cellcal.devices.types import Frame

__all__ = ["calibration_scenes", "monitor_scene", "pose_plane", "track_scene"]


def pose_plane(record: PoseRecord, result: FullFrameResult | None) -> Plane | None:
    """The plane to draw for a pose (camera frame): the full-frame fit's, else the first grid method's."""
    if result is not None:
        return result.plane
    return next((m.plane for m in record.measurements if m.plane is not None), None)


def _mask(result: FullFrameResult | None, frame: Frame) -> np.ndarray | None:
    """The fit's per-pixel inlier mask when it matches the frame (a raw-cloud fit has none)."""
    if result is None or result.inlier_mask.shape != frame.shape:
        return None
    return np.asarray(result.inlier_mask, dtype=bool)


def calibration_scenes(record: PoseRecord, frames: Sequence[Frame], result: FullFrameResult | None,
                       mount: Pose | None, *, camera_frame_id: str = CAMERA_FRAME_ID) -> list[Scene]:
    """One scene per frame of a measured plan pose.

    Args:
        record: The pose's record (the arm's reported flange pose).
        frames: The frames captured there.
        result: The pose's full-frame fit (plane and inlier mask), or None.
        mount: ``T_flange_camera``; None: a fixed camera (placed by
            :meth:`~cellcal.core.liveview.server.LiveView.place_camera`).
        camera_frame_id: The camera's frame (a cell's several cameras: ``camera_NAME``).
    """
    plane = pose_plane(record, result)
    normal, offset = (None, None) if plane is None else (np.asarray(plane.normal, dtype=np.float64),
                                                           float(plane.offset_m))
    flange = None if mount is None else record.reported
    return [Scene(frame, base_flange=flange, flange_camera=mount, plane_normal=normal, plane_offset_m=offset,
                  inlier_mask=_mask(result, frame), camera_frame_id=camera_frame_id) for frame in frames]


def track_scene(frame: Frame, result: FullFrameResult, flange: Pose | None, mount: Pose | None,
                values: Mapping[str, Any], *, camera_frame_id: str = CAMERA_FRAME_ID) -> Scene:
    """The scene of one tracked frame: its cloud and plane at the read flange pose, the tracked mount.

    Args:
        frame: The frame.
        result: Its plane fit (camera frame).
        flange: ``T_base_flange`` paired with the frame (None: a fixed camera, placed in the base frame by
            :meth:`~cellcal.core.liveview.server.LiveView.place_camera`).
        mount: The tracked ``T_flange_camera`` after the frame (None: a fixed camera).
        values: The ``cellcal.Track`` message's values (outcome, chi2, mount, event).
        camera_frame_id: The camera's frame id (one of several: ``camera_NAME``).
    """
    return Scene(frame, base_flange=flange, flange_camera=mount,
                 plane_normal=np.asarray(result.plane.normal, dtype=np.float64),
                 plane_offset_m=float(result.plane.offset_m), inlier_mask=_mask(result, frame), track=values,
                 camera_frame_id=camera_frame_id)


def monitor_scene(frame: Frame, result: FullFrameResult, status: MonitorStatus, *,
                  camera_frame_id: str = CAMERA_FRAME_ID) -> Scene:
    """The scene of one monitored frame, with the detector's drift values (radians, metres)."""
    d = status.detector
    drift: dict[str, float | str | None] = {"label": status.label, "phase": "failed" if d is None else d.phase,
                                            "tilt_x_rad": result.tilt_x_rad, "tilt_y_rad": result.tilt_y_rad,
                                            "height_m": result.height_m}
    if d is not None:
        drift.update(tilt_deviation_rad=d.tilt_deviation_rad, height_deviation_m=d.height_deviation_m)
    return Scene(frame, plane_normal=np.asarray(result.plane.normal, dtype=np.float64),
                 plane_offset_m=float(result.plane.offset_m), inlier_mask=_mask(result, frame), drift=drift,
                 camera_frame_id=camera_frame_id)
