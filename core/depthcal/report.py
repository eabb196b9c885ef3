"""``cellcal depthcal``'s words and what its pictures show: the terminal summary and a view's residual maps.

The summary speaks in %, mm, degrees and px (ADR 0042) and says what the plan spans, what
the fit could and could not see and how to apply the correction (ADR 0057). The pictures
themselves are drawn by :mod:`cellcal.core.report.depthcal` (the report layer sits above
this one).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.systematic import SystematicError, normalised_pixels

__all__ = ["Z95", "format_summary", "held_out_residuals"]

#: The 95 % two-sided normal quantile.
Z95 = 1.959963984540054


def _parameter_lines(document: Mapping[str, Any]) -> list[str]:
    """The correction's parameters with 95 % intervals, in px / % / mm."""
    corr = document["correction"]
    sig = document.get("correction_sigma") or {}
    lines = []

    def line(name: str, value: float, scale: float, unit: str, what: str) -> None:
        s = sig.get(name)
        ci = f" ± {Z95 * s * scale:.3g}" if s is not None and math.isfinite(s) else ""
        lines.append(f"  {what:<28} {value * scale:+.4g}{ci} {unit}")

    if document.get("kind") == "stereo":
        line("fb_error", corr.get("fb_error", 0.0), 100.0, "%", "f*B scale error")
        line("disparity_offset_px", corr.get("disparity_offset_px", 0.0), 1.0, "px", "disparity offset")
        unit, scale = "px", 1.0
    else:
        line("scale_error", corr.get("scale_error", 0.0), 100.0, "%", "range scale error")
        line("offset_m", corr.get("offset_m", 0.0), 1000.0, "mm", "range offset")
        if corr.get("wiggle_period_m"):
            amp = math.hypot(corr.get("wiggle_cos_m", 0.0), corr.get("wiggle_sin_m", 0.0))
            period = 1000 * corr["wiggle_period_m"]
            lines.append(f"  {'wiggling amplitude':<28} {1000 * amp:.3g} mm (period {period:.4g} mm)")
        unit, scale = "mm", 1000.0
    order = int(corr.get("field_order", 0))
    if order:
        correction = SystematicError.from_dict(corr)
        corner = float(np.max(np.abs([correction.field_at(su, sv) for su in (-1, 1) for sv in (-1, 1)])))
        lines.append(f"  {'image field':<28} order {order}, up to {corner * scale:.3g} {unit} at the image corners")
    else:
        lines.append(f"  {'image field':<28} none (order 0 chosen)")
    return lines


def format_summary(document: Mapping[str, Any], path: str | Path) -> str:
    """The terminal summary: the correction, the held-out error before and after, what the plan saw, how to apply."""
    kind = document.get("kind", "?")
    native = "px" if kind == "stereo" else "mm"
    to_native = 1.0 if kind == "stereo" else 1000.0
    views = document.get("views") or []
    held = [v for v in views if v.get("held_out")]
    lines = [f"depth calibration of a {kind} camera from {len(views)} views ({len(held)} held out)"]
    lines += _parameter_lines(document)
    scores = document.get("order_scores") or {}
    if scores:
        lines.append("field order by held-out RMS: " + ", ".join(
            f"{k}: {to_native * v:.3g} {native}" + (" (chosen)" if int(k) == document.get("field_order") else "")
            for k, v in scores.items() if v is not None))
    hold = document.get("holdout") or {}
    if hold.get("rms_before") is not None and hold.get("rms_after") is not None:
        mm = [1000 * v["rms_before_m"] for v in held], [1000 * v["rms_after_m"] for v in held]
        in_mm = (f" ({np.sqrt(np.mean(np.square(mm[0]))):.3g} -> {np.sqrt(np.mean(np.square(mm[1]))):.3g} mm in depth)"
                 if held and kind == "stereo" else "")
        noise = hold.get("noise_only_rms")
        lines.append(f"held-out residual RMS: {to_native * hold['rms_before']:.3g} {native} before -> "
                     f"{to_native * hold['rms_after']:.3g} {native} after" + in_mm
                     + (f"; the noise alone: {to_native * noise:.3g} {native}" if noise is not None else ""))
    plane = document.get("plane") or {}
    if plane.get("normal_base"):
        n = np.asarray(plane["normal_base"], dtype=np.float64)
        tilt = math.degrees(math.acos(min(1.0, abs(float(n[2])) / float(np.linalg.norm(n)))))
        lines.append(f"plane (base frame): tilt {tilt:.3f} deg from the base z axis, offset "
                     f"{1000 * float(plane.get('offset_m', 0.0)):+.2f} mm")
    if document.get("coverage"):
        lines.append(f"the plan: {document['coverage']}")
    lines.append("what the fit sees: " + _observability_text(document.get("observability") or {}))
    lines += [f"note: {note}" for note in document.get("notes") or []]
    lines.append(f'apply it: [camera.correction] file = "{Path(path).absolute()}" (or that path relative to the '
                 "configuration file's directory)")
    return "\n".join(lines)


def _observability_text(obs: Mapping[str, Any]) -> str:
    """One line from the fit's observability report."""
    params = obs.get("parameters") or []
    unseen = [p for p in params if not p.get("observable", True)]
    if not params:
        return "no observability report"
    if not unseen:
        cond = obs.get("condition")
        return f"all {len(params)} parameters" + (f" (condition {float(cond):.3g})" if cond is not None else "")
    return "; ".join(f"{p['name']} NOT seen" + (f": {p['reason']}" if p.get("reason") else "") for p in unseen)


def held_out_residuals(view: Any, mount: Any, document: Mapping[str, Any], correction: SystematicError,
                       ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A view's residual to the fitted plane per pixel, native unit: measured minus true, before and after.

    The true value is the fitted plane seen along the pixel's ray from the camera pose the arm reports.
    """
    frame = view.frame
    intr = frame.intrinsics
    cam = view.flange_pose @ mount
    plane = document["plane"]
    n = np.asarray(plane["normal_base"], dtype=np.float64)
    offset = float(plane["offset_m"])
    xyz = frame.xyz.astype(np.float64)
    valid = frame.valid & np.all(np.isfinite(xyz), axis=-1)
    rng = np.linalg.norm(xyz, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        ray = xyz / rng[..., None]
        n_cam = cam.rotation_matrix.T @ n
        d_cam = offset - float(n @ np.asarray(cam.translation, dtype=np.float64))
        r_true = d_cam / (ray @ n_cam)
        u, v = normalised_pixels(intr.width, intr.height, intr.cx, intr.cy)
        if document.get("kind") == "stereo":
            fb = frame.measurement.fb_px_m
            measured, true = fb / xyz[..., 2], fb / (r_true * ray[..., 2])
        else:
            measured, true = frame.distance.astype(np.float64), r_true
        before = measured - true
        after = correction.correct(measured, u, v) - true
    ok = valid & np.isfinite(before) & np.isfinite(after) & (r_true > 0)
    before[~ok] = np.nan
    after[~ok] = np.nan
    return before, after
