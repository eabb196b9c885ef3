"""The fixed camera's report page: its tables and its pictures' list, drawn from its report data alone.

``cellcal handeye --camera NAME`` for a camera ``on = "base"`` writes its report beside its result
(ADR 0037, ADR 0061): the report data (schema ``cellcal.report/1``, kind :data:`FIXED_KIND`, the result
document in it) and one self-contained page with the camera's pose in the base frame and its 95 %
intervals, the plate in the flange, the measuring plane it saw, the noise test, what the plan sees,
the systematic allowance's share, every pose's residual and the poses left out and why. The pictures
are plain images (:mod:`.fixed_charts`, no matplotlib, drawn in the run's process). The page is
rendered again from the data alone by ``cellcal report DIR/handeye-NAME.report-data.json --out FILE``;
:class:`~cellcal.core.report.fixed.FixedReport` writes it at the end of the run.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from cellcal.core.report.html import _cell, _e, _table

__all__ = ["FIXED_KIND", "fixed_jobs", "fixed_report_paths", "fixed_tables"]

#: The report data's ``kind`` of a fixed camera's hand-eye run.
FIXED_KIND = "handeye-fixed"
_DEG = 180.0 / math.pi


def fixed_report_paths(out_dir: str | Path, name: str) -> tuple[Path, Path]:
    """The report data and the page of fixed camera ``name`` in ``out_dir``."""
    out = Path(out_dir)
    return out / f"handeye-{name}.report-data.json", out / f"handeye-{name}.html"


def fixed_jobs(section: Mapping[str, Any], camera: str) -> list[tuple[str, str, str, tuple[Any, ...]]]:
    """The pictures of a fixed camera's report: (file name, caption, function of :mod:`.figures`, arguments)."""
    doc = section.get("result") or {}
    if not doc.get("camera_base"):
        return []
    stem = f"handeye-{camera}"
    out = [(f"{stem}-pose.png", "the camera's steps from its configured pose, and the plate's, with their intervals",
            "fixed_pose_figure", (doc, camera))]
    if doc.get("residuals"):
        out.append((f"{stem}-residuals.png", "per-pose residuals of the plate", "fixed_residuals_figure",
                    (doc, camera)))
    if doc.get("covariance"):
        out.append((f"{stem}-observability.png", "each parameter's 1-sigma and the systematic allowance's share",
                    "fixed_sigma_figure", (doc, camera)))
    return out


def _pose_table(doc: Mapping[str, Any]) -> str:
    """The camera's pose in the base frame: translation (mm) and roll, pitch, yaw (deg), each with its interval."""
    half, z = doc.get("half_widths") or {}, float((doc.get("noise_model") or {}).get("interval_z") or 1.96)
    t = doc["camera_base"]["translation_m"]
    rpy, rpy_sigma = doc.get("camera_base_rpy_deg") or [math.nan] * 3, doc.get("camera_base_rpy_sigma_deg") or []
    rows = [f"<tr class='pose-value' data-name='t{a}'><td class='l'>t{a}</td>{_cell(t[i], '+.3f', 1000.0)}"
            f"{_cell(half.get(f't{a}'), '.3f', 1000.0)}<td class='l'>mm</td></tr>" for i, a in enumerate("xyz")]
    rows += [f"<tr class='pose-value' data-name='{n}'><td class='l'>{n}</td>{_cell(rpy[i], '+.4f')}"
             f"{_cell(z * rpy_sigma[i] if i < len(rpy_sigma) else None, '.4f')}<td class='l'>deg</td></tr>"
             for i, n in enumerate(("roll", "pitch", "yaw"))]
    rows += [f"<tr class='pose-value' data-name='{k}'><td class='l'>turn about base {k[-1]}</td><td></td>"
             f"{_cell(half.get(k), '.4f', _DEG)}<td class='l'>deg</td></tr>" for k in ("rot_x", "rot_y", "rot_z")]
    conf = round(100 * float(doc.get("confidence", 0.95)))
    return _table(["value", "estimate", f"± ({conf} %)", "unit"], rows)


def _plate_and_plane(doc: Mapping[str, Any]) -> str:
    """The plate's plane in the flange (its terms' intervals) and the measuring plane the camera saw."""
    half = doc.get("half_widths") or {}
    plate = doc.get("plate_flange") or {}
    out = [f"<h2>The plate in the flange frame ({_e(doc.get('plate', ''))})</h2>",
           f"<p class='plate'>normal {_e(_vec(plate.get('normal'), '+.5f'))}, offset "
           f"{_e(_num(plate.get('offset_m'), 1000.0, '+.3f'))} mm</p>"]
    rows = [f"<tr class='plate-term' data-name='{k}'><td class='l'>{k}</td>"
            f"{_cell(doc['steps'][6 + i] if len(doc.get('steps') or []) > 6 + i else None, '+.4f', s)}"
            f"{_cell(half.get(k), '.4f', s)}<td class='l'>{u}</td></tr>"
            for i, (k, s, u) in enumerate((("plate_tilt_a", _DEG, "deg"), ("plate_tilt_b", _DEG, "deg"),
                                          ("plate_offset", 1000.0, "mm"))) if k in half]
    if rows:
        out.append(_table(["term", "step from configured", "±", "unit"], rows))
    plane = doc.get("measuring_plane")
    out.append("<h2>The measuring plane (table) as this camera saw it, base frame</h2>")
    if not plane:
        out.append("<p class='table-plane'>not measured (no [reference] plane)</p>")
    elif "error" in plane:
        out.append(f"<p class='table-plane failed'>no plane found: {_e(plane['error'])}</p>")
    else:
        base = plane["plane_base"]
        n = [float(v) for v in base["normal"]]
        tilt = math.degrees(math.acos(min(1.0, abs(n[2]))))
        sigma = [math.sqrt(max(float(plane["covariance"][i][i]), 0.0)) for i in range(3)]
        out.append(f"<p class='table-plane'>normal {_e(_vec(n, '+.6f'))} ({tilt:.4f} deg from the base z), offset "
                   f"{_e(_num(base['offset_m'], 1000.0, '+.3f'))} mm; 1-sigma tilts {sigma[0] * _DEG:.4f}, "
                   f"{sigma[1] * _DEG:.4f} deg, offset {sigma[2] * 1000:.3f} mm</p>")
    return "".join(out)


def _fit_and_observability(doc: Mapping[str, Any]) -> str:
    """The noise test, what the plan sees, and the systematic allowance's share of each parameter's variance."""
    noise, obs = doc.get("noise_model") or {}, doc.get("observability") or {}
    system = doc.get("systematic") or {}
    out = ["<h2>Fit and observability</h2>",
           f"<p class='fit'>chi2 {_e(_num(doc.get('chi2'), 1.0, '.2f'))} over {_e(doc.get('dof'))} dof, chi2/dof "
           f"<b class='chi2-per-dof'>{_e(_num(noise.get('chi2_per_dof'), 1.0, '.3f'))}</b>, verdict "
           f"<b class='verdict'>{_e(noise.get('verdict'))}</b>; interval scale "
           f"{_e(_num(noise.get('interval_scale'), 1.0, '.3f'))}</p>",
           f"<p class='observability'>rank <b class='rank'>{_e(obs.get('rank'))}</b> of "
           f"{_e(obs.get('n_parameters'))} over {_e(obs.get('n_views'))} views, condition "
           f"{_e(_num(obs.get('condition'), 1.0, '.4g'))}"
           + (f"; unobservable: {_e('; '.join(map(str, obs.get('unobservable') or [])))}"
              if obs.get("unobservable") else "; every parameter observable") + "</p>"]
    share = system.get("variance_share") or {}
    terms = system.get("terms") or []
    out.append(f"<p class='systematic'>The camera's systematic allowance ({_e(', '.join(terms) or 'none stated')}) "
               "is common to the views: its share of each camera parameter's variance</p>")
    rows = [f"<tr class='systematic-share' data-name='{_e(k)}'><td class='l'>{_e(k)}</td>"
            f"{_cell(v, '.1f', 100.0)}</tr>" for k, v in share.items()]
    out.append(_table(["parameter", "share (%)"], rows))
    return "".join(out)


def _residuals_and_left_out(doc: Mapping[str, Any]) -> str:
    """Every plate pose's residual, then the plan's poses left out before the run and why."""
    rows = [f"<tr class='residual' data-pose='{int(r['pose'])}'><td class='l'>pose {int(r['pose'])}</td>"
            f"{_cell(r.get('normal_rad'), '.4f', _DEG)}{_cell(r.get('offset_m'), '+.3f', 1000.0)}"
            f"{_cell(r.get('chi2'), '.2f')}</tr>" for r in doc.get("residuals") or []]
    out = ["<h2>Per-pose residuals</h2>", _table(["plate pose", "normal (deg)", "offset (mm)", "chi2"], rows)]
    left = list(doc.get("left_out") or [])
    out.append(f"<h2>Poses left out ({len(left)})</h2>")
    out.append("<ul class='left-out'>" + "".join(f"<li>{_e(line)}</li>" for line in left) + "</ul>" if left
               else "<p class='left-out'>none: every pose of the plan was inside the envelope and the arm's reach</p>")
    notes = doc.get("notes") or []
    if notes:
        out.append("<h2>What the intervals rest on</h2><ul class='notes'>"
                   + "".join(f"<li>{_e(n)}</li>" for n in notes) + "</ul>")
    return "".join(out)


def _board_tables(doc: Mapping[str, Any]) -> str:
    """With the board (``--method charuco|both``): every OpenCV method's camera pose and spread, the comparison."""
    methods = (doc.get("charuco") or {}).get("methods") or {}
    if not methods:
        return ""
    rows = [f"<tr class='board-method' data-method='{_e(name)}'><td class='l'>{_e(name)}</td>"
            + "".join(_cell(v, "+.3f", 1000.0) for v in c["translation_m"])
            + "".join(_cell(v, "+.4f") for v in c["rpy_deg"]) + _cell(c.get("residual_rms_m"), ".3f", 1000.0)
            + "</tr>" for name, c in methods.items()]
    out = ["<h2>OpenCV's eye-to-hand methods on the ChArUco board (camera in the base frame)</h2>",
           _table(["method", "tx (mm)", "ty (mm)", "tz (mm)", "roll (deg)", "pitch (deg)", "yaw (deg)",
                   "board spread (mm)"], rows)]
    cmp = doc.get("comparison")
    if cmp:
        agree = "agree" if cmp.get("agree_95") else "DISAGREE"
        out.append(f"<p class='comparison'>plate - board: translation "
                   f"{_e(_vec([1000 * v for v in cmp['translation_m']], '+.3f'))} mm, turn about the base axes "
                   f"{_e(_vec(cmp['rotation_deg_about_base_xyz'], '+.4f'))} deg = {_e(_vec(cmp['in_sigmas'], '+.1f'))}"
                   f" combined sigmas: <b class='agree'>{agree}</b> at 95 %</p>")
    return "".join(out)


def fixed_tables(section: Mapping[str, Any]) -> str:
    """The page's tables of a fixed camera's run (nothing without a result: the failure says why)."""
    doc = section.get("result") or {}
    if not doc.get("camera_base"):
        return ""
    return "".join([f"<h2>Camera {_e(doc.get('camera', ''))} in the base frame ({_e(doc.get('method', ''))} "
                    "method)</h2>", _pose_table(doc), _board_tables(doc), _plate_and_plane(doc),
                    _fit_and_observability(doc), _residuals_and_left_out(doc)])


def _num(value: Any, scale: float, spec: str) -> str:
    return "n/a" if value is None else format(float(value) * scale, spec)


def _vec(values: Sequence[Any] | None, spec: str) -> str:
    return "n/a" if not values else "[" + ", ".join(format(float(v), spec) for v in values) + "]"
