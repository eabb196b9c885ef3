"""The ``handeye.json`` document (schema ``cellcal.handeye/1``) and its terminal report.

The mount is given as in the ``[mount]`` table (``translation_m``, ``rpy_deg``) with
1-sigma and intervals; the plane in the base frame; per-pose residuals; the
observability report; and the difference from the configured mount. ``[mount]
from_handeye = "handeye.json"`` in a cell configuration reads it back.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from cellcal.core.calibration.report import ABOVE_NOTE, plane_height_mm
from cellcal.core.handeye.estimator import HandEyeEstimate, rpy_with_sigma_deg
from cellcal.devices.pose import Pose

#: Schema of the document (``[mount] from_handeye`` accepts ``cellcal.handeye/*``).
HANDEYE_SCHEMA = "cellcal.handeye/1"
HANDEYE_FILENAME = "handeye.json"


def _interval(value: np.ndarray, sigma: np.ndarray, z: float) -> list[list[float]]:
    """``[[lo, hi], ...]`` of ``value ± z sigma``."""
    return [[float(v - z * s), float(v + z * s)] for v, s in zip(value, sigma, strict=True)]


def mount_difference(estimated: Pose, configured: Pose) -> dict[str, Any]:
    """How far the estimated mount is from the configured one (translation in the flange frame, m; angle, deg)."""
    delta = configured.inv() @ estimated  # the estimated camera in the configured camera's frame
    return {"translation_m": (estimated.translation - configured.translation).tolist(),
            "distance_m": float(np.linalg.norm(estimated.translation - configured.translation)),
            "rotation_deg": math.degrees(float(np.linalg.norm(delta.rotation.as_rotvec())))}


def interval_z(confidence: float) -> float:
    """Half-width of a two-sided interval at ``confidence``, in sigmas."""
    from scipy.stats import norm

    return float(norm.ppf(0.5 + confidence / 2.0))


def mount_section(mount: Pose, covariance: np.ndarray, confidence: float, *, z: float | None = None,
                  interval_scale: float = 1.0) -> dict[str, Any]:
    """The ``mount`` entry: value, 1-sigma and intervals as in ``[mount]``; the rotation's sigma per flange axis.

    Args:
        mount: ``T_flange_camera``.
        covariance: 6x6 of (turn about the flange x, y, z, rad; translation, m), as the intervals use it.
        confidence: Level of the intervals.
        z: Half-width of the intervals in sigmas (default: the normal quantile of ``confidence``).
        interval_scale: Factor the residuals put on the stated noise's sigmas (1: the stated noise holds).
    """
    z = interval_z(confidence) if z is None else z
    t = mount.translation
    t_sigma = np.sqrt(np.diag(covariance)[3:6])
    rpy, rpy_sigma = rpy_with_sigma_deg(mount, covariance[:3, :3])
    return {"translation_m": t.tolist(), "rpy_deg": rpy.tolist(),
            "translation_sigma_m": t_sigma.tolist(), "rpy_sigma_deg": rpy_sigma.tolist(),
            "translation_ci_m": _interval(t, t_sigma, z), "rpy_ci_deg": _interval(rpy, rpy_sigma, z),
            "rotation_sigma_deg_about_flange_xyz": np.degrees(np.sqrt(np.diag(covariance)[:3])).tolist(),
            "confidence": confidence, "interval_z": z, "interval_scale": interval_scale, "pose": mount.to_dict()}


def plane_sections(estimate: HandEyeEstimate, flanges: Sequence[Pose]) -> dict[str, Any]:
    """The plane method's entries: the base-frame plane, the fit (with its noise verdict and notes),
    observability and per-pose residuals."""
    cov = estimate.covariance
    poses = [{"index": i, "reported_flange_pose": f.to_dict(), "residual": {
        "normal_deg": r.normal_deg, "offset_m": r.offset_m, "chi2": r.chi2}}
        for i, (f, r) in enumerate(zip(flanges, estimate.residuals, strict=True))]
    return {"plane_base": {**estimate.plane.to_dict(), "offset_sigma_m": math.sqrt(cov[8, 8]),
                           "tilt_sigma_deg": np.degrees(np.sqrt(np.diag(cov)[6:8])).tolist()},
            "fit": estimate.to_dict(), "observability": estimate.observability.to_dict(), "poses": poses,
            **({} if estimate.error_budget is None else {"error_budget": estimate.error_budget})}


def handeye_document(mount: Pose, covariance: np.ndarray, confidence: float, configured: Pose, *,
                     header: Mapping[str, Any], sections: Mapping[str, Any], z: float | None = None,
                     interval_scale: float = 1.0) -> dict[str, Any]:
    """The ``handeye.json`` document.

    Args:
        mount: The estimated ``T_flange_camera``; covariance: 6x6 as in :func:`mount_section`.
        confidence: Level of the intervals; z, interval_scale: as in :func:`mount_section`.
        configured: The configured ``[mount]``.
        header: Provenance (version, time, config source, plan kind, method).
        sections: The method's entries (:func:`plane_sections`, the ChArUco results, the comparison).
    """
    mount_entry = mount_section(mount, covariance, confidence, z=z, interval_scale=interval_scale)
    return {"schema": HANDEYE_SCHEMA, **header, "mount": mount_entry,
            "configured_mount": {"translation_m": configured.translation.tolist(),
                                 "rpy_deg": np.degrees(configured.as_xyz_rpy()[3:]).tolist()},
            "difference_from_configured": mount_difference(mount, configured), **sections}


def _triple(values: Sequence[float], spec: str) -> str:
    return "[" + ", ".join(format(float(v), spec) for v in values) + "]"


def mount_table(document: Mapping[str, Any]) -> str:
    """A ``[mount]`` table of the estimate, ready to paste into a cell configuration."""
    mount = document["mount"]
    return "\n".join([
        "[mount]",
        f"translation_m = {_triple(mount['translation_m'], '.6f')}",
        f"rpy_deg = {_triple(mount['rpy_deg'], '.5f')}",
    ])


def _plane_lines(document: Mapping[str, Any], z: float) -> list[str]:
    """The plane method's lines of the report (empty for a ChArUco-only document)."""
    if "plane_base" not in document:
        return []
    plane, fit, seen = document["plane_base"], document["fit"], document["observability"]
    worst = max(document["poses"], key=lambda p: p["residual"]["chi2"])
    p_value = "n/a" if fit["p_value"] is None or math.isnan(fit["p_value"]) else f"{fit['p_value']:.2g}"
    return [f"plane (base frame): normal {_triple(plane['normal'], '.6f')}, {plane_height_mm(plane):+.3f} mm "
            f"± {1000 * plane['offset_sigma_m'] * z:.3f} mm above the base origin",
            ABOVE_NOTE,
            f"fit: chi2 {fit['chi2']:.1f} over {fit['dof']} dof (p = {p_value}); {seen['rank']}/"
            f"{seen['n_parameters']} parameters observable, condition {seen['condition']:.3g}",
            f"residuals: largest at pose {worst['index'] + 1}: normal {worst['residual']['normal_deg']:.4f} deg, "
            f"camera distance {1000 * worst['residual']['offset_m']:+.3f} mm (measured - predicted; "
            f"chi2 {worst['residual']['chi2']:.1f})",
            *(f"note: {note}" for note in fit.get("notes", []))]


def format_report(document: Mapping[str, Any]) -> str:
    """The terminal report: the estimate with intervals, fit, residuals, difference, the ``[mount]`` table."""
    m = document["mount"]
    z = m["interval_z"]
    scale = m.get("interval_scale", 1.0)
    scaled = f", scaled by {scale:.2f} for the residuals (see note)" if scale > 1.0 else ""
    lines = [f"mount (camera in the flange frame) by the {document['method']} method, "
             f"{round(100 * m['confidence'])} % intervals{scaled}:"]
    for axis, value, sigma in zip("xyz", m["translation_m"], m["translation_sigma_m"], strict=True):
        lines.append(f"  t{axis}    {1000 * value:+10.3f} mm  ± {1000 * sigma * z:.3f} mm")
    for name, value, sigma in zip(("roll", "pitch", "yaw"), m["rpy_deg"], m["rpy_sigma_deg"], strict=True):
        lines.append(f"  {name:<5} {value:+10.4f} deg ± {sigma * z:.4f} deg")
    lines += _plane_lines(document, z)
    lines += document.get("report_lines", [])
    diff = document["difference_from_configured"]
    lines.append(f"from the configured [mount]: {1000 * diff['distance_m']:.3f} mm "
                 f"({_triple([1000 * v for v in diff['translation_m']], '+.3f')} mm), {diff['rotation_deg']:.4f} deg")
    lines += ["", mount_table(document)]
    return "\n".join(lines)


__all__ = ["HANDEYE_FILENAME", "HANDEYE_SCHEMA", "format_report", "handeye_document", "interval_z",
           "mount_difference", "mount_section", "mount_table", "plane_sections"]
