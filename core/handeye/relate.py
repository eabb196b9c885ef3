"""Several cameras' calibrations together: every pair's transform with intervals, and whether their planes agree.

Reads ``cellcal handeye`` results: a camera on the flange (``handeye.json``: the mount
``T_flange_camera``, the base-frame plane, their 9x9 covariance) and a fixed camera
(``handeye-NAME.json``: ``T_base_camera``, its 6x6 covariance, the measuring plane it saw). Cameras
with the same parent (two on the flange, two fixed) get their relative transform
``T_a_b = T_a⁻¹ T_b`` with first-order covariance (:func:`~cellcal.core.geometry.relative.relative_pose`,
the calibrations taken as independent); every camera that measured the plane in the base frame
enters :func:`~cellcal.core.geometry.relative.plane_agreement` (ADR 0061).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from cellcal.core.geometry.planes import Plane
from cellcal.core.geometry.relative import PoseWithCovariance, plane_agreement, relative_pose
from cellcal.devices.errors import ConfigError
from cellcal.devices.pose import Pose

__all__ = ["CameraResult", "camera_result", "relate"]


@dataclass(frozen=True)
class CameraResult:
    """One camera's calibration as :func:`relate` takes it.

    Attributes:
        name: The camera's name.
        on: ``"flange"`` (``pose`` is ``T_flange_camera``) or ``"base"`` (``T_base_camera``).
        pose: Its pose with the 6x6 covariance (turn about the parent's axes, rad; shift, m).
        plane: The measuring plane in the base frame and its 3x3 (tilt a, tilt b, offset) covariance, if measured.
        source: The file it came from.
    """

    name: str
    on: str
    pose: PoseWithCovariance
    plane: tuple[Plane, np.ndarray] | None
    source: str


def _matrix(value: object, n: int, what: str, source: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64) if isinstance(value, list) else np.zeros(0)
    if arr.shape != (n, n) or not np.all(np.isfinite(arr)):
        raise ConfigError(f"needs a finite {n}x{n} {what}", source=source)
    return arr


def camera_result(document: Mapping[str, Any], source: str) -> CameraResult:
    """A flange camera's ``handeye.json`` or a fixed camera's ``handeye-NAME.json`` as a :class:`CameraResult`.

    Raises:
        ConfigError: Naming the file: not a hand-eye result of the plane method, or a malformed pose or covariance.
    """
    from cellcal.core.handeye.fixed_run import FIXED_SCHEMA
    from cellcal.core.handeye.result import HANDEYE_SCHEMA

    schema = str(document.get("schema", ""))
    name = str(document.get("camera") or "camera")
    try:
        if schema == FIXED_SCHEMA:
            pose = PoseWithCovariance(Pose.from_dict(document["camera_base"]),
                                      _matrix(document["covariance"], 6, "camera covariance", source))
            table = document.get("measuring_plane")
            plane = None
            if isinstance(table, Mapping) and "plane_base" in table:
                plane = (Plane.from_dict(table["plane_base"]), _matrix(table["covariance"], 3, "plane covariance",
                                                                       source))
            return CameraResult(name, "base", pose, plane, source)
        if schema == HANDEYE_SCHEMA and isinstance(document.get("fit"), Mapping):
            cov = _matrix(document["fit"].get("covariance"), 9, "fit covariance", source)
            pose = PoseWithCovariance(Pose.from_dict(document["mount"]["pose"]), cov[:6, :6])
            plane_table = document["plane_base"]
            plane_base = Plane(np.asarray(plane_table["normal"], dtype=np.float64), float(plane_table["offset_m"]))
            return CameraResult(name, "flange", pose, (plane_base, cov[6:, 6:]), source)
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"a malformed hand-eye result ({type(exc).__name__}: {exc})", source=source) from None
    raise ConfigError(f"not a hand-eye result of the plane method (schema {schema!r}): give handeye.json or "
                      "handeye-NAME.json files", source=source)


def _pose_entry(pose: PoseWithCovariance, confidence: float) -> dict[str, Any]:
    turn, shift = pose.half_widths(confidence)
    return {"translation_m": [float(v) for v in pose.pose.translation],
            "rpy_deg": [float(v) for v in np.degrees(pose.pose.as_xyz_rpy()[3:])],
            "translation_half_width_m": [float(v) for v in shift],
            "turn_half_width_deg": [float(v) for v in np.degrees(turn)],
            "covariance": pose.covariance.tolist()}


def relate(cameras: Sequence[CameraResult], confidence: float = 0.95) -> dict[str, Any]:
    """Every same-parent pair's transform and the planes' agreement (JSON; SI, and degrees for people).

    Raises:
        ConfigError: Fewer than two cameras, or two with one name.
    """
    names = [c.name for c in cameras]
    if len(cameras) < 2:
        raise ConfigError("needs the results of two or more cameras")
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise ConfigError(f"two results for camera {dupes[0]!r}: give each camera once")
    pairs = []
    for i, a in enumerate(cameras):
        for b in cameras[i + 1:]:
            if a.on != b.on:
                continue  # a flange camera and a fixed one: their transform changes with the arm's pose
            rel = relative_pose(a.pose, b.pose)
            pairs.append({"from": a.name, "to": b.name, "parent": a.on, **_pose_entry(rel, confidence)})
    planes = {c.name: c.plane for c in cameras if c.plane is not None}
    agreement = None
    if len(planes) >= 2:
        result = plane_agreement(planes, confidence=confidence)
        agreement = {"agree": result.agree, "message": result.message(), "outlier": result.outlier,
                     "p_value": float(result.p_value), "cameras": sorted(planes)}
    return {"schema": "cellcal.cameras/1", "confidence": confidence,
            "cameras": [{"name": c.name, "on": c.on, "source": c.source, **_pose_entry(c.pose, confidence)}
                        for c in cameras],
            "pairs": pairs, "plane_agreement": agreement}


def format_relate(document: Mapping[str, Any]) -> str:
    """The terminal report of :func:`relate` (mm and degrees)."""
    conf = 100 * document["confidence"]
    lines = [f"cameras ({conf:g} % intervals):"]
    for c in document["cameras"]:
        parent = "T_flange_camera" if c["on"] == "flange" else "T_base_camera"
        lines.append(f"  {c['name']}: {parent} " + _pose_text(c))
    for p in document["pairs"]:
        lines.append(f"  {p['from']} -> {p['to']} (both {'on the flange' if p['parent'] == 'flange' else 'fixed'}): "
                     + _pose_text(p))
    agreement = document["plane_agreement"]
    lines.append("measuring plane: " + ("fewer than two cameras measured it" if agreement is None
                                        else agreement["message"]))
    return "\n".join(lines)


def _pose_text(entry: Mapping[str, Any]) -> str:
    t = " ".join(f"{1000 * v:+.2f}±{1000 * h:.2f}" for v, h in zip(entry["translation_m"],
                                                                    entry["translation_half_width_m"], strict=True))
    r = " ".join(f"{v:+.3f}" for v in entry["rpy_deg"])
    h = "/".join(f"{v:.3f}" for v in entry["turn_half_width_deg"])
    return f"xyz {t} mm, rpy {r} deg (turns ±{h} deg)" if math.isfinite(sum(entry["rpy_deg"])) else t
