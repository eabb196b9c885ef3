"""Feeding the live view from a running monitor: the fit of each frame, joined with the detector's verdict."""

from __future__ import annotations

from collections.abc import Callable

from cellcal.core.liveview.scenes import monitor_scene
from cellcal.core.liveview.server import LiveView
from cellcal.core.methods.fullframe import FullFrameResult, FullFrameSettings
from cellcal.core.monitor import MonitorStatus, PlaneSample
from cellcal.core.monitor.samples import fit_plane_sample
from cellcal.devices.recording.scene import CAMERA_FRAME_ID
from cellcal.devices.types import Frame

__all__ = ["MonitorFeed"]


class MonitorFeed:
    """The monitor's ``fit`` and ``on_status`` hooks, publishing each fitted frame with its drift values.

    The monitor fits a frame (:meth:`fit`) and then reports the detector's status for it
    (:meth:`on_status`) in the same thread, so the fit is held until its status arrives.

    Args:
        view: Where to publish.
        on_status: The status callback to pass every status on to (e.g. the CLI's printer).
        labels: The monitored cameras' labels; with more than one, each camera gets the frame id
            ``camera_<label>``.
    """

    def __init__(self, view: LiveView, on_status: Callable[[MonitorStatus], None] | None,
                 labels: list[str]) -> None:
        self.view = view
        self.forward = on_status
        self.several = len(labels) > 1
        self._pending: tuple[Frame, FullFrameResult] | None = None

    def fit(self, frame: Frame, settings: FullFrameSettings | None) -> PlaneSample:
        """The monitor's plane fit (:func:`fit_plane_sample`), keeping the fit for :meth:`on_status`."""
        self._pending = None
        sample, result = fit_plane_sample(frame, settings)
        self._pending = (frame, result)
        return sample

    def on_status(self, status: MonitorStatus) -> None:
        """Publish the frame just fitted with this status, then pass the status on."""
        pending, self._pending = self._pending, None
        if pending is not None and status.detector is not None:
            frame_id = f"{CAMERA_FRAME_ID}_{status.label}" if self.several else CAMERA_FRAME_ID
            self.view.publish(monitor_scene(*pending, status, camera_frame_id=frame_id))
        if self.forward is not None:
            self.forward(status)
