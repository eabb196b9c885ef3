"""Where the fit looks at one pose: the ``[region]`` pixel mask and the expected plane (ADR 0031).

The region is a set of pixels fixed before the frame is read (a polygon in the image, a
base-frame box seen through the camera model), so the gates' valid fraction and coverage
over it keep their meaning; the expected plane is ``[reference]`` seen from the camera.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellcal.core.calibration.sections import ReferenceSection, RegionSection
from cellcal.core.methods.fullframe.expected import ExpectedPlane
from cellcal.core.methods.measure import ExpectedGeometry
from cellcal.devices.errors import CalibrationError, ConfigError
from cellcal.devices.geometry.camera_model import pixel_grid_rays
from cellcal.devices.pose import Pose
from cellcal.devices.types import Intrinsics

BoolArray = NDArray[np.bool_]

__all__ = ["box_mask", "expected_plane", "polygon_mask", "region_document", "region_mask"]

def polygon_mask(vertices_px: ArrayLike, shape: tuple[int, int]) -> BoolArray:
    """The pixels inside a polygon, its edges included, as an (H, W) bool mask.

    Args:
        vertices_px: (N, 2) vertices ``(u, v)``, pixels of the image (centres at integer
            coordinates, ``u`` along the columns, ``v`` down the rows), N >= 3; each is
            rounded to the nearest pixel centre.
        shape: Image shape (H, W), pixels.
    """
    # vertices rounded to pixel centres (OpenCV's fill rounds fractional vertices anyway)
    pts = np.rint(np.asarray(vertices_px, np.float64)).astype(np.int32).reshape(-1, 1, 2)
    canvas = np.zeros(shape, np.uint8)
    # fill the polygon and its edges (8-connected boundary pixels are inside)
    cv2.fillPoly(canvas, [pts], 1, lineType=cv2.LINE_8)
    out: BoolArray = canvas.astype(bool)
    return out


def box_mask(intrinsics: Intrinsics, camera_in_base: Pose, box_min_m: ArrayLike, box_max_m: ArrayLike) -> BoolArray:
    """The pixels whose centre ray passes through an axis-aligned base-frame box, as an (H, W) bool mask.

    The rays come from the lens model (distortion honoured), not from the measurement, so
    an invalid pixel looking at the box is still in the region.

    Args:
        intrinsics: The camera's lens model (gives the image size).
        camera_in_base: Camera pose in the base frame (``T_base_camera``, metres).
        box_min_m: Smallest corner of the box, base frame, metres.
        box_max_m: Largest corner of the box, base frame, metres.
    """
    rays_cam = pixel_grid_rays(intrinsics)                                   # (H, W, 3) unit rays, camera frame
    h, w = rays_cam.shape[:2]
    # (N, 3) the rays' base-frame directions (OpenCV's 3x3 transform: 3x faster than numpy's matmul here)
    rays_base = cv2.transform(rays_cam.reshape(-1, 1, 3), camera_in_base.rotation_matrix).reshape(-1, 3)
    origin = np.asarray(camera_in_base.translation, np.float64)             # optical centre, base frame, m
    lo = np.asarray(box_min_m, np.float64) - origin                          # box corners relative to the centre, m
    hi = np.asarray(box_max_m, np.float64) - origin
    t_in = np.zeros(h * w)                                                   # entry: not behind the camera, m
    t_out = np.full(h * w, np.inf)                                           # exit, m
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis in range(3):                                                # slab method, one pair of faces at a time
            d = rays_base[:, axis]
            t_lo, t_hi = lo[axis] / d, hi[axis] / d                          # metres along the unit ray to each face
            # the slab's entry and exit; NaN (a ray in a face's plane) constrains nothing
            np.fmax(t_in, np.fmin(t_lo, t_hi), out=t_in)
            np.fmin(t_out, np.fmax(t_lo, t_hi), out=t_out)
    # a hit: the slabs overlap ahead of the camera (undistortion failures hold NaN rays: no hit)
    hit: BoolArray = ((t_out >= t_in) & ~np.isnan(rays_base[:, 0])).reshape(h, w)
    return hit


def _check_vertices(vertices_px: tuple[tuple[float, float], ...], shape: tuple[int, int], source: str | None) -> None:
    """Refuse a vertex more than one image size beyond the image's edge (a unit or axis mistake).

    Raises:
        ConfigError: Naming ``region.polygon_px[i]``.
    """
    h, w = shape
    for i, (u, v) in enumerate(vertices_px):
        if not (-w <= u <= 2 * w - 1 and -h <= v <= 2 * h - 1):
            raise ConfigError(f"vertex ({u:g}, {v:g}) px lies more than one image size outside the {w}x{h} "
                              f"depth image (u along its {w} columns, v down its {h} rows)", source=source,
                              key=f"region.polygon_px[{i}]")


def region_mask(region: RegionSection, intrinsics: Intrinsics, camera_in_base: Pose, *,
                source: str | None = None) -> BoolArray | None:
    """The region of interest at one pose, as an (H, W) bool mask; None for the whole image.

    Args:
        region: The ``[region]`` table.
        intrinsics: The lens model of the frames (gives the image size).
        camera_in_base: Camera pose in the base frame (arm read-back @ mount), metres.
        source: The configuration file, for messages.

    Raises:
        ConfigError: A polygon vertex far outside the image (naming the key).
        CalibrationError: The region holds no pixel of the image at this pose.
    """
    if region.whole_image:
        return None
    shape = (intrinsics.height, intrinsics.width)
    mask = np.ones(shape, bool)
    if region.polygon_px is not None:
        _check_vertices(region.polygon_px, shape, source)
        mask &= polygon_mask(region.polygon_px, shape)
    if region.box_min_m is not None and region.box_max_m is not None:
        mask &= box_mask(intrinsics, camera_in_base, region.box_min_m, region.box_max_m)
    if not mask.any():
        raise CalibrationError(f"the region of interest ([region]: {describe_region(region)}) holds no pixel "
                               f"of the {intrinsics.width}x{intrinsics.height} image at this pose")
    return mask


def describe_region(region: RegionSection) -> str:
    """One line for humans: what the region is (millimetres for the box)."""
    parts = []
    if region.polygon_px is not None:
        parts.append(f"polygon of {len(region.polygon_px)} vertices")
    if region.box_min_m is not None and region.box_max_m is not None:
        lo = ", ".join(f"{1000 * x:.0f}" for x in region.box_min_m)
        hi = ", ".join(f"{1000 * x:.0f}" for x in region.box_max_m)
        parts.append(f"base-frame box [{lo}]..[{hi}] mm")
    return " within the ".join(parts) or "whole image"


def region_document(region: RegionSection, mask: BoolArray | None) -> dict[str, Any] | None:
    """The pose record's ``full_frame.region`` (JSON form, pixels and metres); None for the whole image."""
    if mask is None:
        return None
    return {
        "polygon_px": None if region.polygon_px is None else [list(v) for v in region.polygon_px],
        "box_min_m": None if region.box_min_m is None else list(region.box_min_m),
        "box_max_m": None if region.box_max_m is None else list(region.box_max_m),
        "n_pixels": int(np.count_nonzero(mask)),
        "fraction_of_image": float(np.count_nonzero(mask) / mask.size),
    }


def expected_plane(reference: ReferenceSection | None, geometry: ExpectedGeometry | None) -> ExpectedPlane | None:
    """The plane the fit should find at one pose: ``[reference]`` in the camera frame, with its tolerances.

    Args:
        reference: The reference the fit searches near (``CellConfig.search_reference``), or None.
        geometry: The reference seen from the camera at this pose (normal toward the camera), or None.

    Returns:
        None when either is None (no search).
    """
    if reference is None or geometry is None:
        return None
    return ExpectedPlane(geometry.plane_cam, reference.search_tolerance_rad, reference.search_tolerance_m)
