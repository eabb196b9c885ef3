"""What a report's pictures need, taken while a run runs (JSON data, schema ``cellcal.report/1``, ADR 0037).

Per calibration pose: the depth map, the pixel classes (invalid, plane inlier, mixed pixel,
outlier, inside the region) and the residual map, downsampled and encoded by
:mod:`cellcal.core.report.arrays`; a sample of the cloud for the side view; the pose's
full-frame document (gates, intervals). A pose whose gate failed is fitted again without the
gates, so the report shows why. Per monitored camera: the drift values over time.
"""

from __future__ import annotations

import collections
import re
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from cellcal.core.report.arrays import decode_array, downsample_step, encode_array
from cellcal.devices.jsonsafe import json_safe

if TYPE_CHECKING:
    from cellcal.core.calibration.calibrator import PoseRecord
    from cellcal.core.calibration.config import CellConfig
    from cellcal.core.methods.fullframe import FullFrameResult, FullFrameSettings
    from cellcal.core.monitor import MonitorStatus
    from cellcal.devices.pose import Pose
    from cellcal.devices.types import Frame

__all__ = ["CLASS_INLIER", "CLASS_INVALID", "CLASS_MIXED", "CLASS_NAMES", "CLASS_OUTLIER", "MAX_MONITOR_SAMPLES",
           "MAX_SIDE_POINTS", "MIXED_BAND_RMS", "REGION_BIT", "CalibrationCapture", "FrameKeeper", "MonitorCapture",
           "pixel_classes", "pose_pictures"]

#: Pixel classes of the class map (low two bits); :data:`REGION_BIT` is set inside the region.
CLASS_INVALID, CLASS_INLIER, CLASS_MIXED, CLASS_OUTLIER = 0, 1, 2, 3
CLASS_NAMES = {CLASS_INVALID: "invalid", CLASS_INLIER: "plane (inlier)", CLASS_MIXED: "mixed pixel (dropped)",
               CLASS_OUTLIER: "outlier"}
REGION_BIT = 4
#: A valid pixel that is no inlier but lies within this many inlier RMS of the plane was dropped
#: as a mixed pixel (near a depth edge or an invalid patch); farther ones are outliers.
MIXED_BAND_RMS = 3.0
#: Points of the cloud kept for the side view.
MAX_SIDE_POINTS = 2000
#: Samples kept per monitored camera; past it every second one is dropped (the series stays bounded).
MAX_MONITOR_SAMPLES = 20000


def pixel_classes(frame: Frame, result: FullFrameResult, region: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The class map (uint8, (H, W)) and the signed residual map (m, NaN where invalid) of a fit.

    Residuals are the orthogonal distances to the fitted plane, positive toward the camera.
    """
    valid = np.asarray(frame.valid, dtype=bool)
    residual = np.full(valid.shape, np.nan, dtype=np.float32)
    # orthogonal distance of every valid point to the plane (camera frame), m
    residual[valid] = result.plane.signed_distance(np.asarray(frame.xyz, dtype=np.float64)[valid])
    inlier = np.asarray(result.inlier_mask, dtype=bool)
    if inlier.shape != valid.shape:  # a raw-cloud fit has no per-pixel mask
        inlier = np.zeros_like(valid)
    band = MIXED_BAND_RMS * max(float(result.residual_rms_m), 1e-6)
    classes = np.zeros(valid.shape, dtype=np.uint8)
    classes[valid] = CLASS_OUTLIER
    # valid but no inlier, yet on the plane within the band: dropped as mixed pixels
    near = valid & (np.abs(np.nan_to_num(residual, nan=np.inf)) <= band)
    classes[near] = CLASS_MIXED
    classes[valid & inlier] = CLASS_INLIER
    if region is not None:
        classes[np.asarray(region, dtype=bool)] |= REGION_BIT
    return classes, residual


def coverage_picture(result: FullFrameResult, settings: FullFrameSettings,
                     region: np.ndarray | None) -> dict[str, Any] | None:
    """The coverage grid as the ``coverage`` gate judged it: cell edges (px) and which cells lack plane inliers."""
    from cellcal.core.methods.fullframe.gates import coverage_cells

    mask = np.asarray(result.inlier_mask, dtype=bool)
    if mask.ndim != 2:  # a raw-cloud fit has no image
        return None
    cells = coverage_cells(mask, settings, None if region is None else np.asarray(region, dtype=bool))
    counted = cells.area > 0
    # a counted cell is covered when its inliers reach the per-cell share of its pixels
    covered = cells.counts >= settings.min_cell_inlier_fraction * cells.area
    return {"row_edges_px": [int(v) for v in cells.row_edges], "col_edges_px": [int(v) for v in cells.col_edges],
            "uncovered": (counted & ~covered).astype(int).tolist(), "counted": counted.astype(int).tolist(),
            "min_cell_inlier_fraction": float(settings.min_cell_inlier_fraction)}


def pose_pictures(frame: Frame, result: FullFrameResult, region: np.ndarray | None, *,
                  seed: int = 0, settings: FullFrameSettings | None = None) -> dict[str, Any]:
    """The maps and cloud sample of one pose (JSON data; mm, downsampled to at most 320 columns), and with
    ``settings`` the coverage grid as the gate judged it."""
    classes, residual = pixel_classes(frame, result, region)
    h, w = classes.shape
    step = downsample_step(w)
    used = np.ones(classes.shape, dtype=bool) if region is None else (classes & REGION_BIT) > 0
    valid = np.asarray(frame.valid, dtype=bool)
    depth_mm = np.where(valid, np.asarray(frame.xyz[..., 2], dtype=np.float32) * 1000.0, np.nan)
    # a reproducible sample of the valid points for the side view, camera frame, mm
    idx = np.flatnonzero(valid.ravel())
    if idx.size > MAX_SIDE_POINTS:
        idx = np.sort(np.random.default_rng(seed).choice(idx, MAX_SIDE_POINTS, replace=False))
    points_mm = np.asarray(frame.xyz, dtype=np.float32).reshape(-1, 3)[idx] * 1000.0
    return {
        "shape_px": [h, w],
        "step_px": step,
        "depth_mm": encode_array(depth_mm[::step, ::step], "float16"),
        "residual_mm": encode_array(residual[::step, ::step] * 1000.0, "float16"),
        "classes": encode_array(classes[::step, ::step], "uint8"),
        "region": region is not None,
        "mixed_band_mm": MIXED_BAND_RMS * float(result.residual_rms_m) * 1000.0,
        "points_mm": encode_array(points_mm, "float32"),
        "point_classes": encode_array(classes.ravel()[idx], "uint8"),
        "plane_cam": {"normal": [float(v) for v in result.plane.normal], "offset_m": float(result.plane.offset_m)},
        # counted where the fit looked: inside the region (the whole image without one)
        "class_counts": {CLASS_NAMES[c]: int(np.count_nonzero(((classes & 3) == c) & used)) for c in CLASS_NAMES},
        "coverage": None if settings is None else coverage_picture(result, settings, region),
    }


def decoded_maps(pictures: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """The maps of :func:`pose_pictures` as arrays (``depth_mm``, ``residual_mm``, ``classes``, ...)."""
    return {key: decode_array(pictures[key]).astype(np.float32 if key != "classes" and key != "point_classes"
                                                     else np.uint8)
            for key in ("depth_mm", "residual_mm", "classes", "points_mm", "point_classes")}


class FrameKeeper:
    """A camera that keeps its last frames (the ones a failed pose was fitted on); everything else passes through."""

    def __init__(self, camera: Any, keep: int) -> None:
        self._camera = camera
        self.frames: collections.deque[Frame] = collections.deque(maxlen=max(1, keep))

    def capture(self, timeout: float) -> Frame:
        """The camera's frame, kept."""
        frame = self._camera.capture(timeout)
        self.frames.append(frame)
        return frame  # type: ignore[no-any-return]

    def __getattr__(self, name: str) -> Any:
        return getattr(self._camera, name)


_POSE_IN_MESSAGE = re.compile(r"plan pose (\d+)")


class CalibrationCapture:
    """Collects the pictures of a ``calibrate`` run, pose by pose (a :data:`PoseObserver`)."""

    def __init__(self, config: CellConfig, camera_name: str) -> None:
        self.config = config
        self.camera_name = camera_name
        self.poses: list[dict[str, Any]] = []

    def __call__(self, record: PoseRecord, frames: Sequence[Frame], result: FullFrameResult | None) -> None:
        """Observer: keep the pose's maps and its full-frame document."""
        entry: dict[str, Any] = {"index": record.index, "failed": False, "full_frame": record.full_frame,
                                 "expected": None if record.expected is None else record.expected.to_dict()}
        if result is not None and frames:
            region = None if record.full_frame is None or record.full_frame.get("region") is None else \
                self._region(frames[0], record.camera)
            entry["pictures"] = pose_pictures(frames[0], result, region, seed=record.index,
                                              settings=self.config.full_frame)
        self.poses.append(json_safe(entry))

    def _region(self, frame: Frame, camera_pose: Pose) -> np.ndarray | None:
        from cellcal.core.calibration.region import region_mask

        return region_mask(self.config.region, frame.intrinsics, camera_pose, source=self.config.source)

    def failed_pose(self, exc: Exception, frames: Sequence[Frame], targets: Sequence[Pose]) -> None:
        """Fit the frames of the pose whose gate failed again without gates and keep its pictures.

        The pose is the one the error names (``plan pose N``); its camera pose is the plan's target
        with the ``[mount]`` (the arm's reading is not kept for a failed pose).
        """
        from cellcal.core.calibration.region import expected_plane, region_mask
        from cellcal.core.methods.measure import expected_geometry, full_frame_document, measure_full_frame
        from cellcal.devices.errors import CellcalError

        match = _POSE_IN_MESSAGE.search(str(exc))
        index = int(match.group(1)) - 1 if match else len(self.poses)
        if not frames or not 0 <= index < len(targets):
            return
        config = self.config
        camera_pose = targets[index] @ config.mount.pose()
        expected = None
        if config.reference is not None:
            expected = expected_geometry(camera_pose, config.reference.plane_point_m, config.reference.plane_normal)
        entry: dict[str, Any] = {"index": index, "failed": True, "error": str(exc),
                                 "expected": None if expected is None else expected.to_dict()}
        try:
            region = region_mask(config.region, frames[0].intrinsics, camera_pose, source=config.source)
            search = expected_plane(config.search_reference, expected)
            try:
                _, result = measure_full_frame(list(frames), config.full_frame, expected=expected, region=region,
                                               expected_plane=search, check=False)
            except CellcalError:
                if search is None:
                    raise
                # no plane near the expected one: show the plane the whole image gives instead
                search = None
                entry["note"] = "no plane near the expected one: the pictures show the plane the image gives"
                _, result = measure_full_frame(list(frames), config.full_frame, expected=expected, region=region,
                                               check=False)
        except CellcalError as again:  # no plane at all: the report says so in words
            entry["full_frame"] = None
            entry["error"] = f"{exc} (no plane to draw: {again})"
        else:
            entry["full_frame"] = full_frame_document(result, camera_pose, expected, expected_plane=search)
            gate = getattr(exc, "gate", None)
            if gate is not None:  # the gate that refused the pose, as the run measured it
                entry["full_frame"].setdefault("gates", {})[gate] = {
                    "value": getattr(exc, "value", None), "threshold": getattr(exc, "threshold", None), "passed": False}
            entry["pictures"] = pose_pictures(frames[0], result, region, seed=index, settings=config.full_frame)
        self.poses.append(json_safe(entry))


class MonitorCapture:
    """The drift values of every monitored camera over time (a status callback to chain)."""

    def __init__(self) -> None:
        self.series: dict[str, dict[str, list[Any]]] = {}
        self._stride: dict[str, int] = {}
        self._seen: dict[str, int] = {}

    def __call__(self, status: MonitorStatus) -> None:
        """Keep this frame's tilt and height deviations (s since the camera's first frame, deg, mm)."""
        d = status.detector
        if d is None or d.tilt_deviation_rad is None or d.height_deviation_m is None:
            return
        s = self.series.setdefault(status.label, {"t": [], "tilt_deg": [], "height_mm": [], "drift": [],
                                                  "t0": [d.sample.timestamp]})
        n = self._seen.get(status.label, 0)
        self._seen[status.label] = n + 1
        stride = self._stride.get(status.label, 1)
        if n % stride:
            return
        s["t"].append(d.sample.timestamp - s["t0"][0])
        s["tilt_deg"].append(float(np.degrees(d.tilt_deviation_rad)))
        s["height_mm"].append(1000.0 * d.height_deviation_m)
        s["drift"].append(d.phase == "drift")
        if len(s["t"]) >= MAX_MONITOR_SAMPLES:  # bounded: keep every second sample from now on
            for key in ("t", "tilt_deg", "height_mm", "drift"):
                s[key] = s[key][::2]
            self._stride[status.label] = stride * 2
