"""Live drift monitor: per-frame plane samples against a baseline."""

from cellcal.core.monitor.monitor import (
    BASELINE_SCHEMA,
    Baseline,
    CameraSummary,
    DetectorStatus,
    DriftDetector,
    DriftEvent,
    Monitor,
    MonitoredCamera,
    MonitorStatus,
    MonitorSummary,
    PlaneSample,
    plane_sample,
)
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
    "plane_sample",
]
