"""Baselines of ``cellcal monitor``: its own baseline files, or a calibration result's plane."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from cellcal.core.calibration.calibrator import build_devices
from cellcal.core.calibration.config import CellConfig
from cellcal.core.calibration.report import write_json_atomic
from cellcal.core.geometry.planes import Plane
from cellcal.core.monitor.monitor import CameraSummary, MonitoredCamera
from cellcal.core.monitor.samples import Baseline
from cellcal.devices import boundedjson
from cellcal.devices.arm import RobotArm
from cellcal.devices.errors import CalibrationError, ConfigError

__all__ = [
    "BASELINE_SCHEMA",
    "CALIBRATION_SCHEMA_PREFIX",
    "baseline_from_result",
    "consensus_plane",
    "is_calibration_result",
    "monitored_cameras",
    "read_baseline_file",
    "read_baselines",
    "write_baselines",
]

#: Schema tag of the monitor's baseline file (``cellcal monitor --save-baseline``).
BASELINE_SCHEMA = "cellcal.monitor-baseline/1"
#: Schema tags of ``cellcal calibrate`` results start with this.
CALIBRATION_SCHEMA_PREFIX = "cellcal.calibration/"


def read_baseline_file(path: str) -> Any:
    """A JSON document from a file.

    Raises:
        ConfigError: Missing or unreadable file, invalid JSON.
    """
    try:
        return boundedjson.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError("baseline file not found", source=path) from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ConfigError(f"cannot read baseline file: {exc}", source=path) from None


def is_calibration_result(doc: Any) -> bool:
    """Whether a JSON document is a ``cellcal calibrate`` result."""
    return isinstance(doc, dict) and str(doc.get("schema", "")).startswith(CALIBRATION_SCHEMA_PREFIX)


def consensus_plane(doc: Mapping[str, Any], path: str) -> Plane:
    """The calibrated plane in the base frame of a calibration result.

    Raises:
        ConfigError: If the result has no usable ``summary.plane_consistency.consensus_plane_base``.
    """
    key = "summary.plane_consistency.consensus_plane_base"
    try:
        table = doc["summary"]["plane_consistency"]["consensus_plane_base"]
        return Plane.from_dict(table)
    except (KeyError, TypeError, ValueError, CalibrationError):
        raise ConfigError("calibration result has no plane in the base frame (needs a [reference] plane "
                          "and a cellcal version that writes it)", source=path, key=key) from None


def baseline_from_result(doc: Mapping[str, Any], path: str, config: CellConfig, arm: RobotArm) -> Baseline:
    """The expected plane at the arm's current pose, from a calibration result.

    The arm is connected only to read its flange pose (nothing moves); the camera pose is
    that pose @ the configuration's ``[mount]``.

    Raises:
        ConfigError: If the result holds no plane in the base frame.
        DeviceError: If the arm cannot be reached.
    """
    plane = consensus_plane(doc, path)
    timeout = config.monitor.connect_timeout_s
    with arm.connect(timeout):
        flange = arm.get_pose(timeout)
    return Baseline.from_plane_in_base(plane, flange @ config.mount.pose())


def read_baselines(path: str, labels: Sequence[str], doc: Any = None) -> dict[str, Baseline]:
    """Baselines per label from a ``--save-baseline`` file (``doc``: its JSON, if already read).

    A file with a single camera applies to a single monitored camera whatever its label.

    Raises:
        ConfigError: Unreadable file, wrong schema, or no entry for a monitored camera.
    """
    doc = read_baseline_file(path) if doc is None else doc
    if not isinstance(doc, dict) or doc.get("schema") != BASELINE_SCHEMA:
        raise ConfigError(f"not a monitor baseline file or calibration result (expected schema "
                          f"{BASELINE_SCHEMA!r} or {CALIBRATION_SCHEMA_PREFIX}N)", source=path)
    cams = doc.get("cameras")
    if not isinstance(cams, dict) or not cams:
        raise ConfigError("expected a non-empty table", source=path, key="cameras")
    if len(cams) == 1 and len(labels) == 1:
        ((key, only),) = cams.items()
        return {labels[0]: Baseline.from_dict(only, source=f"{path} (cameras.{key})")}
    out = {}
    for label in labels:
        if label not in cams:
            raise ConfigError(f"no baseline for camera {label!r} (has: {', '.join(sorted(cams))})", source=path)
        out[label] = Baseline.from_dict(cams[label], source=f"{path} (cameras.{label})")
    return out


def write_baselines(path: str | Path, cameras: Sequence[CameraSummary]) -> Path:
    """Write the established baselines (cameras without one are left out); returns the path written."""
    doc = {"schema": BASELINE_SCHEMA,
           "cameras": {c.label: c.baseline.to_dict() for c in cameras if c.baseline is not None}}
    return write_json_atomic(path, doc)


def monitored_cameras(configs: Sequence[tuple[str, CellConfig]], baseline_path: str | None = None
                      ) -> list[MonitoredCamera]:
    """The camera of each labelled configuration, with its baseline from ``baseline_path`` if given.

    ``baseline_path`` is a :func:`write_baselines` file, or a calibration result (then
    for one camera only: its plane in the base frame, seen from the arm's current pose;
    the arm is connected only to read that pose). Without it, each monitor measures
    its baseline from the first frames.

    Raises:
        ConfigError: Bad baseline file, a calibration result for several cameras, or a
            backend that rejects its section.
        DeviceError: If an arm cannot be reached to read its pose.
    """
    doc = read_baseline_file(baseline_path) if baseline_path else None
    from_result = is_calibration_result(doc)
    if from_result and len(configs) > 1:
        raise ConfigError("a calibration result is the baseline of one camera: give one --config, or use a "
                          "--save-baseline file for several", source=baseline_path)
    labels = [label for label, _ in configs]
    baselines = read_baselines(baseline_path, labels, doc) if baseline_path and not from_result else {}
    specs = []
    for label, config in configs:
        camera, arm = build_devices(config)  # the arm is at most connected to read its pose
        if from_result and baseline_path and isinstance(doc, dict):
            baselines[label] = baseline_from_result(doc, baseline_path, config, arm)
        specs.append(MonitoredCamera(label, camera, config.monitor, config.full_frame, baselines.get(label)))
    return specs
