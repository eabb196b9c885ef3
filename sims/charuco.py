"""A printed ChArUco board lying on the simulated measuring plane (``[sim.charuco]``).

The board is a reflectivity texture: where a pixel's footprint falls on it, the plane's
near-infrared reflectivity becomes that of the print (dark or light), so the board shows
in the ToF camera's amplitude image as on a real one (and the range noise of the dark
squares grows with their weaker return). Each pixel averages ``supersample``² sub-rays
through the real lens model, so edges are anti-aliased. The board frame is OpenCV's
(origin at the board's top-left outer corner, x along the columns, y along the rows, z
into the table), so ``cv2.aruco.CharucoBoard.getChessboardCorners()`` are its points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.geometry.camera_model import pixel_rays
from cellcal.devices.pose import Pose
from cellcal.devices.types import Intrinsics

FloatArray = NDArray[np.float64]
#: OpenCV ArUco dictionaries a board may use.
Dictionary = Literal["4X4_50", "4X4_100", "5X5_50", "5X5_100", "6X6_50", "6X6_250"]


@dataclass(frozen=True)
class CharucoConfig:
    """The ``[sim.charuco]`` table: a ChArUco board lying face up on the measuring plane."""

    center_m: tuple[float, float, float] = field(
        default=(0.3, 0.0, 0.0), metadata={"ge": -10.0, "le": 10.0, "doc": "board centre, base frame (onto the plane)"})
    yaw_deg: float = field(default=0.0, metadata={"ge": -360.0, "le": 360.0,
                                                  "doc": "turn of the board about the plane normal, degrees"})
    squares: tuple[int, int] = field(default=(7, 5), metadata={"ge": 2, "le": 40, "doc": "squares (columns, rows)"})
    square_m: float = field(default=0.04, metadata={"gt": 0.001, "le": 1.0, "doc": "square side, m"})
    marker_ratio: float = field(default=0.75, metadata={"ge": 0.3, "le": 0.95, "doc": "marker side / square side"})
    dictionary: Dictionary = field(default="4X4_50", metadata={"doc": "the OpenCV ArUco dictionary of the markers"})
    dark_reflectivity: float = field(default=0.05, metadata={"gt": 0.0, "le": 2.0, "doc": "reflectivity of the ink"})
    light_reflectivity: float = field(default=0.9, metadata={"gt": 0.0, "le": 2.0,
                                                             "doc": "reflectivity of the paper"})
    supersample: int = field(default=3, metadata={"ge": 1, "le": 8, "doc": "sub-rays per pixel and axis"})
    texture_px_per_square: int = field(default=80, metadata={"ge": 10, "le": 400,
                                                             "doc": "texture resolution, px per square"})
    on: Literal["plane", "plate"] = field(default="plane", metadata={
        "doc": "where the board is printed: on the measuring plane (at center_m), or on the face of the plate the "
               "arm holds ([sim.plate], centred on it, turned by yaw_deg about its normal): a fixed camera's board"})

    @property
    def size_m(self) -> tuple[float, float]:
        """Board width (along the columns) and height, metres."""
        return self.squares[0] * self.square_m, self.squares[1] * self.square_m

    def board(self):  # type: ignore[no-untyped-def]  # cv2 types
        """The OpenCV board (``cv2.aruco.CharucoBoard``)."""
        import cv2

        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, f"DICT_{self.dictionary}"))
        return cv2.aruco.CharucoBoard(self.squares, self.square_m, self.square_m * self.marker_ratio, dictionary)

    def pose_on_plane(self, plane_point_m: FloatArray, plane_normal: FloatArray) -> Pose:
        """``T_base_board``: the board face up on the plane, centred at ``center_m`` projected onto it."""
        from scipy.spatial.transform import Rotation

        n = plane_normal / np.linalg.norm(plane_normal)
        ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = ref - (ref @ n) * n  # base x laid onto the plane
        x = Rotation.from_rotvec(math.radians(self.yaw_deg) * n).apply(x / np.linalg.norm(x))
        z = -n  # OpenCV's board z points into the table
        rot = np.column_stack([x, np.cross(z, x), z])
        centre = np.asarray(self.center_m, float)
        centre = centre - ((centre - plane_point_m) @ n) * n  # onto the plane
        w, h = self.size_m
        return Pose(Rotation.from_matrix(rot), centre - rot @ np.array([w / 2, h / 2, 0.0]))

    def pose_on_plate(self, plate_in_base: Pose) -> Pose:
        """``T_base_board``: the board centred on the held plate's face (``T_base_plate``; the face looks along the
        plate's -z, so OpenCV's board z, into the print, is the plate's +z), turned by ``yaw_deg`` about it."""
        turn = Pose.from_xyz_rpy(np.zeros(3), np.array([0.0, 0.0, math.radians(self.yaw_deg)]))
        w, h = self.size_m
        return plate_in_base @ turn @ Pose.from_xyz_rpy(np.array([-w / 2, -h / 2, 0.0]), np.zeros(3))


def sub_rays(intrinsics: Intrinsics, s: int) -> FloatArray:
    """Unit rays (H*W*s*s, 3) through an s x s grid inside every pixel, pixel by pixel (row-major).

    The lens model is inverted only at the pixel centres and a one-pixel border; the
    sub-pixel rays interpolate its normalised coordinates bilinearly (the distortion is
    smooth over a pixel), which keeps the first capture of a board fast.
    """
    from scipy.interpolate import RegularGridInterpolator

    w, h = intrinsics.width, intrinsics.height
    u, v = np.arange(-1.0, w + 1.0), np.arange(-1.0, h + 1.0)
    grid = pixel_rays(intrinsics, np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)).reshape(len(v), len(u), 3)
    normalised = grid[..., :2] / grid[..., 2:]  # (x/z, y/z) at the centres and the border
    offs = (np.arange(s) + 0.5) / s - 0.5  # sub-pixel offsets in (-0.5, 0.5)
    du, dv = np.meshgrid(offs, offs)
    pu, pv = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    at = np.stack([pv.ravel()[:, None] + dv.ravel()[None], pu.ravel()[:, None] + du.ravel()[None]], axis=-1)
    xy = RegularGridInterpolator((v, u), normalised)(at.reshape(-1, 2))
    rays = np.column_stack([xy, np.ones(len(xy))])
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


class BoardTexture:
    """Renders a board's reflectivity into a camera's pixels (anti-aliased by sub-rays).

    Args:
        config: The board.
        board_in_base: ``T_base_board``.
        intrinsics: The camera whose pixels are rendered.
    """

    def __init__(self, config: CharucoConfig, board_in_base: Pose, intrinsics: Intrinsics) -> None:
        self.config = config
        self.board_in_base = board_in_base
        ppm = config.texture_px_per_square / config.square_m  # texture pixels per metre
        w, h = config.size_m
        self._ppm = ppm
        self._texture = np.asarray(config.board().generateImage((round(w * ppm), round(h * ppm))), dtype=np.float64)
        self._rays = sub_rays(intrinsics, config.supersample)  # (H*W*s*s, 3) sub-rays through the lens
        self._n_sub = config.supersample**2
        self._centre = self._rays.reshape(-1, self._n_sub, 3).mean(axis=1)  # about each pixel's centre ray
        self._pixel_rad = 1.0 / min(intrinsics.fx, intrinsics.fy)  # angular size of a pixel, rad

    def reflectivity(self, camera_in_base: Pose, on_plane: NDArray[np.bool_], plane_rho: float | FloatArray,
                     board_in_base: Pose | None = None) -> FloatArray:
        """Per-pixel reflectivity (H*W,): the board's print where sub-rays land on it, ``plane_rho`` elsewhere.

        Only pixels whose centre ray lands within a few footprints of the board trace their sub-rays.

        Args:
            camera_in_base: ``T_base_camera``.
            on_plane: (H*W,) pixels whose centre ray hits the measuring plane (not a box).
            plane_rho: The plane's reflectivity (scalar or per pixel).
            board_in_base: Where the board is for this frame (a board on the held plate moves); None: where built.
        """
        cam_in_board = (self.board_in_base if board_in_base is None else board_in_base).inv() @ camera_in_base
        rot, origin = cam_in_board.rotation.as_matrix(), np.asarray(cam_in_board.translation, float)
        w, h = self.config.size_m
        # where each centre ray meets the board plane z = 0, and its footprint there (m)
        centre = self._centre @ rot.T
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -origin[2] / centre[:, 2]
            reach = 3.0 * t * self._pixel_rad / np.maximum(np.abs(centre[:, 2]), 0.1)
        x, y = origin[0] + t * centre[:, 0], origin[1] + t * centre[:, 1]
        near = on_plane & (t > 0) & (x > -reach) & (x < w + reach) & (y > -reach) & (y < h + reach)
        idx = np.flatnonzero(near)
        base = np.array(np.broadcast_to(np.asarray(plane_rho, float), on_plane.shape))
        dirs = self._rays.reshape(-1, self._n_sub, 3)[idx].reshape(-1, 3) @ rot.T  # their sub-rays, board frame
        with np.errstate(divide="ignore", invalid="ignore"):
            ts = -origin[2] / dirs[:, 2]
        xs, ys = origin[0] + ts * dirs[:, 0], origin[1] + ts * dirs[:, 1]
        on_board = (ts > 0) & (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)
        # texture lookup (nearest texel; the sub-rays average it); 255 = paper, 0 = ink
        col = np.clip(np.nan_to_num(xs * self._ppm), 0, self._texture.shape[1] - 1).astype(int)
        row = np.clip(np.nan_to_num(ys * self._ppm), 0, self._texture.shape[0] - 1).astype(int)
        c = self.config
        rho_board = c.dark_reflectivity + (c.light_reflectivity - c.dark_reflectivity) * self._texture[row, col] / 255.0
        sub = np.where(on_board, rho_board, np.repeat(base[idx], self._n_sub))
        base[idx] = sub.reshape(-1, self._n_sub).mean(axis=1)  # each pixel averages its sub-rays
        return base


__all__ = ["BoardTexture", "CharucoConfig", "Dictionary", "sub_rays"]
