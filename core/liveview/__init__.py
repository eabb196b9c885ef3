"""Live view of calibrations and monitors in Foxglove, and the scenes they draw (ADR 0020)."""

from cellcal.core.liveview.feed import MonitorFeed
from cellcal.core.liveview.presence import linger, live_view_session, wait_for_viewer
from cellcal.core.liveview.scenes import calibration_scenes, monitor_scene, pose_plane, track_scene
from cellcal.core.liveview.server import HOST, LiveView, camera_frame_id, camera_topics, import_foxglove, open_live_view

__all__ = ["HOST", "LiveView", "MonitorFeed", "calibration_scenes", "camera_frame_id", "camera_topics",
           "import_foxglove", "linger",
           "live_view_session", "monitor_scene", "open_live_view", "pose_plane", "track_scene", "wait_for_viewer"]
