"""calibrate's error budget: what a 1 % depth scale, a 1 mm depth offset and the arm's accuracy do to the plane.

Each pose's full-frame fit states what a 1 % depth scale and a 1 mm depth offset do to its plane in
the camera frame (``full_frame.error_budget``, :mod:`cellcal.core.methods.fullframe.systematic`).
The plane in the base frame also moves with the flange pose's error: the arm's absolute position
accuracy along the normal moves its height, its orientation accuracy tilts it (and, over the
lever from the flange to the plane, moves its height too). A depth error is common to every pose,
so the consensus moves by the poses' mean shift in the base frame (an equal-weight mean standing
for the consensus's weights); the arm's accuracy errs smoothly with the pose, so it is not taken
to average out either.

The sensitivities (per 1 % and per 1 mm) say how the result answers a depth error; which error
*dominates* is judged at what is plausible for this camera and this arm: each term at the camera's
stated systematic allowance (scale, offset, field at the image corner; 1-sigma, the fit's own
``allowance_shifts``) and the arm's stated accuracy. A ToF camera states 0.2 % of scale and 5 mm
of offset: its offset, not its scale, moves the height most, although 1 % of scale is five times
1 mm of offset. The dominant term is named with what to calibrate next. Without the allowance (a
document written before it) the per-unit sensitivities are judged instead, and the budget says so.
Rationale: docs/adr/0059-systematic-allowance-and-error-budget.md.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from cellcal.devices.arm_model import UNSTATED_ARM_MODEL, ArmModel
from cellcal.devices.pose import Pose

__all__ = ["ALLOWANCE_TERMS", "HANDEYE_TERMS", "HANDEYE_VALUES", "NEXT_STEP", "TERMS", "budget_line", "budget_table",
           "error_budget", "handeye_budget_line", "handeye_value", "pose_budget_line", "term_label"]

#: Budget sensitivities and their labels for people.
TERMS: dict[str, str] = {"depth_scale_1pct": "depth scale (1 %)", "depth_offset_1mm": "depth offset (1 mm)",
                         "arm_accuracy": "arm accuracy"}
#: Terms judged at the camera's stated allowance and the arm's stated accuracy, their names for people.
ALLOWANCE_TERMS: dict[str, str] = {"depth_scale": "depth scale", "depth_offset": "depth offset",
                                   "depth_field": "depth field", "depth_wiggle": "depth wiggle",
                                   "arm_accuracy": "arm accuracy"}
#: The sensitivity standing for each judged term when there is no allowance to judge at.
_PER_UNIT: dict[str, str] = {"depth_scale": "depth_scale_1pct", "depth_offset": "depth_offset_1mm",
                             "arm_accuracy": "arm_accuracy"}
#: What to calibrate when a term dominates.
NEXT_STEP: dict[str, str] = {"depth_scale": "run cellcal depthcal", "depth_offset": "run cellcal depthcal",
                             "depth_field": "run cellcal depthcal",
                             "depth_wiggle": "run cellcal depthcal (a ToF wiggle is fitted at its stated period)",
                             "arm_accuracy": "calibrate the arm's kinematics (or state its accuracy in [arm.model])"}
#: The allowance's keys in ``full_frame.error_budget.allowance_shifts`` and ``allowance``.
_SHIFT_KEY: dict[str, str] = {"depth_scale": "scale", "depth_offset": "offset", "depth_field": "field",
                               "depth_wiggle": "wiggle"}


def term_label(key: str) -> str:
    """A term's name for people (a judged term, a sensitivity, or the key itself: documents of other versions)."""
    return ALLOWANCE_TERMS.get(key) or TERMS.get(key) or key


def _arm(arm: ArmModel, lever_m: float) -> dict[str, float]:
    return {"tilt_rad": arm.accuracy_rad, "height_m": math.hypot(arm.accuracy_m, arm.accuracy_rad * lever_m)}


def _size(term: Mapping[str, Any] | None, what: str) -> float:
    return abs(float((term or {}).get(what) or 0.0))


def _dominant(block: Mapping[str, Any]) -> tuple[dict[str, str], str]:
    """The dominant term for tilt and height, judged at the allowance when there is one, and how it was judged."""
    at = block.get("at_allowance")
    if at and any(_size(at[k], w) > 0 for k in at for w in ("tilt_rad", "height_m")):
        return {w.split("_")[0]: max(at, key=lambda k: _size(at[k], w)) for w in ("tilt_rad", "height_m")}, \
            "allowance"
    return {w.split("_")[0]: max(_PER_UNIT, key=lambda k: _size(block[_PER_UNIT[k]], w))
            for w in ("tilt_rad", "height_m")}, "per unit"


def _allowance_label(key: str, allowance: Mapping[str, Any]) -> str:
    """What the term's stated size is, for people: ``0.2 %``, ``5 mm``, ``0.1 px``, ``2 mm at the corner``."""
    if key == "depth_wiggle":
        return f"{float(allowance.get('wiggle_m') or 0.0) * 1000:.3g} mm"
    value = float(allowance.get(_SHIFT_KEY[key]) or 0.0)
    if key == "depth_scale":
        return f"{value * 100:.3g} %"
    px = allowance.get("offset_unit") == "px"
    text = f"{value:.3g} px" if px else f"{value * 1000:.3g} mm"
    return text + (" at the corner" if key == "depth_field" else "")


def _field_keys(shifts: Mapping[str, Any]) -> list[str]:
    """The field's terms among the allowance's shifts: ``field`` (one worst shape) or ``field:<shape>`` (each shape)."""
    return [k for k in shifts if k == "field" or k.startswith("field:")]


def _rss(sizes: Iterable[tuple[float, float]]) -> dict[str, float]:
    """Independent terms' combined 1-sigma size: the root sum of squares of (tilt, height)."""
    arr = np.asarray(list(sizes), dtype=np.float64).reshape(-1, 2)
    tot = np.sqrt(np.sum(arr * arr, axis=0))
    return {"tilt_rad": float(tot[0]), "height_m": float(tot[1])}


def _at_allowance(eb: Mapping[str, Any], arm_term: Mapping[str, float]) -> dict[str, Any] | None:
    """A pose's terms at the camera's stated allowance (camera frame) and the arm's accuracy; None without it.

    The field is either one (worst) shape, ``field``, or independent shapes ``field:<shape>`` at
    their share of the allowance: their root sum of squares.
    """
    allowance = eb.get("allowance")
    if not isinstance(allowance, Mapping):
        return None
    shifts = eb.get("allowance_shifts") or {}
    out: dict[str, Any] = {}
    for key, sk in _SHIFT_KEY.items():
        keys = (_field_keys(shifts) if key == "depth_field"
                else [k for k in shifts if k.startswith("wiggle:")] if key == "depth_wiggle" else [sk])
        if key == "depth_wiggle" and not keys:
            continue                                  # no wiggle stated (stereo, or a document before it)
        size = _rss((_size(shifts.get(k), "tilt_rad"), _size(shifts.get(k), "height_m")) for k in keys)
        stated = allowance.get("wiggle_m") if key == "depth_wiggle" else allowance.get(sk)
        entry: dict[str, Any] = {**size, "allowance": float(stated or 0.0),
                                 "stated": _allowance_label(key, allowance)}
        if key == "depth_field":
            entry["shape"] = allowance.get("field_shape")
        out[key] = entry
    out["arm_accuracy"] = {**arm_term, "stated": "arm"}
    return out


def _pose_block(ff: Mapping[str, Any], arm: ArmModel) -> dict[str, Any] | None:
    eb = ff.get("error_budget")
    if not eb:
        return None
    height = ff.get("height_m") or 0.0
    block: dict[str, Any] = {k: {"tilt_rad": eb[k]["tilt_rad"], "height_m": eb[k]["height_m"] or 0.0}
                             for k in ("depth_scale_1pct", "depth_offset_1mm")}
    block["arm_accuracy"] = _arm(arm, height)
    block["at_allowance"] = _at_allowance(eb, block["arm_accuracy"])
    block["dominant"], block["judged"] = _dominant(block)
    return block


def _base_shift(term: Mapping[str, Any], r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """A camera-frame plane shift (``normal_cam``, ``offset_m``) as (normal change, offset change) in the base frame."""
    dn = r @ np.asarray(term["normal_cam"], dtype=np.float64)       # the normal's change in the base frame
    return np.append(dn, float(term["offset_m"]) - float(dn @ t))


def _consensus_term(shifts: list[np.ndarray]) -> dict[str, float]:
    mean = np.mean(np.asarray(shifts), axis=0)
    return {"tilt_rad": float(np.linalg.norm(mean[:3])), "height_m": float(mean[3])}


def error_budget(poses: Iterable[Mapping[str, Any]], arm: ArmModel | None = None) -> dict[str, Any] | None:
    """The result document's ``summary.error_budget``: per pose (camera frame) and for the consensus (base frame).

    The sensitivities (``depth_scale_1pct``, ``depth_offset_1mm``, ``arm_accuracy``) are signed as the
    fit answers; ``at_allowance`` holds each term's size (magnitudes) at the camera's stated
    allowance and the arm's stated accuracy, by which ``dominant`` is judged (``judged``: ``allowance``,
    or ``per unit`` when the poses carry no allowance). The depth field's shape is unknown before
    depthcal and each pose takes its own worst one: the consensus takes the poses' mean base-frame
    shift when every pose took the same shape, else the mean of their sizes (a field fixed to the
    pixels is the same error at every pose; different worst shapes are not).

    Args:
        poses: The result document's pose entries (``full_frame`` with its ``error_budget``, ``camera_pose``).
        arm: The arm's stated model (None: :data:`~cellcal.devices.arm_model.UNSTATED_ARM_MODEL`).

    Returns:
        ``{"arm_model", "poses": [{index, terms..., at_allowance, dominant, judged}],
        "consensus": {terms..., at_allowance, dominant, judged, next}}`` (tilt in rad, height in m);
        None when no pose has a full-frame budget.
    """
    arm = arm or UNSTATED_ARM_MODEL
    rows: list[dict[str, Any]] = []
    levers: list[float] = []
    shifts: dict[str, list[np.ndarray]] = {k: [] for k in ("depth_scale_1pct", "depth_offset_1mm")}
    at_shifts: list[dict[str, np.ndarray]] = []
    shapes: set[Any] = set()
    for p in poses:
        ff = p.get("full_frame") or {}
        block = _pose_block(ff, arm)
        if block is None:
            continue
        rows.append({"index": p.get("index"), **block})
        rot = Pose.from_dict(p["camera_pose"])
        r, t = rot.rotation_matrix, np.asarray(rot.translation)
        for k in shifts:
            shifts[k].append(_base_shift(ff["error_budget"][k], r, t))
        if block["at_allowance"] is not None:
            at_shifts.append({k: _base_shift(s, r, t)
                              for k, s in (ff["error_budget"].get("allowance_shifts") or {}).items()})
            shapes.add(block["at_allowance"]["depth_field"].get("shape"))
        levers.append(ff.get("height_m") or 0.0)
    if not rows:
        return None
    cons: dict[str, Any] = {k: _consensus_term(v) for k, v in shifts.items()}
    cons["arm_accuracy"] = _arm(arm, float(np.mean(levers)))
    cons["at_allowance"] = None
    if all(r["at_allowance"] is not None for r in rows):
        cons["at_allowance"] = _consensus_at_allowance(rows, at_shifts, shapes, cons["arm_accuracy"])
    cons["dominant"], cons["judged"] = _dominant(cons)
    cons["next"] = NEXT_STEP[cons["dominant"]["height"]]
    return {"arm_model": arm.to_dict(), "poses": rows, "consensus": cons}


def _consensus_at_allowance(rows: list[dict[str, Any]], at_shifts: list[dict[str, np.ndarray]], shapes: set[Any],
                            arm_term: Mapping[str, float]) -> dict[str, Any]:
    """The consensus's terms at the allowance: each error common to the poses, so their mean base-frame shift.

    The field's shapes are independent terms (their mean shifts' root sum of squares); a field of
    one worst shape per pose that differs between poses is not one error: the mean of the poses' sizes.
    """
    first = rows[0]["at_allowance"]
    keys = sorted({k for s in at_shifts for k in s})
    zero = np.zeros(4)
    mean = {k: _consensus_term([s.get(k, zero) for s in at_shifts]) for k in keys}
    at: dict[str, Any] = {}
    for key, sk in _SHIFT_KEY.items():
        if key not in first:
            continue                                  # no wiggle stated (stereo, or a document before it)
        if key == "depth_field" and "field" in keys and len(shapes) > 1:
            size = {w: float(np.mean([_size(r["at_allowance"][key], w) for r in rows]))
                    for w in ("tilt_rad", "height_m")}
        else:
            fkeys = (_field_keys(mean) if key == "depth_field"
                     else [k for k in mean if k.startswith("wiggle:")] if key == "depth_wiggle" else [sk])
            size = _rss((_size(mean.get(k), "tilt_rad"), _size(mean.get(k), "height_m")) for k in fkeys)
        at[key] = {**size, "allowance": first[key]["allowance"], "stated": first[key]["stated"]}
    at["depth_field"]["shape"] = first["depth_field"].get("shape") if len(shapes) == 1 else "per pose"
    at["arm_accuracy"] = {**arm_term, "stated": "arm"}
    return at


def _figure(key: str, term: Mapping[str, Any], what: str) -> str:
    """One term's figure: ``5 mm offset: 4.6 mm`` (height) or ``2 mm at the corner field: 0.51 deg`` (tilt)."""
    value = f"{_size(term, 'height_m') * 1000:.2g} mm" if what == "height_m" else \
        f"{math.degrees(_size(term, 'tilt_rad')):.2g} deg"
    if key == "arm_accuracy":
        return f"arm {value}"
    return f"{str(term['stated']).replace(' at the corner', '')} {ALLOWANCE_TERMS[key].split()[1]}: {value}"


def _judged_clause(block: Mapping[str, Any], what: str) -> str:
    """``depth offset dominates (5 mm offset: 4.6 mm; 0.2 % scale: 1.1 mm; ...)`` for tilt or height."""
    at = block["at_allowance"]
    dom = block["dominant"][what.split("_")[0]]
    order = [dom, *sorted((k for k in at if k != dom), key=lambda k: -_size(at[k], what))]
    return f"{term_label(dom)} dominates ({'; '.join(_figure(k, at[k], what) for k in order)})"


def budget_line(budget: Mapping[str, Any] | None) -> str:
    """One line for the terminal: the term dominating the consensus's height, the figures, what to calibrate next.

    Judged at the camera's stated allowance and the arm's stated accuracy, with the per-unit
    sensitivities after them; the tilt's dominant term is added when it is another one.
    """
    if not budget:
        return ""
    c = budget["consensus"]
    per_unit = (f"per 1 % scale {_size(c['depth_scale_1pct'], 'height_m') * 1000:.3g} mm, "
                f"per 1 mm offset {_size(c['depth_offset_1mm'], 'height_m') * 1000:.3g} mm")
    if c.get("judged") != "allowance" or not c.get("at_allowance"):
        dom = c["dominant"]["height"]
        return (f"error budget, height: {term_label(dom)} dominates per unit ({per_unit}, "
                f"arm {_size(c['arm_accuracy'], 'height_m') * 1000:.3g} mm; the camera states no allowance): "
                f"{c['next']}")
    line = f"error budget, height: {_judged_clause(c, 'height_m')[:-1]}; {per_unit})"
    if c["dominant"]["tilt"] != c["dominant"]["height"]:
        tdom = c["dominant"]["tilt"]
        line += f"; tilt: {term_label(tdom)} dominates ({_figure(tdom, c['at_allowance'][tdom], 'tilt_rad')})"
    return f"{line}: {c['next']}"


def pose_budget_line(budget: Mapping[str, Any] | None, index: Any) -> str:
    """A pose's budget line, only when it says something the consensus's line does not ("" otherwise).

    Said when the pose's dominant term (judged at the allowance) differs from the consensus's for
    the height or the tilt; its figures are in the report either way.
    """
    if not budget or budget["consensus"].get("judged") != "allowance":
        return ""
    row = next((r for r in budget["poses"] if r.get("index") == index), None)
    if row is None or row.get("judged") != "allowance":
        return ""
    cons = budget["consensus"]["dominant"]
    parts = [f"{what}: {_judged_clause(row, what + ('_m' if what == 'height' else '_rad'))}"
             for what in ("height", "tilt") if row["dominant"][what] != cons[what]]
    return "error budget, " + "; ".join(parts) if parts else ""


def budget_table(budget: Mapping[str, Any] | None) -> list[list[str]]:
    """Rows of a text "error budget" table of the consensus: term, stated, tilt (deg) and height (mm) at it, per unit.

    The first row is the header; the dominant (height) term's name is marked with ``*``.
    """
    if not budget:
        return []
    c = budget["consensus"]
    at = c.get("at_allowance") or {}
    dom = c["dominant"]["height"]
    out = [["term", "stated", "tilt (deg)", "height (mm)", "per 1 % / 1 mm: tilt (deg)", "height (mm)"]]
    for key, label in ALLOWANCE_TERMS.items():
        a = at.get(key)
        unit = c.get(_PER_UNIT.get(key, ""))
        if a is None and unit is None:
            continue
        out.append([label + (" *" if key == dom else ""),
                    "-" if a is None else ("accuracy" if key == "arm_accuracy" else str(a["stated"])),
                    "-" if a is None else f"{math.degrees(_size(a, 'tilt_rad')):.4f}",
                    "-" if a is None else f"{_size(a, 'height_m') * 1000:.3f}",
                    "-" if unit is None or key == "arm_accuracy" else f"{math.degrees(_size(unit, 'tilt_rad')):.4f}",
                    "-" if unit is None or key == "arm_accuracy" else f"{_size(unit, 'height_m') * 1000:.3f}"])
    return out


#: The hand-eye budget's values (``handeye.json`` ``error_budget.terms.*``), their labels and units.
HANDEYE_VALUES: dict[str, tuple[str, str]] = {
    "tx_m": ("tx", "mm"), "ty_m": ("ty", "mm"), "tz_m": ("tz", "mm"), "roll_rad": ("roll", "deg"),
    "pitch_rad": ("pitch", "deg"), "yaw_rad": ("yaw", "deg"), "plane_offset_m": ("plane offset", "mm")}
#: Labels of the hand-eye budget's terms (others are shown by their key).
HANDEYE_TERMS: dict[str, str] = {**TERMS, **ALLOWANCE_TERMS}


def handeye_value(key: str, value: Any) -> float | None:
    """A hand-eye budget value in the report's units (mm, degrees); None when absent."""
    if value is None:
        return None
    v = float(value)
    return math.degrees(v) if key.endswith("_rad") else v * 1000.0


def _short(value: float) -> str:
    """Two significant digits; below 0.0005 (mm or deg) shown as 0."""
    return "0" if value < 5e-4 else f"{value:.2g}"


def _largest(term: Mapping[str, Any]) -> tuple[float, float]:
    """A hand-eye term's largest translation (mm) and rotation (deg) of the mount."""
    t = max((abs(handeye_value(k, term.get(k)) or 0.0) for k in ("tx_m", "ty_m", "tz_m")), default=0.0)
    r = max((abs(handeye_value(k, term.get(k)) or 0.0) for k in ("roll_rad", "pitch_rad", "yaw_rad")), default=0.0)
    return t, r


def handeye_budget_line(document: Mapping[str, Any]) -> str:
    """One line for ``cellcal handeye``: the dominant term of the mount's budget, its largest moves, the next step.

    With ``at_allowance`` (each term at the camera's stated allowance and the arm's stated
    accuracy, by which ``dominant`` is judged) those figures, largest first, then the per-unit
    sensitivities; without it the sensitivities alone. "" when the document has no ``error_budget``.
    """
    eb = document.get("error_budget")
    if not isinstance(eb, Mapping) or not eb.get("terms"):
        return ""
    terms = eb["terms"]
    at = eb.get("at_allowance") if isinstance(eb.get("at_allowance"), Mapping) else None
    dom = str(eb.get("dominant") or "")
    shown = at or terms
    order = ([dom] if dom in shown else []) + sorted((k for k in shown if k != dom),
                                                      key=lambda k: -_largest(shown[k])[0])
    figures = "; ".join(f"{HANDEYE_TERMS.get(k, k)} {_short(t)} mm, {_short(r)} deg"
                        for k in order for t, r in [_largest(shown[k])])
    if at:
        per = {"depth_scale_1pct": "per 1 % scale", "depth_offset_1mm": "per 1 mm offset"}
        figures += "; " + ", ".join(f"{label} {_short(_largest(terms[k])[0])} mm" for k, label in per.items()
                                    if k in terms)
    head = f"{HANDEYE_TERMS.get(dom, dom)} dominates" if dom else "by term"
    nxt = eb.get("next")
    return f"error budget of the mount: {head} ({figures})" + (f": {nxt}" if nxt else "")
