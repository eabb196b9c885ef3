"""Live drift monitor: per-frame plane samples against a baseline (ADR 0013)."""

from cellcal.core.monitor.baselines import (
    BASELINE_SCHEMA,
    baseline_from_result,
    is_calibration_result,
    monitored_cameras,
    read_baseline_file,
    read_baselines,
    write_baselines,
)
from cellcal.core.monitor.detector import DetectorStatus, DriftDetector, DriftEvent
from cellcal.core.monitor.monitor import (
    CameraSummary,
    Monitor,
    MonitoredCamera,
    MonitorStatus,
    MonitorSummary,
)
from cellcal.core.monitor.samples import Baseline, PlaneSample, plane_sample
from cellcal.devices.errors import MonitorError

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
    "baseline_from_result",
    "is_calibration_result",
    "monitored_cameras",
    "plane_sample",
    "read_baseline_file",
    "read_baselines",
    "write_baselines",
]
