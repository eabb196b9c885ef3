"""The service's metrics: the plane's figures from a calibration, frames from a result, a registry per service."""

from __future__ import annotations

import math
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("prometheus_client")

from prometheus_client.parser import text_string_to_metric_families

from cellcal.core.geometry.planes import Plane
from cellcal.core.service import Service
from cellcal.core.service.calibration import Z95, CameraCalibration
from cellcal.core.service.metrics import frames_of_result, plane_figures
from cellcal.core.service.planepoint import PlaneCalibration
from cellcal.devices.pose import Pose
from cellcal.devices.types import Intrinsics

SIM_TOML = resources.files("cellcal.configs").joinpath("sim.toml").read_text()


def calibration(normal: np.ndarray, offset_m: float, sigmas: tuple[float, float, float]) -> CameraCalibration:
    """A calibration whose plane is ``normal . x + offset_m = 0`` with tilt and height sigmas (rad, rad, m)."""
    intrinsics = Intrinsics(width=224, height=172, fx=194.0, fy=207.6, cx=111.5, cy=85.5)
    cov = np.zeros((9, 9))
    cov[6, 6], cov[7, 7], cov[8, 8] = (s**2 for s in sigmas)
    plane = Plane(normal, offset_m)
    model = PlaneCalibration(intrinsics, Pose.identity(), plane, -offset_m * np.asarray(plane.normal), cov)
    return CameraCalibration("handeye", Path("handeye.json"), "2024-05-01T10:00:00+00:00", True, model)


def test_the_plane_figures_are_its_tilt_from_the_reference_and_its_height_with_their_half_widths() -> None:
    tilt = 0.02  # rad about base x
    normal = np.array([0.0, -math.sin(tilt), math.cos(tilt)])
    found = calibration(normal, -0.1, (1e-3, 2e-3, 5e-4))  # the plane 0.1 m from the origin along its normal
    got = plane_figures(found, [0.0, 0.0, 1.0])
    assert got[0] == pytest.approx(tilt, abs=1e-12)
    assert got[1] == pytest.approx(Z95 * 2e-3, rel=1e-12)  # the larger tilt axis
    assert got[2] == pytest.approx(0.1, abs=1e-15)
    assert got[3] == pytest.approx(Z95 * 5e-4, rel=1e-12)
    # the reference the other way up: the same tilt (orientation ignored), the height seen from the other side
    flipped = plane_figures(found, [0.0, 0.0, -2.0])
    assert flipped[0] == pytest.approx(tilt, abs=1e-12) and flipped[2] == pytest.approx(-0.1, abs=1e-15)
    # no reference: base +z
    assert plane_figures(found)[0] == pytest.approx(tilt, abs=1e-12)


def test_frames_of_a_result_are_fitted_or_refused_by_their_first_failed_gate() -> None:
    passed = {"passed": True, "value": 1.0, "threshold": 0.5}
    document = {"poses": [
        {"full_frame": {"n_frames": 2, "gates": {"valid_fraction": passed, "coverage": passed}}},
        {"full_frame": {"n_frames": 3, "gates": {"valid_fraction": passed, "coverage": {"passed": False},
                                                 "flatness": {"passed": False}}}},
        {"full_frame": {"gates": {"inlier_fraction": {"passed": False}}}},  # no n_frames: one frame
        {"measurements": []},  # no full-frame fit: not counted
    ]}
    assert frames_of_result(document) == (2, {"coverage": 3, "inlier_fraction": 1})
    assert frames_of_result({"schema": "cellcal.handeye/1"}) == (0, {})


def samples(service: Service) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    """Every sample of the service's exposition: (name, sorted labels) -> value."""
    assert service.metrics is not None
    text = service.metrics.exposition().decode()
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for family in text_string_to_metric_families(text) for s in family.samples}


def test_each_service_has_its_own_registry_and_counts_its_own_drift_events(tmp_path: Path) -> None:
    config = tmp_path / "sim.toml"
    config.write_text(SIM_TOML)
    first, second = (Service([config], tmp_path / name) for name in ("a", "b"))
    try:
        first.bus.publish("drift.mount", {"cell": "paper-sim", "camera": "camera", "rotation_deg": 0.4})
        first.bus.publish("drift.mount", {"cell": "paper-sim", "camera": "camera"})
        first.bus.publish("run.progress", {"cell": "paper-sim", "camera": "camera"})  # not a drift event
        key = ("cellcal_drift_events_total", (("camera", "camera"), ("cell", "paper-sim"), ("kind", "mount")))
        assert samples(first)[key] == 2.0
        assert samples(second)[key] == 0.0  # created at zero, untouched by the other service
        info = [(dict(labels), value) for (name, labels), value in samples(second).items()
                if name == "cellcal_service_info"]
        assert len(info) == 1 and info[0][0]["cell"] == "paper-sim" and info[0][1] == 1.0
        # a camera without a calibration has no plane figures yet
        assert not any(name.startswith("cellcal_plane_") for name, _ in samples(first))
    finally:
        first.close()
        second.close()
