"""The simulated scene of one study trial: plane rays, boxes (clutter), the trial's sim document.

The plane is ``z = 0`` in the base frame (so the plane frame of ``[sim] boxes`` is the base
frame); clutter is placed by exact ray/box occlusion (ADR 0012).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.calibration.calibrator import build_camera
from cellcal.devices.errors import CalibrationError
from cellcal.devices.geometry.camera_model import pixel_grid_rays
from cellcal.devices.pose import Pose
from cellcal.devices.registry import Registry
from cellcal.devices.types import Frame, Intrinsics

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = [
    "OBSERVED_BOX_MIN_M",
    "BoxSpec",
    "PlaneRays",
    "capture_frame",
    "observed_clutter",
    "occluded",
    "place_boxes",
    "plane_rays",
    "trial_document",
]

#: A frame pixel counts as "on a box" if it is invalid or this far in front of the plane, m.
OBSERVED_BOX_MIN_M = 0.01


@dataclass(frozen=True)
class BoxSpec:
    """One box on the plane ``z = 0`` (base frame == plane frame).

    Attributes:
        center_xy_m: Footprint centre, metres.
        half_xy_m: Half edge lengths of the footprint, metres.
        yaw_rad: Rotation about the plane normal, rad.
        height_m: Height, metres.
    """

    center_xy_m: tuple[float, float]
    half_xy_m: tuple[float, float]
    yaw_rad: float
    height_m: float

    def to_table(self) -> dict[str, Any]:
        """The ``[[sim.boxes]]`` entry."""
        return {"center_xy_m": [float(v) for v in self.center_xy_m],
                "size_m": [2.0 * self.half_xy_m[0], 2.0 * self.half_xy_m[1], float(self.height_m)],
                "yaw_deg": math.degrees(self.yaw_rad)}


@dataclass(frozen=True)
class PlaneRays:
    """The pixels' rays against the plane ``z = 0`` for one camera pose.

    Attributes:
        origin_m: Camera centre, base frame, metres.
        ground_m: Where each pixel's ray meets the plane, (H, W, 3), metres (NaN if never).
        on_plane: (H, W) True where the ray meets the plane in front of the camera.
        distance_m: Radial distance from the camera to ``ground_m``, (H, W), metres.
    """

    origin_m: FloatArray
    ground_m: FloatArray
    on_plane: BoolArray
    distance_m: FloatArray


def plane_rays(camera_in_base: Pose, intrinsics: Intrinsics) -> PlaneRays:
    """Intersect every pixel's ray (distortion honoured) with the plane ``z = 0``."""
    rays = pixel_grid_rays(intrinsics)
    dirs = rays @ camera_in_base.rotation.as_matrix().T
    o = np.asarray(camera_in_base.translation, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[2] / dirs[..., 2]
    on_plane = np.isfinite(t) & (t > 0)
    t = np.where(on_plane, t, np.nan)
    return PlaneRays(o, o + t[..., None] * dirs, on_plane, t)


def occluded(rays: PlaneRays, boxes: Sequence[BoxSpec], scale: float = 1.0,
             pixels: tuple[slice, slice] | None = None) -> BoolArray:
    """Which pixels' rays hit a box before the plane (boxes' footprints scaled by ``scale``).

    A box is a vertical prism on the plane; the ray toward ground point ``g`` crosses
    heights ``[0, h]`` along the plane segment ``g -> g + (h / o_z) (o - g)``, so it
    hits the box iff that segment meets the footprint (2D slab test, vectorised).

    Args:
        rays: Output of :func:`plane_rays`.
        boxes: The boxes.
        scale: Multiplier of every footprint about its centre.
        pixels: Optional (rows, cols) slices to evaluate a subsampled image.
    """
    sl = pixels or (slice(None), slice(None))
    g = rays.ground_m[sl][..., :2]
    ok = rays.on_plane[sl]
    g = np.where(ok[..., None], g, 0.0)
    out = np.zeros(ok.shape, dtype=bool)
    o = rays.origin_m
    for b in boxes:
        c, s = math.cos(b.yaw_rad), math.sin(b.yaw_rad)
        rot = np.array([[c, s], [-s, c]])  # world -> box local
        p0 = (g - np.asarray(b.center_xy_m)) @ rot.T
        d = (o[:2] - g) @ rot.T * (b.height_m / o[2])
        t_lo = np.zeros(ok.shape)
        t_hi = np.ones(ok.shape)
        for axis, half in enumerate(b.half_xy_m):
            hs = half * scale
            da, pa = d[..., axis], p0[..., axis]
            with np.errstate(divide="ignore", invalid="ignore"):
                t1, t2 = (-hs - pa) / da, (hs - pa) / da
            parallel = da == 0
            inside = np.abs(pa) <= hs
            t_lo = np.maximum(t_lo, np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2)))
            t_hi = np.minimum(t_hi, np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2)))
        out |= t_lo <= t_hi
    out &= ok
    return out


def place_boxes(rng: np.random.Generator, rays: PlaneRays, fraction: float, *, max_boxes: int = 3,
                height_m: tuple[float, float] = (0.03, 0.08), tolerance: float = 0.004
                ) -> tuple[list[BoxSpec], BoolArray]:
    """Boxes hiding ``fraction`` of the image's plane pixels.

    Draws 1..``max_boxes`` boxes (centres on random plane points seen by the central
    70 % of the image, random aspect, yaw and height), then scales their footprints
    together by bisection on a 4x-subsampled image until the occluded fraction is
    within ``tolerance`` of the request.

    Returns:
        The boxes and the (H, W) mask of the pixels they hide (full resolution).
    """
    if fraction <= 0:
        return [], np.zeros(rays.on_plane.shape, dtype=bool)
    h, w = rays.on_plane.shape
    n_plane = int(np.count_nonzero(rays.on_plane))
    if n_plane == 0:
        raise CalibrationError("no pixel sees the plane; cannot place boxes")
    k = int(rng.integers(1, max_boxes + 1))
    rows = rng.integers(int(0.15 * h), int(0.85 * h), size=4 * k)
    cols = rng.integers(int(0.15 * w), int(0.85 * w), size=4 * k)
    centres = [rays.ground_m[r, c, :2] for r, c in zip(rows, cols, strict=True) if rays.on_plane[r, c]][:k]
    if not centres:
        raise CalibrationError("no plane point near the image centre; cannot place boxes")
    span = float(np.nanmedian(rays.distance_m)) * 0.25
    boxes = []
    for centre in centres:
        aspect = float(rng.uniform(0.5, 2.0))
        base = span * float(rng.uniform(0.6, 1.4))
        boxes.append(BoxSpec((float(centre[0]), float(centre[1])), (base * math.sqrt(aspect), base / math.sqrt(aspect)),
                             float(rng.uniform(0.0, math.pi)), float(rng.uniform(*height_m))))
    sub = (slice(1, None, 4), slice(1, None, 4))
    n_sub = max(int(np.count_nonzero(rays.on_plane[sub])), 1)

    def frac(scale: float) -> float:
        return float(np.count_nonzero(occluded(rays, boxes, scale, sub))) / n_sub

    lo, hi = 0.0, 1.0
    while frac(hi) < fraction and hi < 64.0:
        lo, hi = hi, hi * 2.0
    scale = hi
    for _ in range(30):
        scale = 0.5 * (lo + hi)
        f = frac(scale)
        if abs(f - fraction) <= tolerance:
            break
        lo, hi = (scale, hi) if f < fraction else (lo, scale)
    boxes = [BoxSpec(b.center_xy_m, (b.half_xy_m[0] * scale, b.half_xy_m[1] * scale), b.yaw_rad, b.height_m)
             for b in boxes]
    return boxes, occluded(rays, boxes)


def observed_clutter(frame: Frame, rays: PlaneRays, camera_in_base: Pose) -> float:
    """Fraction of the plane pixels the frame shows as not the plane.

    A plane pixel counts if it is invalid or its point lies more than
    :data:`OBSERVED_BOX_MIN_M` in front of the plane (boxes' bottom centimetre is missed).
    """
    on = rays.on_plane
    n = int(np.count_nonzero(on))
    if n == 0:
        return math.nan
    pts = frame.xyz[on].astype(np.float64)
    z = pts @ camera_in_base.rotation.as_matrix()[2] + camera_in_base.translation[2]
    valid = frame.valid[on]
    with np.errstate(invalid="ignore"):
        box = ~valid | (z > OBSERVED_BOX_MIN_M)
    return float(np.count_nonzero(box)) / n


def trial_document(camera_in_base: Pose, boxes: Sequence[BoxSpec], seed: int, noise_scale: float,
                   camera: Mapping[str, Any] | None = None, artefacts: Mapping[str, Any] | None = None
                   ) -> dict[str, Any]:
    """The configuration document of one trial: a ``sim`` camera whose (identity-mounted)
    flange starts at the camera pose, over the plane ``z = 0`` with the boxes, with the
    ``[sim.artefacts]`` table ``artefacts`` (None: the sim's defaults, every artefact on).

    The camera has no systematic depth error and the arm no kinematic error (``[sim.systematic]``
    and ``[sim.arm_errors]`` off): the study measures what each method makes of the noise and the
    artefacts, i.e. the accuracy of a camera whose systematic error ``cellcal depthcal`` has
    calibrated (issue 39; what an uncalibrated one adds is the error budget's part)."""
    xyz_rpy = camera_in_base.as_xyz_rpy()
    section = {"backend": "sim", **dict(camera or {}), "noise_scale": float(noise_scale),
               "noise": bool(noise_scale > 0)}
    return {
        "cell": {"name": "study", "seed": int(seed)},
        "camera": section,
        "arm": {"backend": "sim"},
        "mount": {"translation_m": [0.0, 0.0, 0.0], "rpy_deg": [0.0, 0.0, 0.0]},
        "sim": {"plane_point_m": [0.0, 0.0, 0.0], "plane_normal": [0.0, 0.0, 1.0],
                "boxes": [b.to_table() for b in boxes],
                "initial_flange_translation_m": [float(v) for v in xyz_rpy[:3]],
                "initial_flange_rpy_deg": [math.degrees(float(v)) for v in xyz_rpy[3:]],
                "artefacts": dict(artefacts or {}),
                "systematic": {"enabled": False}, "arm_errors": {"enabled": False}},
    }


def capture_frame(document: Mapping[str, Any], registry: Registry | None = None,
                  timeout_s: float = 5.0) -> Frame:
    """Build the document's camera from the registry, connect, capture one frame, close."""
    camera = build_camera(document, registry, source="<study>")
    with camera.connect(timeout_s):
        return camera.capture(timeout_s)
