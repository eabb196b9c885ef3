"""The report as one self-contained HTML page: tables from the report data, pictures as data URIs."""

from __future__ import annotations

import base64
import html
import math
from collections.abc import Mapping, Sequence
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


def render_html(data: Mapping[str, Any], pictures: Sequence[Picture], note: str = "") -> str:
    """The whole page: title, failure (if any), tables, pictures (data URIs), the summary text."""
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
    parts.append({"calibrate": _calibrate_tables, "handeye": _handeye_tables,
                  "monitor": _monitor_tables}.get(kind, lambda s: "")(section))
    if pictures:
        parts.append("<h2>Pictures</h2>")
    for pic in pictures:
        uri = "data:image/png;base64," + base64.b64encode(pic.png).decode("ascii")
        parts.append(f"<figure><img src='{uri}' alt='{_e(pic.caption)}' data-file='{_e(pic.name)}'>"
                     f"<figcaption>{_e(pic.caption)} ({_e(pic.name)})</figcaption></figure>")
    parts.append(f"<h2>Summary (as printed)</h2><pre class='summary'>{_e(data.get('summary_text', ''))}</pre>")
    parts.append("</body></html>\n")
    return "".join(parts)
