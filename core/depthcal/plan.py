"""The ``cellcal depthcal`` plan: heights x inclinations x tool rolls over the reference plane.

What the depth calibration must see (ADR 0057): the plane at several distances (the arm's
known motion between them fixes the depth scale and offset), and its slope crossing the
image in several directions (a field fixed to the pixels moves with the camera, the plane's
geometry does not). Each view is built as ``cellcal handeye`` builds its views
(:func:`cellcal.core.handeye.plan.view_pose`: the tool pitched toward the base and rolled
about its axis, which a 5-axis arm can do), its optical axis meeting the target at the
view's height. Every pose is checked against the arm class and every move against
``[safety]`` before anything moves.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cellcal.core.calibration.config import CellConfig
from cellcal.core.handeye.plan import MAX_ITERATIONS, YAW_TOLERANCE_RAD, check_plan
from cellcal.devices.errors import CalibrationQualityError, ConfigError
from cellcal.devices.pose import Pose

__all__ = ["MIN_HEIGHT_SPAN_M", "Coverage", "PlanView", "depthcal_heights", "depthcal_plan", "plan_coverage",
           "view_pose"]

#: The default heights span at least this much, metres (the arm's motion between them fixes the scale).
MIN_HEIGHT_SPAN_M = 0.3
#: Heights of the default plan.
DEFAULT_N_HEIGHTS = 3


@dataclass(frozen=True)
class PlanView:
    """One view of the plan: its flange pose and what it was made for.

    Attributes:
        pose: The flange pose, base frame.
        height_m: The camera's distance from the target along its optical axis, metres.
        inclination_deg: The optical axis' angle with the plane, degrees.
        roll_deg: The tool's roll about its axis, degrees.
        target_m: Where the optical axis meets the plane, base frame, metres.
    """

    pose: Pose
    height_m: float
    inclination_deg: float
    roll_deg: float
    target_m: tuple[float, float, float]

    def label(self) -> str:
        """``h 0.450 m, 80 deg, roll 90`` (for the dry run and the report)."""
        return f"h {self.height_m:.3f} m, {self.inclination_deg:g} deg, roll {self.roll_deg:g}"


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _radial_matrix(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """:func:`~cellcal.devices.geometry.reach.radial_flange_rotation` as a matrix, without scipy's import.

    Tool down (about x by pi), pitched in the vertical plane at base yaw ``yaw``, rolled about the tool axis.
    """
    c, s = math.cos(pitch), math.sin(pitch)
    ry = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    rx_pi = np.diag([1.0, -1.0, -1.0])
    out: np.ndarray = _rz(yaw) @ ry @ rx_pi @ _rz(roll)
    return out


def view_pose(target_m: np.ndarray, height_m: float, inclination_rad: float, roll_rad: float, mount: Pose) -> Pose:
    """The flange pose whose camera's optical axis meets ``target_m`` at ``height_m``.

    :func:`cellcal.core.handeye.plan.view_pose`'s view (the tool pitched toward the base within the
    vertical plane through the base axis, rolled about its axis) in rotation matrices, so that the plan
    does not import scipy (0.3 s or more of a run that otherwise needs none).

    Raises:
        ConfigError: If the flange yaw does not converge (target on the base axis).
    """
    pitch = math.pi / 2 - inclination_rad
    yaw = math.atan2(target_m[1], target_m[0])
    mount_r, mount_t = mount.rotation_matrix, np.asarray(mount.translation, dtype=np.float64)
    for _ in range(MAX_ITERATIONS):
        rot = _radial_matrix(yaw, pitch, roll_rad)
        axis = rot @ mount_r[:, 2]  # optical axis in the base frame
        flange = target_m - height_m * axis - rot @ mount_t
        new_yaw = math.atan2(flange[1], flange[0])
        step = math.remainder(new_yaw - yaw, 2 * math.pi)
        yaw = new_yaw
        if abs(step) < YAW_TOLERANCE_RAD:
            return Pose.from_rotation_matrix(_radial_matrix(yaw, pitch, roll_rad), flange)
    raise ConfigError("no flange yaw puts the tool in the base's vertical plane for this view (target "
                      f"{np.round(target_m, 3).tolist()} m too close to the base axis?)", key="depthcal.target_m")


def depthcal_heights(config: CellConfig) -> tuple[float, ...]:
    """The plan's heights: ``[depthcal] heights_m``, else three over the ``[plan]`` heights widened to 0.3 m."""
    dc = config.depthcal
    if dc.heights_m is not None:
        return tuple(dc.heights_m)
    lo, hi = min(config.plan.heights_m), max(config.plan.heights_m)
    if hi - lo < MIN_HEIGHT_SPAN_M:
        mid = (lo + hi) / 2
        lo, hi = mid - MIN_HEIGHT_SPAN_M / 2, mid + MIN_HEIGHT_SPAN_M / 2
    return tuple(round(float(h), 4) for h in np.linspace(lo, hi, DEFAULT_N_HEIGHTS))


def _rolls(rolls: Sequence[float], height_index: int, inclination_index: int) -> list[float]:
    """The two rolls of a tilted view: consecutive ``rolls`` from a start that moves by two per height."""
    n = len(rolls)
    start = 2 * (height_index + inclination_index)
    return [float(rolls[start % n])] if n == 1 else [float(rolls[start % n]), float(rolls[(start + 1) % n])]


def depthcal_plan(config: CellConfig) -> list[PlanView]:
    """The plan's views in order, every pose reach- and envelope-checked.

    Raises:
        ConfigError: Without a ``[reference]`` plane, or one that is not horizontal.
        SafetyError: Naming the first pose the arm class cannot take or the first move out of ``[safety]``.
    """
    ref = config.reference
    if ref is None:
        raise ConfigError("cellcal depthcal needs a [reference] plane (the plan is built around it)",
                          source=config.source, key="reference")
    normal = np.asarray(ref.plane_normal, dtype=np.float64)
    if abs(normal[2]) / np.linalg.norm(normal) < math.cos(math.radians(5.0)):
        raise ConfigError("the depthcal plan assumes a horizontal reference plane (normal within 5 deg of z)",
                          source=config.source, key="reference.plane_normal")
    dc = config.depthcal
    target0 = np.asarray(dc.target_m if dc.target_m is not None else config.plan.target_m, dtype=np.float64)
    mount = config.mount.pose()
    views: list[PlanView] = []
    for ih, height in enumerate(depthcal_heights(config)):
        shift = ((ih + 1) % 3 - 1) * dc.offset_m  # 0, +, -, 0, ... across the base's y axis
        target = target0 + np.array([0.0, shift, 0.0])
        tilted = 0
        for incl in dc.inclinations_deg:
            rolls = [float(dc.rolls_deg[ih % len(dc.rolls_deg)])] if incl >= 90.0 else \
                _rolls(dc.rolls_deg, ih, tilted)
            tilted += incl < 90.0
            for roll in rolls:
                pose = view_pose(target, height, math.radians(incl), math.radians(roll), mount)
                views.append(PlanView(pose, float(height), float(incl), roll,
                                      (float(target[0]), float(target[1]), float(target[2]))))
    check_plan(config, [v.pose for v in views])
    return views


@dataclass(frozen=True)
class Coverage:
    """What a plan's geometry lets the fit see, before anything moves.

    Attributes:
        heights_m: The distinct heights, metres.
        inclinations_deg: The distinct inclinations, degrees.
        slope_directions: The distinct directions (degrees in the image, 0 = +u) the plane's slope takes.
        notes: What the plan cannot see, one sentence each (empty: all of it).
    """

    heights_m: tuple[float, ...]
    inclinations_deg: tuple[float, ...]
    slope_directions: tuple[float, ...]
    notes: tuple[str, ...]

    def check(self, n_poses: int) -> None:
        """Refuse a plan that cannot see a term of the correction, before anything connects or moves.

        Raises:
            CalibrationQualityError: Gate ``observability`` (the number of unseen terms against 0),
                naming each and what would show it.
        """
        if self.notes:
            raise CalibrationQualityError("observability", len(self.notes), 0,
                                          f"{n_poses} poses cannot calibrate the depth: {'; '.join(self.notes)}")

    def message(self) -> str:
        """One line: what the plan spans and what it cannot see."""
        lo, hi = 1000 * min(self.heights_m), 1000 * max(self.heights_m)
        incl = ", ".join(f"{i:g}" for i in self.inclinations_deg)
        span = (f"{len(self.heights_m)} heights ({lo:.0f}-{hi:.0f} mm), {len(self.inclinations_deg)} inclinations "
                f"({incl} deg), the plane's slope in {len(self.slope_directions)} image directions")
        return span + ("; " + "; ".join(self.notes) if self.notes else "; scale, offset and field all observable")


def plan_coverage(config: CellConfig, views: Sequence[PlanView]) -> Coverage:
    """What the plan spans: its heights, inclinations and the image directions of the plane's slope.

    The notes name what it cannot see: the depth scale with one height; the image field (when
    ``[depthcal] field_max_order`` > 0) without a tilted view or with the slope one way only.
    """
    mount = config.mount.pose()
    ref = config.reference
    normal = np.asarray(ref.plane_normal if ref is not None else (0.0, 0.0, 1.0), dtype=np.float64)
    normal /= np.linalg.norm(normal)
    heights = tuple(sorted({round(v.height_m, 4) for v in views}))
    incl = tuple(sorted({round(v.inclination_deg, 3) for v in views}, reverse=True))
    directions: set[float] = set()
    for v in views:
        if v.inclination_deg >= 90.0:
            continue
        n_cam = (v.pose @ mount).rotation_matrix.T @ normal  # the plane's normal seen from the camera
        directions.add(float(5 * round(math.degrees(math.atan2(n_cam[1], n_cam[0])) / 5) % 360))
    notes = []
    if len(heights) < 2:
        notes.append("one height: the depth scale cannot be told from the offset (add heights_m)")
    fits_field = config.depthcal.field_max_order > 0  # without a field the slope's directions decide nothing
    if fits_field and not directions:
        notes.append("no tilted view: the image field cannot be told from the plane's height (add inclinations < 90)")
    elif fits_field and len(directions) < 2:
        notes.append("the slope crosses the image one way only: the field across it is not seen (add rolls_deg)")
    return Coverage(heights, incl, tuple(sorted(directions)), tuple(notes))
