"""A camera's current calibration as the service knows it: read from its output directory's result files.

``DIR/result.json`` (``cellcal calibrate``: the consensus plane in the base frame with its
interval, the mount the run used, the camera's intrinsics) and ``DIR/handeye.json``
(``cellcal handeye``: the mount and the plane estimated together, their 9x9 covariance) are
read with the project's readers; the newer of the two (``created_utc``) is the current
calibration. The intrinsics come from ``result.json`` when there is one, else from the
configuration (a camera whose configuration fixes them).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cellcal.core.calibration.report import RESULT_FILENAME
from cellcal.core.handeye.result import HANDEYE_FILENAME, HANDEYE_SCHEMA
from cellcal.core.service.planepoint import PlaneCalibration
from cellcal.devices import boundedjson
from cellcal.devices.errors import CalibrationError, ConfigError
from cellcal.devices.pose import Pose
from cellcal.devices.types import Intrinsics

__all__ = ["MAX_RESULT_BYTES", "Z95", "CameraCalibration", "read_calibration"]

#: Largest result file read, bytes.
MAX_RESULT_BYTES = 50 << 20
#: Half-width of a two-sided 95 % interval, in sigmas.
Z95 = 1.959963984540054


@dataclass(frozen=True, eq=False)
class CameraCalibration:
    """One camera's current calibration.

    Attributes:
        kind: ``"handeye"`` or ``"calibrate"``: the run that wrote it.
        path: The file it was read from.
        created_utc: When that run started (ISO 8601), "" if the file does not say.
        estimated_mount: Whether the mount is an estimate with an interval (hand-eye), or the configured one.
        model: What ``pixel_to_base`` uses.
    """

    kind: str
    path: Path
    created_utc: str
    estimated_mount: bool
    model: PlaneCalibration

    def to_dict(self) -> dict[str, Any]:
        """JSON form: the plane (base frame) and the mount, 1-sigma and 95 % half-widths (SI; degrees for people)."""
        m = self.model
        cov = m.covariance
        sig = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        plane = m.plane
        return {
            "kind": self.kind, "file": str(self.path), "created_utc": self.created_utc, "confidence": 0.95,
            "plane_base": {"normal": list(plane.normal), "offset_m": plane.offset_m,
                           "anchor_m": m.anchor_m.tolist(), "tilt_sigma_rad": sig[6:8].tolist(),
                           "height_sigma_m": float(sig[8]),
                           "tilt_halfwidth_deg": np.degrees(Z95 * sig[6:8]).tolist(),
                           "height_halfwidth_m": float(Z95 * sig[8])},
            "mount": {**m.mount.to_dict(), "estimated": self.estimated_mount,
                      "rotation_sigma_rad": sig[0:3].tolist(), "translation_sigma_m": sig[3:6].tolist(),
                      "rotation_halfwidth_deg": np.degrees(Z95 * sig[0:3]).tolist(),
                      "translation_halfwidth_m": (Z95 * sig[3:6]).tolist()},
            "covariance": cov.tolist(),
            "parameters": ["mount_rot_x", "mount_rot_y", "mount_rot_z", "mount_x", "mount_y", "mount_z",
                           "plane_tilt_a", "plane_tilt_b", "plane_height"],
            "intrinsics": {"width": m.intrinsics.width, "height": m.intrinsics.height, "model": m.intrinsics.model},
        }


def _read_json(path: Path) -> dict[str, Any] | None:
    """The JSON object of ``path``; None when there is no such file.

    Raises:
        ConfigError: Naming the file: too large, unreadable, or not a JSON object.
    """
    try:
        size = os.stat(path).st_size
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise ConfigError(f"cannot read: {exc.strerror or exc}", source=str(path)) from None
    if size > MAX_RESULT_BYTES:
        raise ConfigError(f"{size} bytes, more than the {MAX_RESULT_BYTES} a result may have", source=str(path))
    try:
        document = boundedjson.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ConfigError(f"not a readable JSON file: {exc}", source=str(path)) from None
    if not isinstance(document, dict):
        raise ConfigError("not a JSON object", source=str(path))
    return document


def _intrinsics(document: Mapping[str, Any] | None) -> Intrinsics | None:
    """The camera intrinsics a calibrate result recorded (its first pose's), or None."""
    poses = (document or {}).get("poses")
    data = poses[0].get("camera_intrinsics") if isinstance(poses, list) and poses and isinstance(
        poses[0], Mapping) else None
    if not isinstance(data, Mapping):
        return None
    try:
        return Intrinsics(**data)
    except (TypeError, ValueError, CalibrationError):
        return None


def _from_result(document: Mapping[str, Any], path: Path, intrinsics: Intrinsics) -> CameraCalibration:
    """A ``cellcal calibrate`` result: its consensus plane with its interval, the mount it used (no interval)."""
    from cellcal.core.monitor.baselines import consensus_plane, is_calibration_result

    if not is_calibration_result(document):
        raise ConfigError("not a cellcal calibrate result", source=str(path))
    plane = consensus_plane(document, str(path))
    consistency = document["summary"]["plane_consistency"]
    interval = consistency.get("consensus_interval") or {}
    try:
        mount = Pose.from_dict(document["mount"])
        anchor = plane.project_points(np.asarray(consistency["reference_point_m"], dtype=np.float64))
        normal_sigma = math.radians(float(interval.get("normal_sigma_deg") or 0.0))
        height_sigma = float(interval.get("height_sigma_m") or 0.0)
    except (KeyError, TypeError, ValueError, CalibrationError) as exc:
        raise ConfigError(f"a malformed calibrate result ({type(exc).__name__}: {exc})", source=str(path)) from None
    cov = np.zeros((9, 9))
    cov[6, 6] = cov[7, 7] = normal_sigma**2 / 2.0  # an RMS angle of an isotropic tilt: half its square per axis
    cov[8, 8] = height_sigma**2
    return CameraCalibration("calibrate", path, str(document.get("created_utc", "")), False,
                             PlaneCalibration(intrinsics, mount, plane, anchor, cov))


def _from_handeye(document: Mapping[str, Any], path: Path, intrinsics: Intrinsics) -> CameraCalibration:
    """A ``cellcal handeye`` result (plane method): the mount and plane with their joint 9x9 covariance.

    The fit's plane parameters are tilts about the axes across the configured normal with the offset
    kept; here they are taken about the estimated normal's axes (the same to first order), turning
    about the plane's point nearest the base origin, and the offset's step becomes a height step of
    the opposite sign.
    """
    from cellcal.core.handeye.relate import camera_result

    if document.get("schema") != HANDEYE_SCHEMA:
        raise ConfigError("not a hand-eye result of a camera on the flange", source=str(path))
    result = camera_result(document, str(path))  # checks the pose, the plane and the 9x9 covariance
    assert result.plane is not None
    cov = np.asarray(document["fit"]["covariance"], dtype=np.float64).copy()
    cov[8, :] *= -1.0  # offset step -> height step along the normal
    cov[:, 8] *= -1.0
    plane = result.plane[0]
    anchor = -plane.offset_m * np.asarray(plane.normal)  # the plane's point nearest the origin
    return CameraCalibration("handeye", path, str(document.get("created_utc", "")), True,
                             PlaneCalibration(intrinsics, result.pose.pose, plane, anchor, cov))


def read_calibration(directory: Path, configured_intrinsics: Callable[[], Intrinsics | None]
                     ) -> CameraCalibration | None:
    """The current calibration of the camera whose runs write into ``directory``; None if it has none yet.

    Args:
        directory: The camera's output directory (``result.json``, ``handeye.json``).
        configured_intrinsics: The intrinsics the configuration fixes (asked only when no result.json has them).

    Raises:
        ConfigError: A result file that is unreadable or malformed, or no intrinsics known.
    """
    result = _read_json(directory / RESULT_FILENAME)
    handeye = _read_json(directory / HANDEYE_FILENAME)
    if result is None and handeye is None:
        return None
    intrinsics = _intrinsics(result) or configured_intrinsics()
    if intrinsics is None:
        raise ConfigError("no camera intrinsics known: the configuration does not fix them and no calibrate "
                          "result recorded them (run calibrate)", source=str(directory))
    found = []
    if result is not None:
        found.append(_from_result(result, directory / RESULT_FILENAME, intrinsics))
    if handeye is not None:
        found.append(_from_handeye(handeye, directory / HANDEYE_FILENAME, intrinsics))
    return max(found, key=lambda c: (c.created_utc, c.kind == "handeye"))  # the newest; a tie: the estimate
