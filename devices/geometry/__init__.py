"""Geometry every layer needs: the camera model and vendor pose conventions."""

from cellcal.devices.geometry.camera_model import (
    NominalFovModel,
    normalized_to_pixels,
    pixel_grid_rays,
    pixel_rays,
    pixels_to_normalized,
    project,
    triangulate,
    undistort_pixels,
)
from cellcal.devices.geometry.vendor_poses import (
    pose_from_ur,
    pose_from_xarm,
    pose_to_ur,
    pose_to_xarm,
)

__all__ = [
    "NominalFovModel",
    "normalized_to_pixels",
    "pixel_grid_rays",
    "pixel_rays",
    "pixels_to_normalized",
    "pose_from_ur",
    "pose_from_xarm",
    "pose_to_ur",
    "pose_to_xarm",
    "project",
    "triangulate",
    "undistort_pixels",
]
