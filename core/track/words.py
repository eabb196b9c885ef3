"""What ``cellcal track`` says: a change event in one line, the end-of-run summary of a camera.

Lengths are printed in mm and angles in degrees; the documents keep SI units.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from cellcal.core.track.run import TrackOutcome
    from cellcal.core.track.state import ChangeEvent

__all__ = ["event_line", "fixed_summary_lines", "frames_line", "summary_lines"]


def _mm(v: float | None) -> str:
    return "n/a" if v is None or not math.isfinite(v) else f"{v * 1e3:.3f} mm"


def event_line(event: ChangeEvent, *, final: bool = True, fixed: bool = False) -> str:
    """One line for a change event: when, which, how large, resolved or not.

    While the run goes on (``final=False``) the size is the first fit's, from one or two poses:
    the rotation is told, the translation only once the whole run has been seen. A fixed camera's
    (``fixed``) is how the plane moved in its view: its own move or the plane's (the cell's summary says which).
    """
    size = event.size
    later = "" if final else " (its size is refined as the work shows more)"
    if fixed:
        what = ("the camera or the plane moved: cannot tell yet" if "view_tilt_deg" not in size else
                f"the plane moved in the camera's view: {size['view_tilt_deg']:.3f} deg, "
                f"{_mm(size.get('view_shift_m'))} along its normal")
    elif event.kind == "mount" and "rotation_deg" in size:
        moved = _mm(size.get("translation_m")) if final else ""
        what = f"the mount moved: {size['rotation_deg']:.3f} deg{', ' + moved if moved else ''}{later}"
    elif event.kind == "plane" and "plane_tilt_deg" in size:
        shift = f", {_mm(size.get('plane_shift_m'))} along its normal" if final else ""
        what = f"the plane moved: {size['plane_tilt_deg']:.3f} deg{shift}{later}"
    else:
        what = "mount or plane: cannot tell yet"
    state = f"; resolved at t={event.resolved_at_s:.1f} s" if event.resolved_at_s is not None else ""
    return f"t={event.detected_at_s:.1f} s: change detected ({what}){state}"


def summary_lines(outcome: TrackOutcome) -> list[str]:
    """The end-of-run summary: frames, the mount with its intervals, the plane, what is not seen, events."""
    from cellcal.core.calibration.report import ABOVE_NOTE, plane_height_mm

    doc = outcome.document
    lines = [frames_line(doc)]
    iv = doc["intervals"]
    conf = f"{iv['confidence'] * 100:g} %"
    mount = doc["mount"]
    axes = ("x", "y", "z")
    t_int, r_int = iv["mount_translation_m"], iv["mount_rpy_deg"]
    parts = []
    for i, a in enumerate(axes):
        lo_hi = t_int[i]
        span = f" [{lo_hi[0] * 1e3:.3f}, {lo_hi[1] * 1e3:.3f}]" if lo_hi else " (not seen)"
        parts.append(f"{a} {mount['translation_m'][i] * 1e3:.3f}{span}")
    lines.append(f"mount translation, mm ({conf}): " + ", ".join(parts))
    parts = []
    for i, a in enumerate(("roll", "pitch", "yaw")):
        lo_hi = r_int[i]
        span = f" [{lo_hi[0]:.4f}, {lo_hi[1]:.4f}]" if lo_hi else " (not seen)"
        parts.append(f"{a} {mount['rpy_deg'][i]:.4f}{span}")
    lines.append(f"mount rotation, deg ({conf}): " + ", ".join(parts))
    plane = doc["plane"]
    lines.append(f"plane (base frame): normal [{', '.join(f'{v:.5f}' for v in plane['normal'])}], "
                 f"{plane_height_mm(plane):+.3f} mm above the base origin")
    lines.append(ABOVE_NOTE)
    if iv.get("withheld"):
        lines.append(f"intervals withheld: {iv['withheld']}")
    for text in doc["unseen"]:
        lines.append(f"not seen yet: {text}")
    for event in outcome.state.events:
        lines.append(event_line(event))
    if doc["change_unresolved"]:
        lines.append("a change is open: the frames after it have not shown every parameter again")
    return lines


def frames_line(doc: dict[str, Any]) -> str:
    """Frames seen, used, held out and skipped (with why)."""
    c = doc["counters"]
    why = {k: v for k, v in sorted(c.items()) if k.startswith(("skipped", "refused", "no plane"))}
    reasons = ", ".join(f"{k.split(': ', 1)[-1]} {v}" for k, v in why.items()) or "none"
    return (f"frames: {c.get('frames', 0)}, used {c.get('accepted', 0)}, held out {c.get('held out', 0)}, "
            f"skipped {sum(why.values())} ({reasons})")


def fixed_summary_lines(outcome: TrackOutcome) -> list[str]:
    """A fixed camera's summary: frames, its view of the plane against the configured one, the plane, events."""
    from cellcal.core.calibration.report import plane_height_mm

    doc = outcome.document
    view, drift, plane = doc["view"], doc["drift"], doc["plane"]
    normal = ", ".join(f"{v:.5f}" for v in plane["normal"])
    lines = [frames_line(doc),
             f"view of the plane (camera frame): {view['offset_m'] * 1e3:.3f} mm away; {drift['tilt_deg']:.3f} deg "
             f"and {drift['shift_m'] * 1e3:+.3f} mm (toward the camera) from the configured pose's view",
             f"plane (base frame, through the configured pose): normal [{normal}], "
             f"{plane_height_mm(plane):+.3f} mm above the base origin"]
    lines += [event_line(event, fixed=True) for event in outcome.state.events]
    return lines
