"""Calibration results: the versioned JSON document, atomic writing, and the summary table.

The document's schema is :data:`RESULT_SCHEMA` (what changed from ``/1``: ADR 0008).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile
from collections import defaultdict
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from cellcal.core.calibration.budget import budget_line, error_budget, pose_budget_line
from cellcal.core.geometry.consistency import PosePlane, noise_shifts, plane_consistency
from cellcal.core.geometry.planes import Plane
from cellcal.devices.arm_model import ArmModel
from cellcal.devices.errors import CalibrationError, OutputError
from cellcal.devices.jsonsafe import json_safe
from cellcal.devices.pose import Pose

#: Version of the result document; bump on any incompatible change.
RESULT_SCHEMA = "cellcal.calibration/2"
RESULT_FILENAME = "result.json"
#: What "above" means in the summaries, said once per output: heights in mm along a plane's normal (ADR 0042).
ABOVE_NOTE = ("note: 'above' is the signed distance along the plane's normal, in mm (+ where the normal points); "
              "the JSON files keep SI: a plane's offset_m is minus its height above the base origin, in m")


def write_json_atomic(path: str | Path, document: Mapping[str, Any]) -> Path:
    """Write JSON to ``path`` atomically (see :func:`write_bytes_atomic`), cleaned by :func:`json_safe`.

    Raises:
        OutputError: If the directory cannot be created or written.
        TypeError: If ``document`` holds an object that is not JSON data (nothing is written).
    """
    text = json.dumps(json_safe(document), indent=2, allow_nan=False) + "\n"
    return write_bytes_atomic(path, text.encode("utf-8"))


def write_bytes_atomic(path: str | Path, data: bytes, *, fsync_dir: bool = False) -> Path:
    """Write bytes to ``path`` atomically: a temp file in the same directory, fsync, rename.

    An earlier file at ``path`` is replaced only once the new one is complete, and
    no temporary file is left behind on failure. The file gets mode 0644.

    Args:
        path: The file to write.
        data: Its whole content.
        fsync_dir: Also fsync the directory after the rename, so the new directory
            entry itself survives a power loss (the resume journal needs that; a
            filesystem that cannot fsync a directory is tolerated).

    Raises:
        OutputError: If the directory cannot be created or written (disk full, no permission ...).
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise OutputError(f"cannot write {path}: {exc.strerror or exc}", errno=exc.errno) from None
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o644)  # mkstemp makes it 0600; a result file is for everyone to read
        os.replace(tmp, path)
    except BaseException as exc:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise OutputError(f"cannot write {path}: {exc.strerror or exc}", errno=exc.errno) from None
        raise
    if fsync_dir:
        _fsync_dir(path.parent)
    return path


def _fsync_dir(directory: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def summarize(rows: Iterable[Mapping[str, Any]]) -> dict[str, Any]:
    """Mean absolute angle error (%) and mean angle by method: overall, per pose and per perimeter.

    Args:
        rows: Flat measurement rows with keys ``method``, ``pose_index`` (0-based),
            ``perimeter_px`` (None for a method without perimeter: no "P px" group),
            ``angle_deg`` and (optionally) ``error_pct``.

    Returns:
        ``{method: {"all" | "pose N" | "P px": {n, mean_angle_deg, mean_error_pct, max_error_pct}}}``.
    """
    groups: dict[str, dict[str, list[Mapping[str, Any]]]] = defaultdict(lambda: defaultdict(list))
    for row in rows:
        m = row["method"]
        groups[m]["all"].append(row)
        groups[m][f"pose {row['pose_index'] + 1}"].append(row)
        if row.get("perimeter_px") is not None:
            groups[m][f"{row['perimeter_px']} px"].append(row)
    out: dict[str, Any] = {}
    for method, by in groups.items():
        out[method] = {}
        for key, items in by.items():
            errs = [r["error_pct"] for r in items if r.get("error_pct") is not None]
            angles = [r["angle_deg"] for r in items]
            out[method][key] = {
                "n": len(items),
                "mean_angle_deg": sum(angles) / len(angles),
                "mean_error_pct": sum(errs) / len(errs) if errs else None,
                "max_error_pct": max(errs) if errs else None,
            }
    return out


def plane_height_mm(plane: Mapping[str, Any]) -> float:
    """A plane's height above the origin of its frame along its normal, mm: ``-offset_m`` of ``n·x + offset_m = 0``.

    The plane passes through ``height * normal``; with the normal up (+z) the height is the plane's z.
    """
    return -1000.0 * float(plane["offset_m"])


def format_table(rows: list[Mapping[str, Any]]) -> str:
    """A plain-text summary table: one line per pose x perimeter x method (heights in mm, angles in deg)."""
    header = (f"{'pose':>4} {'height_mm':>9} {'per_px':>6} {'method':<18} {'angle_deg':>9} {'expect':>7} "
              f"{'err_%':>6} {'tilt_x':>7} {'tilt_y':>7} {'rms_mm':>7}")
    lines = [header, "-" * len(header)]

    def f(v: Any, spec: str, width: int) -> str:
        return f"{v:{width}{spec}}" if isinstance(v, (int, float)) else f"{'-':>{width}}"

    for r in rows:
        rms, height = r.get("residual_rms_m"), r.get("height_m")
        per = "all" if r.get("perimeter_px") is None else r["perimeter_px"]
        lines.append(
            f"{r['pose_index'] + 1:>4} {f(None if height is None else height * 1000, '.1f', 9)} {per:>6} "
            f"{r['method']:<18} "
            f"{f(r['angle_deg'], '.3f', 9)} {f(r.get('expected_angle_deg'), '.2f', 7)} "
            f"{f(r.get('error_pct'), '.2f', 6)} {f(r.get('tilt_x_deg'), '.2f', 7)} {f(r.get('tilt_y_deg'), '.2f', 7)} "
            f"{f(None if rms is None else rms * 1000, '.2f', 7)}"
        )
    return "\n".join(lines)


# ---------------------------------------------------------------------- the plane in the base frame
def _pose_plane(pose: Mapping[str, Any], method: str) -> PosePlane | None:
    """The plane a pose record holds for ``method`` (``plane_fit``: at the largest perimeter)."""
    camera = Pose.from_dict(pose["camera_pose"])
    flange = Pose.from_dict(pose["reported_flange_pose"]) if pose.get("reported_flange_pose") else None
    if method == "full_frame":
        ff = pose.get("full_frame")
        if not ff:
            return None
        # the noise alone per pose and the systematic allowance's shifts, a coefficient common to the poses
        # (ADR 0055, "Poses combined"); an older document's covariance is taken as noise, without shifts
        cov = np.asarray(ff.get("noise_normal_covariance") or ff["normal_covariance"], dtype=np.float64)
        sigma = ff.get("noise_offset_sigma_m")
        if sigma is None:
            sigma = ff["plane_cam"].get("noise_offset_sigma_m", ff["plane_cam"].get("offset_sigma_m"))
        return PosePlane.from_camera(Plane.from_dict(ff["plane_cam"]), camera,
                                     normal_sigma_rad=float(np.sqrt(max(np.trace(cov), 0.0))),
                                     offset_sigma_m=sigma, shifts_cam=noise_shifts(ff), flange_in_base=flange)
    fits = [m for m in pose.get("measurements", []) if m["method"] == method and m.get("plane_cam")]
    if not fits:
        return None
    best = max(fits, key=lambda m: m["perimeter_px"] or 0)
    return PosePlane.from_camera(Plane.from_dict(best["plane_cam"]), camera, flange_in_base=flange)


def plane_summary(poses: Iterable[Mapping[str, Any]], reference: Plane | None = None, *,
                  arm: ArmModel | None = None) -> dict[str, Any] | None:
    """Consensus plane in the base frame and its consistency across poses, from pose records.

    Uses each pose's ``full_frame`` plane (or, when the method was not run, the
    ``plane_fit`` plane at the largest perimeter) and its ``camera_pose``; the spread is
    judged against the poses' noise, the differential part of the camera's systematic
    allowance and the arm's varying accuracy, the consensus's interval carries the common
    parts (``arm``: the arm's stated model, None: not counted; ADR 0055). Adds
    ``source_method`` and, with a ``reference`` plane (base frame), ``reference``: the
    angle between the consensus and reference normals (deg) and the consensus's height
    above the reference along the reference normal at the consensus reference point (m).

    Returns:
        The :meth:`PlaneConsistency.to_dict` form plus those keys; None when no pose
        holds a plane; ``{"source_method", "verdict": "failed", "interpretation"}`` when
        the planes are too far apart to be one plane (the run's data is still written).
    """
    pose_list = list(poses)
    for source in ("full_frame", "plane_fit"):
        planes = [pp for pp in (_pose_plane(p, source) for p in pose_list) if pp is not None]
        if planes:
            break
    else:
        return None
    try:
        result = plane_consistency(planes, arm=arm)
    except CalibrationError as exc:
        return {"source_method": source, "n_poses": len(planes), "verdict": "failed",
                "interpretation": f"{exc}: the hand-eye transform or the arm's pose readings are far off"}
    out: dict[str, Any] = {"source_method": source, **result.to_dict()}
    if reference is not None:
        n_ref = reference.normal if reference.normal @ result.consensus.normal >= 0 else -reference.normal
        cos = float(np.clip(n_ref @ result.consensus.normal, -1.0, 1.0))
        out["reference"] = {
            "angle_deg": math.degrees(math.acos(cos)),
            "height_m": float(np.sign(n_ref @ reference.normal) * reference.signed_distance(result.reference_point_m)),
        }
    return out


def summarize_poses(poses: Iterable[Mapping[str, Any]], reference: Plane | None = None, *,
                    arm: ArmModel | None = None) -> dict[str, Any]:
    """The document's ``summary``: per-method statistics, the plane's consistency and the error budget.

    Args:
        poses: Pose records (``document["poses"]``).
        reference: The ``[reference]`` plane in the base frame, if known.
        arm: The arm's stated model for the error budget (None: unstated, ADR 0059).
    """
    pose_list = list(poses)
    rows = [r for p in pose_list for r in p.get("measurements", [])]
    return {"methods": summarize(rows), "plane_consistency": plane_summary(pose_list, reference, arm=arm),
            "error_budget": error_budget(pose_list, arm)}


def _ci(value: Any, ci: Any, spec: str) -> str:
    if value is None:
        return "-"
    text = f"{value:{spec}}"
    if ci and None not in ci:
        text += f" [{ci[0]:{spec}}, {ci[1]:{spec}}]"
    return text


_GATE_LABEL = {"valid_fraction": ("valid", 100.0, "%", "min"), "inlier_fraction": ("inliers", 100.0, "%", "min"),
               "residual_rms_m": ("rms", 1000.0, "mm", "max"), "coverage": ("coverage", 100.0, "%", "min"),
               "flatness": ("flatness", 1000.0, "mm", "max"),
               "residual_floor": ("rms vs sensor", 1.0, "x", "min"),
               "expected_plane": ("off expected", 180.0 / math.pi, "deg", "max")}


def _gates(gates: Mapping[str, Any]) -> str:
    parts = []
    for name, g in gates.items():
        label, k, unit, side = _GATE_LABEL.get(name, (name, 1.0, "", "limit"))
        value = "-" if g["value"] is None else f"{g['value'] * k:.3g}"
        mark = "ok" if g["passed"] else "FAILED"
        sep = " " if unit else ""
        parts.append(f"{label} {value}{sep}{unit} ({side} {g['threshold'] * k:.3g}{sep}{unit}, {mark})")
    return "; ".join(parts)


def _multipath(ff: Mapping[str, Any]) -> str:
    """The multipath (radial range bias) estimate and the shift it implies: a bias the intervals do not cover."""
    beta, ci, shift = ff.get("multipath_border_m"), ff.get("multipath_border_ci_m"), ff.get("multipath_shift")
    if beta is None:
        return ""
    ci_mm = [None if c is None else c * 1000.0 for c in ci] if ci else None
    text = f"multipath border bias {_ci(beta * 1000.0, ci_mm, '+.3f')} mm"
    if shift:
        text += (f", would move tilt_x {shift['tilt_x_deg']:+.4f} deg, tilt_y {shift['tilt_y_deg']:+.4f} deg, "
                 f"height {shift['height_m'] * 1000.0:+.3f} mm")
    return text + " (a bias: not in the intervals)"


def _vec(v: Iterable[float], spec: str = "+.5f") -> str:
    return "[" + ", ".join(f"{x:{spec}}" for x in v) + "]"


def _mm(value_m: Any) -> Any:
    """Metres to millimetres (None and a list of them as they come)."""
    if value_m is None:
        return None
    if isinstance(value_m, (list, tuple)):
        return [_mm(v) for v in value_m]
    return float(value_m) * 1000.0


def format_full_frame(document: Mapping[str, Any]) -> str:
    """Human-readable full-frame results and the plane in the base frame ("" if neither is there).

    Lengths in mm and angles in deg; a base-frame plane by its height above the base origin along its
    normal (:func:`plane_height_mm`), what "above" means said once at the end (:data:`ABOVE_NOTE`).
    """
    lines: list[str] = []
    above = False
    poses = [p for p in document.get("poses", []) if p.get("full_frame")]
    if poses:
        conf = poses[0]["full_frame"].get("confidence", 0.95)
        lines.append(f"full frame (every valid pixel; [{conf * 100:.0f} % interval]):")
        for p in poses:
            ff = p["full_frame"]
            exp = p.get("expected") or {}
            lines.append(
                f"  pose {p['index'] + 1}: tilt_x {_ci(ff['tilt_x_deg'], ff['tilt_x_ci_deg'], '.4f')} deg, "
                f"tilt_y {_ci(ff['tilt_y_deg'], ff['tilt_y_ci_deg'], '.4f')} deg, "
                f"height {_ci(_mm(ff['height_m']), _mm(ff['height_ci_m']), '.2f')} mm"
                + (f" (expected tilt_x {exp['tilt_x_deg']:.4f}, tilt_y {exp['tilt_y_deg']:.4f} deg, "
                   f"height {_mm(exp['height_m']):.2f} mm)" if exp else ""))
            mp = _multipath(ff)
            if mp:
                lines.append(f"          {mp}")
            lines.append(f"          gates: {_gates(ff['gates'])}")
            pose_budget = pose_budget_line((document.get("summary") or {}).get("error_budget"), p["index"])
            if pose_budget:
                lines.append(f"          {pose_budget}")
            pb = ff.get("plane_base")
            if pb:
                lines.append(f"          plane in base frame: normal {_vec(pb['normal'])}, "
                             f"{plane_height_mm(pb):+.3f} mm above the base origin")
                above = True
    cons = (document.get("summary") or {}).get("plane_consistency")
    if cons and "consensus_plane_base" not in cons:
        lines.append(f"plane in the base frame: {cons['verdict']} - {cons['interpretation']}")
    elif cons:
        cp = cons["consensus_plane_base"]
        lines.append(f"plane in the base frame ({cons['source_method']}, {cons['n_poses']} poses): "
                     f"normal {_vec(cp['normal'])}, {plane_height_mm(cp):+.3f} mm above the base origin")
        above = True
        exp_n, exp_h = cons.get("expected_normal_rms_deg"), cons.get("expected_height_rms_m")
        lines.append(f"  consistency: normal spread {cons['normal_spread_deg']:.4f} deg "
                     f"(rms {cons['normal_rms_deg']:.4f}"
                     + (f", noise {exp_n:.4f}" if exp_n is not None else "")
                     + f"), height spread {cons['height_spread_m'] * 1000:.3f} mm "
                     f"(rms {cons['height_rms_m'] * 1000:.3f}"
                     + (f", noise {exp_h * 1000:.3f}" if exp_h is not None else "")
                     + ")" + (f", orientations span {cons['orientation_span_deg']:.1f} deg"
                              if cons.get("orientation_span_deg") is not None else ""))
        lines.append(f"  verdict: {cons['verdict']} - {cons['interpretation']}")
        ref = cons.get("reference")
        if ref:
            lines.append(f"  vs [reference] plane: {ref['angle_deg']:.4f} deg apart, "
                         f"{ref['height_m'] * 1000:+.3f} mm above it at "
                         f"{_vec(_mm(cons['reference_point_m']), '+.3f')} mm")
    budget = budget_line((document.get("summary") or {}).get("error_budget"))
    if budget:
        lines.append(budget)
    if above:
        lines.append(ABOVE_NOTE)
    return "\n".join(lines)
