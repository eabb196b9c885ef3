"""The service's Prometheus metrics: a registry per :class:`~cellcal.core.service.cell.Service`, served at ``/metrics``.

Counters and the run-duration histogram are fed as things happen (a run ends, an event is
published); each camera's plane figures are computed when scraped, from its current
calibration. Every labelled series a dashboard queries is created at zero when the service
starts, so a fresh service already answers every panel. Names (all SI):

``cellcal_service_info{version,cell}`` (gauge, 1), ``cellcal_plane_tilt_rad``,
``cellcal_plane_tilt_halfwidth_rad``, ``cellcal_plane_height_m``,
``cellcal_plane_height_halfwidth_m`` (gauges, ``{cell,camera}``), ``cellcal_drift_events_total{cell,camera,kind}``,
``cellcal_frames_fitted_total{cell,camera}``, ``cellcal_frames_refused_total{cell,camera,gate}``,
``cellcal_runs_total{cell,kind,status}``, ``cellcal_run_duration_seconds{cell,kind,status}`` (histogram),
``cellcal_runs_active{cell}`` (gauge) and ``cellcal_history_failures_total`` (counter).
Needs ``prometheus-client`` (the ``serve`` extra).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.core import GaugeMetricFamily, Metric
from prometheus_client.exposition import CONTENT_TYPE_LATEST

from cellcal.core.methods.fullframe import GATE_NAMES
from cellcal.core.service.calibration import Z95, CameraCalibration
from cellcal.core.service.runs import KINDS, STATES

__all__ = ["CONTENT_TYPE", "DRIFT_KINDS", "DRIFT_PREFIX", "RUN_BUCKETS_S", "ServiceMetrics", "frames_of_result",
           "plane_figures"]

log = logging.getLogger(__name__)

#: The exposition's content type (Prometheus text format).
CONTENT_TYPE = CONTENT_TYPE_LATEST
#: An event published on the bus whose type starts with this is a drift event of the kind that follows
#: (``drift.mount``, ``drift.plane``, ``drift.started``...), for the camera its data names.
DRIFT_PREFIX = "drift."
#: Drift kinds whose series exist (at zero) from the start: the tracker's changes told apart (``mount``,
#: ``plane``; ``mount_or_plane`` when neither alone explains one) and the monitor's drift (``monitor``).
DRIFT_KINDS = ("mount", "plane", "monitor")
#: Upper bounds of the run-duration histogram's buckets, seconds.
RUN_BUCKETS_S = (1.0, 5.0, 15.0, 30.0, 60.0, 120.0, 300.0, 600.0, 1800.0, 3600.0)
#: Longest label value kept (a longer camera name or kind from an event is cut).
_MAX_LABEL = 64


def plane_figures(calibration: CameraCalibration, reference_normal: Any = None) -> tuple[float, float, float, float]:
    """The plane's tilt and height and their 95 % half-widths, as the metrics give them.

    Args:
        calibration: The camera's current calibration (its base-frame plane and 9x9 covariance).
        reference_normal: The configured reference plane's normal, base frame (None: base +z).

    Returns:
        ``(tilt_rad, tilt_halfwidth_rad, height_m, height_halfwidth_m)``: the angle between the plane's
        normal and the reference normal (either orientation, so 0..pi/2); the larger of the two tilt
        axes' 95 % half-widths; the plane's signed distance from the base origin along its normal
        oriented to the reference normal's side; the 95 % half-width of the height at the calibration's
        anchor point.
    """
    model = calibration.model
    r = np.array([0.0, 0.0, 1.0]) if reference_normal is None else np.asarray(reference_normal, dtype=np.float64)
    r = r / np.linalg.norm(r)
    n = np.asarray(model.plane.normal, dtype=np.float64)
    along = float(n @ r)
    tilt = math.acos(min(1.0, abs(along)))  # angle between the normals, orientation ignored
    sign = 1.0 if along >= 0.0 else -1.0
    height = -model.plane.offset_m * sign  # n.x + d = 0: the plane's point along n is -d n from the origin
    sigma = np.sqrt(np.clip(np.diag(model.covariance), 0.0, None))
    return tilt, Z95 * float(max(sigma[6], sigma[7])), height, Z95 * float(sigma[8])


def frames_of_result(document: Mapping[str, Any]) -> tuple[int, dict[str, int]]:
    """Frames a result document's poses fitted, and frames refused per gate (the first gate a pose failed).

    Reads each pose's full-frame fit (``poses[i].full_frame``: ``n_frames`` and ``gates.<name>.passed``);
    a document without them (a hand-eye or depthcal result) counts none.
    """
    fitted, refused = 0, dict[str, int]()
    poses = document.get("poses")
    for pose in poses if isinstance(poses, list) else []:
        fit = pose.get("full_frame") if isinstance(pose, Mapping) else None
        if not isinstance(fit, Mapping) or not isinstance(fit.get("gates"), Mapping):
            continue
        frames = fit.get("n_frames")
        frames = frames if isinstance(frames, int) and frames > 0 else 1
        failed = [name for name, gate in fit["gates"].items() if isinstance(gate, Mapping) and not gate.get("passed")]
        if failed:
            refused[str(failed[0])[:_MAX_LABEL]] = refused.get(str(failed[0])[:_MAX_LABEL], 0) + frames
        else:
            fitted += frames
    return fitted, refused


class _PlaneCollector:
    """Each flange camera's plane figures, computed at scrape time from its current calibration."""

    def __init__(self, cells: Mapping[str, Any]) -> None:
        self.cells = cells

    def describe(self) -> list[Metric]:
        return list(self._families())

    def _families(self) -> tuple[GaugeMetricFamily, ...]:
        labels = ["cell", "camera"]
        return (GaugeMetricFamily("cellcal_plane_tilt_rad", "angle between the current plane's normal (base frame) "
                                  "and the configured reference normal, rad", labels=labels),
                GaugeMetricFamily("cellcal_plane_tilt_halfwidth_rad", "95 % half-width of the plane's tilt (the "
                                  "larger of its two axes), rad", labels=labels),
                GaugeMetricFamily("cellcal_plane_height_m", "signed distance of the current plane from the base "
                                  "origin along its normal (oriented as the reference normal), m", labels=labels),
                GaugeMetricFamily("cellcal_plane_height_halfwidth_m", "95 % half-width of the plane's height, m",
                                  labels=labels))

    def collect(self) -> Iterator[Metric]:
        families = self._families()
        for cell in self.cells.values():
            for name, config in cell.configs.items():
                if config.camera_entry.on != "flange":
                    continue
                try:
                    calibration = cell.calibration(name)
                except Exception as exc:  # an unreadable result: no figures for it, the scrape goes on
                    log.warning("metrics: %s/%s: %s", cell.name, name, exc)
                    continue
                if calibration is None:
                    continue
                reference = config.reference.plane_normal if config.reference is not None else None
                for family, value in zip(families, plane_figures(calibration, reference), strict=True):
                    family.add_metric([cell.name, name], value)
        yield from families


class ServiceMetrics:
    """The metrics of one service, in a registry of its own (no process-wide state).

    Args:
        cells: The service's cells (:class:`~cellcal.core.service.cell.CellService` by name).
        version: cellcal's version, for the info gauge.
    """

    def __init__(self, cells: Mapping[str, Any], version: str) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.info = Gauge("cellcal_service_info", "the service is up: cellcal's version, one series per cell",
                          ["version", "cell"], registry=r)
        self.runs = Counter("cellcal_runs", "runs ended, by kind and status", ["cell", "kind", "status"], registry=r)
        self.run_duration = Histogram("cellcal_run_duration_seconds", "a run's time from its start to its end, s",
                                      ["cell", "kind", "status"], buckets=RUN_BUCKETS_S, registry=r)
        self.active = Gauge("cellcal_runs_active", "runs in progress (0 or 1 per cell)", ["cell"], registry=r)
        self.drift = Counter("cellcal_drift_events", "drift events published, by kind", ["cell", "camera", "kind"],
                             registry=r)
        self.fitted = Counter("cellcal_frames_fitted", "frames whose full-frame fit passed every gate (in the "
                              "results of the service's runs, and tracked)", ["cell", "camera"], registry=r)
        self.refused = Counter("cellcal_frames_refused", "frames whose full-frame fit failed a gate (the first "
                               "failed)", ["cell", "camera", "gate"], registry=r)
        self.history_failures = Counter("cellcal_history_failures", "history writes that failed (the service "
                                        "went on)", registry=r)
        r.register(_PlaneCollector(cells))
        for cell in cells.values():  # every series a dashboard queries exists from the start
            self.info.labels(version, cell.name).set(1)
            self.active.labels(cell.name).set(0)
            for kind in KINDS:
                for status in STATES[2:]:
                    self.runs.labels(cell.name, kind, status)
                    self.run_duration.labels(cell.name, kind, status)
            for camera in cell.configs:
                self.fitted.labels(cell.name, camera)
                for kind in DRIFT_KINDS:
                    self.drift.labels(cell.name, camera, kind)
                for gate in GATE_NAMES:
                    self.refused.labels(cell.name, camera, gate)

    def run_started(self, cell: str) -> None:
        """A run started on ``cell``."""
        self.active.labels(cell).inc()

    def run_ended(self, cell: str, camera: str, kind: str, status: str, duration_s: float | None,
                  result: Mapping[str, Any] | None) -> None:
        """A run ended: counted, its duration observed, its result's frames counted."""
        self.active.labels(cell).dec()
        self.runs.labels(cell, kind, status).inc()
        if duration_s is not None and math.isfinite(duration_s) and duration_s >= 0.0:
            self.run_duration.labels(cell, kind, status).observe(duration_s)
        if result is not None:
            fitted, refused = frames_of_result(result)
            self.fitted.labels(cell, camera).inc(fitted)
            for gate, frames in refused.items():
                self.refused.labels(cell, camera, gate).inc(frames)

    def event(self, type_: str, data: Mapping[str, Any]) -> None:
        """An event published on the bus: a drift event (``drift.<kind>``) is counted."""
        if not type_.startswith(DRIFT_PREFIX):
            return
        kind = type_[len(DRIFT_PREFIX):][:_MAX_LABEL] or "unknown"
        self.drift.labels(str(data.get("cell", ""))[:_MAX_LABEL], str(data.get("camera", ""))[:_MAX_LABEL],
                          kind).inc()

    def exposition(self) -> bytes:
        """The registry in Prometheus' text format."""
        return generate_latest(self.registry)
