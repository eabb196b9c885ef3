"""The target-based cross-check: a ChArUco board in the amplitude/IR image, OpenCV's hand-eye solvers.

Per view: the amplitude image scaled to 8 bits (1st-99th percentile) and enlarged
(a ToF camera's board squares are only ~15 px), ``cv2.aruco.CharucoDetector`` finds
the chessboard corners, ``cv2.solvePnP`` (with the camera's own intrinsics and
distortion) the board pose ``T_camera_board``. With the flange poses,
``cv2.calibrateHandEye`` solves AX = XB by each method it offers. Per pose the residual
is how far that pose's board, mapped to the base frame through the estimate, lies from
the mean board; leave-one-out (jackknife) gives each method's covariance (ADR 0018).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.errors import CalibrationError, CalibrationQualityError
from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame, Intrinsics

FloatArray = NDArray[np.float64]
#: OpenCV's hand-eye methods (AX = XB), by name.
METHODS = ("TSAI", "PARK", "HORAUD", "ANDREFF", "DANIILIDIS")
#: Enlargement of the amplitude image before detection (sub-pixel corners are mapped back).
UPSCALE = 3
#: Fewest chessboard corners a view needs for its board pose.
MIN_CORNERS = 6


@dataclass(frozen=True)
class BoardSpec:
    """The printed board: squares (columns, rows), square side (m), marker side / square side, dictionary."""

    squares: tuple[int, int] = (7, 5)
    square_m: float = 0.04
    marker_ratio: float = 0.75
    dictionary: str = "4X4_50"

    def board(self) -> Any:
        """The OpenCV board (``cv2.aruco.CharucoBoard``).

        Raises:
            CalibrationError: If this OpenCV has no such dictionary.
        """
        import cv2

        name = f"DICT_{self.dictionary}"
        if not hasattr(cv2.aruco, name):
            raise CalibrationError(f"OpenCV has no ArUco dictionary {name}")
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
        return cv2.aruco.CharucoBoard(self.squares, self.square_m, self.square_m * self.marker_ratio, dictionary)


@dataclass(frozen=True)
class BoardView:
    """The board seen in one frame.

    Attributes:
        board_in_camera: ``T_camera_board`` from solvePnP.
        corners: Chessboard corners found.
        reprojection_px: RMS reprojection error of the corners, pixels.
    """

    board_in_camera: Pose
    corners: int
    reprojection_px: float


def amplitude_image(frame: Frame) -> NDArray[np.uint8]:
    """The frame's amplitude scaled to 8 bits between its 1st and 99th percentiles."""
    a = np.nan_to_num(frame.amplitude.astype(np.float64), nan=0.0)
    lo, hi = np.percentile(a, [1.0, 99.0])
    image: NDArray[np.uint8] = np.clip((a - lo) / max(hi - lo, 1e-12) * 255.0, 0, 255).astype(np.uint8)
    return image


def detect_board(frame: Frame, spec: BoardSpec) -> BoardView | None:
    """The board's pose in one frame (None when fewer than :data:`MIN_CORNERS` corners are found)."""
    import cv2

    board = spec.board()
    big = cv2.resize(amplitude_image(frame), None, fx=UPSCALE, fy=UPSCALE, interpolation=cv2.INTER_CUBIC)
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(big)
    if ids is None or len(ids) < MIN_CORNERS:
        return None
    img = (corners.reshape(-1, 2) + 0.5) / UPSCALE - 0.5  # back to the frame's pixels (centres at integers)
    obj = np.asarray(board.getChessboardCorners(), dtype=np.float64)[ids.ravel()]
    return board_pose(obj, img, frame.intrinsics)


def board_pose(obj: FloatArray, img: FloatArray, intrinsics: Intrinsics) -> BoardView:
    """``T_camera_board`` from board points (m) and their pixels, by ``cv2.solvePnP`` (iterative)."""
    import cv2
    from scipy.spatial.transform import Rotation

    k, dist = intrinsics.camera_matrix, intrinsics.distortion
    ok, rvec, tvec = cv2.solvePnP(obj, img, k, dist, flags=cv2.SOLVEPNP_IPPE)  # planar start
    ok, rvec, tvec = cv2.solvePnP(obj, img, k, dist, rvec, tvec, useExtrinsicGuess=True,
                                  flags=cv2.SOLVEPNP_ITERATIVE)  # refine on the reprojection error
    if not ok:
        raise CalibrationError("solvePnP found no board pose")
    proj, _ = cv2.projectPoints(obj, rvec, tvec, k, dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
    return BoardView(Pose(Rotation.from_rotvec(rvec.ravel()), tvec.ravel()), len(obj), rms)


def hand_eye(flanges: Sequence[Pose], boards: Sequence[Pose], method: str) -> Pose:
    """``T_flange_camera`` by ``cv2.calibrateHandEye`` with one method (AX = XB, eye in hand).

    Args:
        flanges: ``T_base_flange`` per view (OpenCV's gripper-to-base).
        boards: ``T_camera_board`` per view (OpenCV's target-to-camera).
        method: One of :data:`METHODS`.

    Raises:
        CalibrationError: If this OpenCV lacks ``calibrateHandEye`` (OpenCV 5.0's wheel) or the method.
    """
    import cv2
    from scipy.spatial.transform import Rotation

    if not hasattr(cv2, "calibrateHandEye"):
        raise CalibrationError(f"OpenCV {cv2.__version__} has no calibrateHandEye (4.x has it; 5.0's wheel not)")
    check_motion(flanges)
    try:
        r, t = cv2.calibrateHandEye([f.rotation.as_matrix() for f in flanges], [f.translation for f in flanges],
                                    [b.rotation.as_matrix() for b in boards], [b.translation for b in boards],
                                    method=getattr(cv2, f"CALIB_HAND_EYE_{method}"))
    except cv2.error as exc:
        why = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise CalibrationError(f"calibrateHandEye ({method}) failed: {why}") from None
    if not np.all(np.isfinite(r)) or abs(np.linalg.det(r) - 1.0) > 1e-6:
        raise CalibrationError(f"calibrateHandEye ({method}) returned no rotation")
    return Pose(Rotation.from_matrix(r), np.asarray(t, dtype=np.float64).ravel())


#: Smallest rotation between two views that counts as motion, and smallest angle between two rotation axes, rad.
MIN_TURN_RAD = np.radians(2.0)
MIN_AXIS_ANGLE_RAD = np.radians(5.0)


def check_motion(flanges: Sequence[Pose]) -> None:
    """Refuse flange poses whose relative rotations do not turn about two different axes (AX = XB is then blind).

    Raises:
        CalibrationQualityError: Gate ``motion``, naming the largest rotation and the spread of the axes.
    """
    turns = [(flanges[0].rotation.inv() * f.rotation).as_rotvec() for f in flanges[1:]]  # flange frame of view 1
    axes = [t / np.linalg.norm(t) for t in turns if np.linalg.norm(t) > MIN_TURN_RAD]
    spread = max((float(np.arccos(min(1.0, abs(a @ b)))) for a in axes for b in axes), default=0.0)
    if len(axes) < 2 or spread < MIN_AXIS_ANGLE_RAD:
        largest = max((float(np.linalg.norm(t)) for t in turns), default=0.0)
        raise CalibrationQualityError("motion", spread, MIN_AXIS_ANGLE_RAD,
                                      f"the views turn the flange by at most {np.degrees(largest):.2f} deg about "
                                      f"axes within {np.degrees(spread):.2f} deg of each other; calibrateHandEye "
                                      "needs turns of > 2 deg about two axes > 5 deg apart", unit="rad")


def board_residuals(mount: Pose, flanges: Sequence[Pose], boards: Sequence[Pose]) -> list[tuple[float, float]]:
    """Per view: (deg, m) from its base-frame board ``A_i X C_i`` to the mean board of all views."""
    from scipy.spatial.transform import Rotation

    in_base = [f @ mount @ b for f, b in zip(flanges, boards, strict=True)]
    mean_rot = Rotation.concatenate([p.rotation for p in in_base]).mean()
    mean_t = np.mean([p.translation for p in in_base], axis=0)
    return [(float(np.degrees(np.linalg.norm((mean_rot.inv() * p.rotation).as_rotvec()))),
             float(np.linalg.norm(p.translation - mean_t))) for p in in_base]


def jackknife_covariance(flanges: Sequence[Pose], boards: Sequence[Pose], method: str, mount: Pose) -> FloatArray:
    """6x6 covariance of (rotation about the flange axes, rad; translation, m) by leave-one-out."""
    n = len(flanges)
    steps = []
    for k in range(n):
        keep = [i for i in range(n) if i != k]
        x = hand_eye([flanges[i] for i in keep], [boards[i] for i in keep], method)
        rot = (x.rotation * mount.rotation.inv()).as_rotvec()  # turn about the flange axes
        steps.append(np.concatenate([rot, x.translation - mount.translation]))
    d = np.asarray(steps) - np.mean(steps, axis=0)
    cov: FloatArray = (n - 1) / n * d.T @ d  # the jackknife's variance estimate
    return cov


__all__ = ["METHODS", "BoardSpec", "BoardView", "amplitude_image", "board_pose", "board_residuals", "check_motion",
           "detect_board", "hand_eye", "jackknife_covariance"]
