"""calibrate's error budget: what a 1 % depth scale, a 1 mm depth offset and the arm's accuracy do to the plane.

Each pose's full-frame fit states what a 1 % depth scale and a 1 mm depth offset do to its plane in
the camera frame (``full_frame.error_budget``, :mod:`cellcal.core.methods.fullframe.systematic`).
The plane in the base frame also moves with the flange pose's error: the arm's absolute position
accuracy along the normal moves its height, its orientation accuracy tilts it (and, over the
lever from the flange to the plane, moves its height too). A depth error is common to every pose,
so the consensus moves by the poses' mean shift in the base frame (an equal-weight mean standing
for the consensus's weights); the arm's accuracy errs smoothly with the pose, so it is not taken
to average out either. The term that moves the height most is named, with what to calibrate next.
Rationale: docs/adr/0059-systematic-allowance-and-error-budget.md.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from cellcal.devices.arm_model import UNSTATED_ARM_MODEL, ArmModel
from cellcal.devices.pose import Pose

__all__ = ["NEXT_STEP", "budget_line", "error_budget"]

#: Budget terms, their labels for people, and what to calibrate when a term dominates.
TERMS: dict[str, str] = {"depth_scale_1pct": "depth scale (1 %)", "depth_offset_1mm": "depth offset (1 mm)",
                         "arm_accuracy": "arm accuracy"}
NEXT_STEP: dict[str, str] = {"depth_scale_1pct": "run cellcal depthcal", "depth_offset_1mm": "run cellcal depthcal",
                             "arm_accuracy": "calibrate the arm's kinematics (or state its accuracy in [arm.model])"}


def _arm(arm: ArmModel, lever_m: float) -> dict[str, float]:
    return {"tilt_rad": arm.accuracy_rad, "height_m": math.hypot(arm.accuracy_m, arm.accuracy_rad * lever_m)}


def _dominant(block: Mapping[str, Mapping[str, float]]) -> dict[str, str]:
    out = {}
    for what in ("tilt_rad", "height_m"):
        out[what.split("_")[0]] = max(TERMS, key=lambda k: abs(block[k][what] or 0.0))
    return out


def _pose_block(ff: Mapping[str, Any], arm: ArmModel) -> dict[str, Any] | None:
    eb = ff.get("error_budget")
    if not eb:
        return None
    height = ff.get("height_m") or 0.0
    block: dict[str, Any] = {k: {"tilt_rad": eb[k]["tilt_rad"], "height_m": eb[k]["height_m"] or 0.0}
                             for k in ("depth_scale_1pct", "depth_offset_1mm")}
    block["arm_accuracy"] = _arm(arm, height)
    block["dominant"] = _dominant(block)
    return block


def error_budget(poses: Iterable[Mapping[str, Any]], arm: ArmModel | None = None) -> dict[str, Any] | None:
    """The result document's ``summary.error_budget``: per pose (camera frame) and for the consensus (base frame).

    Args:
        poses: The result document's pose entries (``full_frame`` with its ``error_budget``, ``camera_pose``).
        arm: The arm's stated model (None: :data:`~cellcal.devices.arm_model.UNSTATED_ARM_MODEL`).

    Returns:
        ``{"arm_model", "poses": [{index, terms..., dominant}], "consensus": {terms..., dominant, next}}``
        (tilt in rad, height in m); None when no pose has a full-frame budget.
    """
    arm = arm or UNSTATED_ARM_MODEL
    rows: list[dict[str, Any]] = []
    levers: list[float] = []
    shifts: dict[str, list[np.ndarray]] = {k: [] for k in ("depth_scale_1pct", "depth_offset_1mm")}
    for p in poses:
        ff = p.get("full_frame") or {}
        block = _pose_block(ff, arm)
        if block is None:
            continue
        rows.append({"index": p.get("index"), **block})
        rot = Pose.from_dict(p["camera_pose"])
        r, t = rot.rotation_matrix, np.asarray(rot.translation)
        for k in shifts:
            term = ff["error_budget"][k]
            dn = r @ np.asarray(term["normal_cam"], dtype=np.float64)       # the normal's change in the base frame
            shifts[k].append(np.append(dn, float(term["offset_m"]) - float(dn @ t)))
        levers.append(ff.get("height_m") or 0.0)
    if not rows:
        return None
    cons: dict[str, Any] = {}
    for k, v in shifts.items():
        mean = np.mean(np.asarray(v), axis=0)
        cons[k] = {"tilt_rad": float(np.linalg.norm(mean[:3])), "height_m": float(mean[3])}
    cons["arm_accuracy"] = _arm(arm, float(np.mean(levers)))
    cons["dominant"] = _dominant(cons)
    cons["next"] = NEXT_STEP[cons["dominant"]["height"]]
    return {"arm_model": arm.to_dict(), "poses": rows, "consensus": cons}


def budget_line(budget: Mapping[str, Any] | None) -> str:
    """One line for the terminal: the term dominating the consensus's height and what to calibrate next."""
    if not budget:
        return ""
    c = budget["consensus"]
    dom = c["dominant"]["height"]
    figures = ", ".join(f"{TERMS[k]} {abs(c[k]['height_m']) * 1000:.3g} mm" for k in TERMS)
    return f"error budget: {TERMS[dom].split(' (')[0]} dominates the height ({figures}): {c['next']}"


def budget_table(budget: Mapping[str, Any] | None) -> list[list[str]]:
    """Rows of the report's "error budget" table: term, tilt (deg) and height (mm), consensus and pose range."""
    if not budget:
        return []
    out = [["term", "consensus tilt (deg)", "consensus height (mm)", "per pose height (mm)"]]
    for k, label in TERMS.items():
        c = budget["consensus"][k]
        hs = [abs(r[k]["height_m"]) * 1000 for r in budget["poses"]]
        out.append([label, f"{math.degrees(c['tilt_rad']):.4f}", f"{abs(c['height_m']) * 1000:.3f}",
                    f"{min(hs):.3f}-{max(hs):.3f}"])
    return out
