"""The report as one self-contained HTML page: tables from the report data, pictures as data URIs."""

from __future__ import annotations

import base64
import html
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

__all__ = ["Picture", "render_html"]


class Picture(NamedTuple):
    """One PNG of the report: its file name beside ``report.html``, a caption and its bytes."""

    name: str
    caption: str
    png: bytes


_STYLE = """
body{font-family:sans-serif;margin:1.5em;max-width:1400px;color:#111}
h1{font-size:1.5em}h2{font-size:1.2em;border-bottom:1px solid #999;margin-top:1.6em}
table{border-collapse:collapse;margin:.6em 0}td,th{border:1px solid #bbb;padding:.2em .5em;text-align:right}
th{background:#eee}td.l,th.l{text-align:left}.failed{color:#b2182b;font-weight:bold}
.error{border:2px solid #b2182b;padding:.6em;background:#fff0f0}pre{background:#f6f6f6;padding:.6em;overflow-x:auto}
tr.dominant td,td.dominant{background:#ffe9a8;font-weight:bold}p.budget-next{font-weight:bold}
figure{margin:1em 0}img{max-width:100%;border:1px solid #ddd}figcaption{font-size:.9em;color:#333}
"""


def _e(text: Any) -> str:
    return html.escape(str(text), quote=True)


def _cell(value: Any, spec: str, scale: float = 1.0) -> str:
    """A number cell: shown with ``spec``, its exact JSON value in ``data-value``."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "<td>n/a</td>"
    return f'<td data-value="{_e(repr(float(value)))}">{float(value) * scale:{spec}}</td>'


def _ci(ci: Sequence[Any] | None, spec: str, scale: float = 1.0) -> str:
    if not ci or ci[0] is None or ci[1] is None:
        return "<td>n/a</td>"
    return f"<td>[{float(ci[0]) * scale:{spec}}, {float(ci[1]) * scale:{spec}}]</td>"


def _table(head: Sequence[str], rows: Sequence[str]) -> str:
    th = "".join(f'<th class="l">{_e(h)}</th>' if i == 0 else f"<th>{_e(h)}</th>" for i, h in enumerate(head))
    return f"<table><tr>{th}</tr>{''.join(rows)}</table>"


_DEG = 180.0 / math.pi


def _budget_tables(budget: Mapping[str, Any] | None) -> str:
    """calibrate's error budget: the consensus by term (at the allowance and per unit), then each pose (ADR 0059).

    Millimetres and degrees (ADR 0042); the exact values (m, rad) in ``data-value``; the dominant
    term's row (and a pose's dominant cells) highlighted, what to calibrate next said.
    """
    from cellcal.core.calibration.budget import ALLOWANCE_TERMS, TERMS, term_label

    if not budget:
        return ""
    c = budget["consensus"]
    at = c.get("at_allowance") or {}
    judged = c.get("judged")
    dom = c["dominant"]
    per_unit = {"depth_scale": "depth_scale_1pct", "depth_offset": "depth_offset_1mm"}
    where = "at the camera's stated systematic allowance (1-sigma) and the arm's stated accuracy" \
        if judged == "allowance" else "per 1 % depth scale and 1 mm depth offset (the camera states no allowance)"
    parts = ["<h2>Error budget</h2>",
             f"<p>What each systematic error would move the plane by: {_e(where)}; the sensitivities per 1 % "
             "depth scale and per 1 mm depth offset beside them. The consensus in the base frame (a depth error "
             "is common to every pose), each pose in its camera frame.</p>",
             f"<p class='budget-next'>height: <span class='dominant-term'>{_e(term_label(dom['height']))}"
             f"</span> dominates; tilt: {_e(term_label(dom['tilt']))} dominates; next: "
             f"<span class='next'>{_e(c.get('next', ''))}</span></p>"]
    rows = []
    for key, label in ALLOWANCE_TERMS.items():
        a = at.get(key)
        unit = c.get(per_unit.get(key, "")) or {}
        if a is None and key in ("depth_field", "depth_wiggle"):
            continue
        if key == "arm_accuracy":
            arm = budget.get("arm_model") or {}
            stated = (f"{float(arm['accuracy_m']) * 1000:.3g} mm, {float(arm['accuracy_rad']) * _DEG:.3g} deg "
                      f"({arm.get('source', '')})") if arm else "stated accuracy"
            a, probe, unit = a or c["arm_accuracy"], "", {}
        else:
            stated = "n/a" if a is None else str(a["stated"])
            probe = TERMS[per_unit[key]].split("(")[-1].rstrip(")") if key in per_unit else ""
        mark = " dominant" if dom["height"] in (key, per_unit.get(key)) else ""
        rows.append(f"<tr class='budget{mark}' data-term='{_e(key)}'><td class='l'>{_e(label)}</td>"
                    f"<td class='l'>{_e(stated)}</td>"
                    + (_cell(abs(a["tilt_rad"]), ".4f", _DEG) + _cell(abs(a["height_m"]), ".3f", 1000.0)
                       if a is not None else "<td>n/a</td><td>n/a</td>")
                    + f"<td class='l'>{_e(probe)}</td>"
                    + (_cell(abs(unit["tilt_rad"]), ".4f", _DEG) + _cell(abs(unit["height_m"]), ".3f", 1000.0)
                       if unit else "<td></td><td></td>") + "</tr>")
    parts.append(_table(["term (consensus)", "stated", "tilt (deg)", "height (mm)", "per", "tilt (deg)",
                         "height (mm)"], rows))
    keys = [k for k in ALLOWANCE_TERMS if any((r.get("at_allowance") or {}).get(k) for r in budget["poses"])]
    if keys:
        rows = []
        for r in budget["poses"]:
            a = r.get("at_allowance") or {}
            cells = []
            for what, spec, scale in (("height", ".3f", 1000.0), ("tilt", ".4f", _DEG)):
                for k in keys:
                    v = a.get(k) or {}
                    cell = _cell(abs(v[what + ("_m" if what == "height" else "_rad")]), spec, scale) if v else \
                        "<td>n/a</td>"
                    if k == r["dominant"][what]:
                        cell = cell.replace("<td", "<td class='dominant'", 1)
                    cells.append(cell)
            rows.append(f"<tr class='budget-pose' data-index='{int(r['index'])}'><td class='l'>pose "
                        f"{int(r['index']) + 1}</td>{''.join(cells)}</tr>")
        head = (["pose"] + [f"{ALLOWANCE_TERMS[k]} height (mm)" for k in keys]
                + [f"{ALLOWANCE_TERMS[k]} tilt (deg)" for k in keys])
        parts += ["<p>Each pose in its camera frame, at the allowance; its dominant terms highlighted.</p>",
                  _table(head, rows)]
    return "".join(parts)


def _handeye_budget(doc: Mapping[str, Any]) -> str:
    """The hand-eye result's ``error_budget`` (when there): per term, how far the mount and the plane move.

    At the camera's stated allowance and the arm's stated accuracy (``at_allowance``, when there:
    the dominant term judged by it), then per 1 % depth scale and 1 mm depth offset.
    """
    from cellcal.core.calibration.budget import HANDEYE_TERMS, HANDEYE_VALUES

    eb = doc.get("error_budget")
    if not isinstance(eb, Mapping) or not eb.get("terms"):
        return ""
    dom = eb.get("dominant")
    head = ["term"] + [f"{label} ({unit})" for label, unit in HANDEYE_VALUES.values()]

    def table(terms: Mapping[str, Any], kind: str, judged: bool) -> str:
        rows = []
        for key, term in terms.items():
            mark = " dominant" if judged and key == dom else ""
            cells = "".join(_cell(None if term.get(v) is None else abs(float(term[v])),
                                  ".3f" if unit == "mm" else ".4f", 1000.0 if unit == "mm" else _DEG)
                            for v, (_, unit) in HANDEYE_VALUES.items())
            rows.append(f"<tr class='{kind}{mark}' data-term='{_e(key)}'><td class='l'>"
                        f"{_e(HANDEYE_TERMS.get(key, key))}</td>{cells}</tr>")
        return _table(head, rows)

    out = ["<h2>Error budget</h2><p>What each systematic error would move the mount and the plane by.</p>"]
    if dom:
        out.append(f"<p class='budget-next'><span class='dominant-term'>{_e(HANDEYE_TERMS.get(dom, dom))}</span>"
                   f" dominates" + (f"; next: <span class='next'>{_e(eb['next'])}</span>" if eb.get("next") else "")
                   + "</p>")
    at = eb.get("at_allowance")
    if isinstance(at, Mapping) and at:
        out += ["<p>At the camera's stated systematic allowance (1-sigma) and the arm's stated accuracy:</p>",
                table(at, "handeye-budget-allowance", True), "<p>Per 1 % depth scale and per 1 mm depth offset:</p>"]
    out.append(table(eb["terms"], "handeye-budget", not (isinstance(at, Mapping) and at)))
    return "".join(out)


def _calibrate_tables(section: Mapping[str, Any]) -> str:
    parts = ["<h2>Poses (full frame, 95 % intervals)</h2>"]
    rows = []
    for pose in section.get("poses") or []:
        ff = pose.get("full_frame") or {}
        exp = pose.get("expected") or {}
        gates = ff.get("gates") or {}
        failed = [name for name, g in gates.items() if not g.get("passed")]
        state = f'<td class="l failed">failed: {_e(", ".join(failed))}</td>' if failed else \
            ('<td class="l failed">failed</td>' if pose.get("failed") else '<td class="l">passed</td>')
        rows.append(f'<tr class="pose" data-index="{int(pose["index"])}"><td class="l">pose {int(pose["index"]) + 1}'
                    f"</td>{_cell(ff.get('tilt_x_deg'), '.4f')}{_ci(ff.get('tilt_x_ci_deg'), '.4f')}"
                    f"{_cell(ff.get('tilt_y_deg'), '.4f')}{_ci(ff.get('tilt_y_ci_deg'), '.4f')}"
                    f"{_cell(ff.get('height_m'), '.3f', 1000.0)}{_ci(ff.get('height_ci_m'), '.3f', 1000.0)}"
                    f"{_cell(exp.get('tilt_x_deg'), '.4f')}{_cell(exp.get('height_m'), '.3f', 1000.0)}"
                    f"{_cell(ff.get('residual_rms_m'), '.3f', 1000.0)}{state}</tr>")
    parts.append(_table(["pose", "tilt x (deg)", "95 %", "tilt y (deg)", "95 %", "height (mm)", "95 %",
                         "expected tilt x (deg)", "expected height (mm)", "residual RMS (mm)", "gates"], rows))
    result = section.get("result") or {}
    summary = result.get("summary") or {}
    methods = summary.get("methods") or {}
    if methods:
        parts.append("<h2>The paper's methods</h2>")
        rows = [f'<tr class="method" data-method="{_e(name)}"><td class="l">{_e(name)}</td><td>{int(g["all"]["n"])}'
                f"</td>{_cell(g['all'].get('mean_angle_deg'), '.3f')}{_cell(g['all'].get('mean_error_pct'), '.3f')}"
                f"{_cell(g['all'].get('max_error_pct'), '.3f')}</tr>" for name, g in methods.items()]
        parts.append(_table(["method", "estimates", "mean angle (deg)", "mean |error| (%)", "max |error| (%)"],
                            rows))
    cons = summary.get("plane_consistency")
    if cons:
        parts.append("<h2>Cross-pose consistency (base frame)</h2>")
        parts.append(f'<p>verdict <b class="verdict">{_e(cons.get("verdict"))}</b>: '
                     f"{_e(cons.get('interpretation', ''))}</p>")
    parts.append(_budget_tables(summary.get("error_budget")))
    return "".join(parts)


def _handeye_tables(section: Mapping[str, Any]) -> str:
    doc = section.get("result") or {}
    m = doc.get("mount")
    if not m:
        return ""
    rows = [f"<tr><td class='l'>t{a}</td>{_cell(m['translation_m'][i], '+.3f', 1000.0)}"
            f"{_ci(m['translation_ci_m'][i], '+.3f', 1000.0)}<td class='l'>mm</td></tr>" for i, a in enumerate("xyz")]
    rows += [f"<tr><td class='l'>{n}</td>{_cell(m['rpy_deg'][i], '+.4f')}{_ci(m['rpy_ci_deg'][i], '+.4f')}"
             f"<td class='l'>deg</td></tr>" for i, n in enumerate(("roll", "pitch", "yaw"))]
    out = [f"<h2>Mount (camera in the flange frame, {doc.get('method', '')} method)</h2>",
           _table(["value", "estimate", f"{round(100 * float(m.get('confidence', 0.95)))} %", "unit"], rows)]
    fit = doc.get("fit") or {}
    obs = doc.get("observability") or {}
    out.append(f"<p>chi2/dof {_e(format(float(fit.get('chi2_per_dof', math.nan)), '.3f'))}; observability rank "
               f"{_e(obs.get('rank'))} of {_e(obs.get('n_parameters'))}"
               + (f"; unobservable: {_e('; '.join(map(str, obs.get('unobservable') or [])))}"
                  if obs.get("unobservable") else "") + "</p>")
    methods = (doc.get("charuco") or {}).get("methods") or {}
    if methods:
        rows = [f"<tr><td class='l'>{_e(name)}</td>"
                + "".join(_cell(v, "+.3f", 1000.0) for v in c["translation_m"])
                + "".join(_cell(v, "+.4f") for v in c["rpy_deg"]) + "</tr>" for name, c in methods.items()]
        rows.insert(0, "<tr><td class='l'>plane (cellcal)</td>"
                    + "".join(_cell(v, "+.3f", 1000.0) for v in m["translation_m"])
                    + "".join(_cell(v, "+.4f") for v in m["rpy_deg"]) + "</tr>")
        out += ["<h2>OpenCV's methods on the ChArUco board against the plane</h2>",
                _table(["method", "tx (mm)", "ty (mm)", "tz (mm)", "roll (deg)", "pitch (deg)", "yaw (deg)"], rows)]
    out.append(_handeye_budget(doc))
    return "".join(out)


def _monitor_tables(section: Mapping[str, Any]) -> str:
    rows = []
    for label, cam in (section.get("cameras") or {}).items():
        drifting = bool(cam.get("drifting"))
        rows.append(f"<tr><td class='l'>{_e(label)}</td><td>{int(cam.get('frames', 0))}</td>"
                    f"<td>{int(cam.get('drift_events', 0))}</td>"
                    f"{_cell(cam.get('max_tilt_deviation_rad'), '.4f', 180 / math.pi)}"
                    f"{_cell(cam.get('tilt_threshold_rad'), '.4f', 180 / math.pi)}"
                    f"{_cell(cam.get('max_height_deviation_m'), '.3f', 1000.0)}"
                    f"{_cell(cam.get('height_threshold_m'), '.3f', 1000.0)}"
                    f"<td class='l{' failed' if drifting else ''}'>{'DRIFTING' if drifting else 'ok'}</td></tr>")
    return "<h2>Cameras</h2>" + _table(["camera", "frames", "drift events", "largest tilt (deg)",
                                         "tilt threshold (deg)", "largest height (mm)", "height threshold (mm)",
                                         "now"], rows)


def render_html(data: Mapping[str, Any], pictures: Sequence[Picture], note: str = "",
                tables: Callable[[Mapping[str, Any]], str] | None = None) -> str:
    """The whole page: title, failure (if any), tables, pictures (data URIs), the summary text.

    ``tables``: draws the tables of the run's section (None: those of its ``kind`` here).
    """
    kind = str(data.get("kind", ""))
    title = f"cellcal {kind} report - camera {data.get('camera', '')}"
    parts = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><link rel='icon' href='data:,'>"
             f"<title>{_e(title)}</title><style>{_STYLE}</style></head><body><h1>{_e(title)}</h1>",
             f"<p>status <b class='status'>{_e(data.get('status'))}</b>; created {_e(data.get('created_utc'))} "
             f"by cellcal {_e(data.get('cellcal_version'))}; configuration {_e(data.get('config_source'))}</p>"]
    if data.get("error"):
        parts.append(f"<div class='error'><b>The run failed:</b> {_e(data['error'])}</div>")
    if note:
        parts.append(f"<p class='note'>{_e(note)}</p>")
    section = data.get(kind) or {}
    by_kind: dict[str, Callable[[Mapping[str, Any]], str]] = {
        "calibrate": _calibrate_tables, "handeye": _handeye_tables, "monitor": _monitor_tables}
    draw = tables if tables is not None else by_kind.get(kind, lambda s: "")
    parts.append(draw(section))
    if pictures:
        parts.append("<h2>Pictures</h2>")
    for pic in pictures:
        uri = "data:image/png;base64," + base64.b64encode(pic.png).decode("ascii")
        parts.append(f"<figure><img src='{uri}' alt='{_e(pic.caption)}' data-file='{_e(pic.name)}'>"
                     f"<figcaption>{_e(pic.caption)} ({_e(pic.name)})</figcaption></figure>")
    parts.append(f"<h2>Summary (as printed)</h2><pre class='summary'>{_e(data.get('summary_text', ''))}</pre>")
    parts.append("</body></html>\n")
    return "".join(parts)
