"""Views of the plane for depth-calibration tests and benchmarks: a plan, sim frames with a known systematic error.

The sims render an ideal camera (``[sim.systematic]`` off where the sim has it); the known
:class:`SystematicError` is then injected into each frame's native values (disparity ``f·B/Z`` or
range) through :meth:`SystematicError.distort`, the points moved along their rays to match.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from cellcal.core.depthcal import DepthcalView
from cellcal.devices.pose import Pose
from cellcal.devices.systematic import SystematicError, normalised_pixels
from cellcal.devices.types import Frame
from cellcal.sims.camera import SimCamera, SimCameraConfig
from cellcal.sims.scene import Scene
from cellcal.sims.stereo import SimStereoCamera, SimStereoConfig
from cellcal.sims.tof import ArtefactsConfig
from cellcal.sims.world import SimWorld

DOWN = Rotation.from_euler("x", 180.0, degrees=True)  # camera z along world -z
#: The mount the tests use: the camera 6 cm below the flange, slightly turned.
MOUNT = Pose.from_xyz_rpy([0.01, -0.02, 0.06], np.radians([1.0, -2.0, 90.0]))


def plan(heights: Sequence[float] = (0.45, 0.55, 0.65), tilts_deg: Sequence[float] = (0.0, 10.0, 20.0),
         n_poses: int = 12, seed: int = 0) -> list[Pose]:
    """Camera poses ``T_base_camera`` over the plane z = 0: every height, inclinations, azimuths and shifts.

    ``n_poses`` poses cycle through the heights and tilts (from straight down, i.e. inclinations 90 down
    to 70 deg), with the tilt's azimuth and a sideways shift varying so the plane crosses the pixels.
    """
    rng = np.random.default_rng(seed)
    poses = []
    for k in range(n_poses):
        h = heights[k % len(heights)]
        tilt = tilts_deg[(k // len(heights) + k) % len(tilts_deg)]
        azim = 360.0 * k / n_poses + 37.0 * (k % 3)
        rot = DOWN * Rotation.from_euler("z", azim, degrees=True) * Rotation.from_euler("x", tilt, degrees=True)
        shift = rng.uniform(-0.05, 0.05, 2)
        poses.append(Pose(rot, np.array([shift[0], shift[1], h])))
    return poses


def _ideal_world(pose: Pose, seed: int, **extra: Any) -> SimWorld:
    kwargs: dict[str, Any] = dict(extra)
    try:  # the sims' own systematic error, when they have it, is switched off: the test injects its own
        from cellcal.sims.systematic import SystematicConfig
        kwargs["systematic"] = SystematicConfig(enabled=False)
    except ImportError:  # pragma: no cover - sims without [sim.systematic]
        pass
    return SimWorld(Scene(), MOUNT, flange_pose=pose @ MOUNT.inv(), seed=seed, **kwargs)


def inject(frame: Frame, err: SystematicError, fb_px_m: float | None = None) -> Frame:
    """The frame as a camera with systematic error ``err`` would have measured it (native values distorted)."""
    intr = frame.intrinsics
    u, v = normalised_pixels(intr.width, intr.height, intr.cx, intr.cy)
    valid = frame.valid.copy()
    xyz = frame.xyz.astype(np.float64)
    dist = frame.distance.astype(np.float64)
    if err.kind == "stereo":
        assert fb_px_m is not None
        z = xyz[..., 2]
        d = fb_px_m / np.where(valid, z, 1.0)
        ratio = d / err.distort(d, u, v)                       # Z' / Z = d / d'
    else:
        r = np.where(valid, dist, 1.0)
        ratio = err.distort(r, u, v) / r
    ratio = np.where(valid, ratio, np.nan)
    valid &= np.isfinite(ratio) & (ratio > 0)
    return dataclasses.replace(frame, xyz=(xyz * ratio[..., None]).astype(np.float32),
                               distance=(dist * ratio).astype(np.float32), valid=valid)


def stereo_views(err: SystematicError, poses: Sequence[Pose], seed: int = 0, **config: Any
                 ) -> tuple[list[DepthcalView], SimStereoCamera]:
    """Stereo-sim views of the plane at ``poses`` (camera poses) with ``err`` injected."""
    world = _ideal_world(poses[0], seed)
    cam = SimStereoCamera(SimStereoConfig(**config), world=world)
    views = []
    for k, pose in enumerate(poses):
        frame = inject(cam.render(pose), err, cam.config.fb_px_m)
        views.append(DepthcalView(frame, pose @ MOUNT.inv(), f"pose {k}"))
    return views, cam


def tof_views(err: SystematicError, poses: Sequence[Pose], seed: int = 0, **config: Any
              ) -> tuple[list[DepthcalView], SimCamera]:
    """ToF-sim views (artefacts off: the data-sheet noise law) at ``poses`` with ``err`` injected."""
    world = _ideal_world(poses[0], seed, artefacts=ArtefactsConfig.off())
    cam = SimCamera(SimCameraConfig(**config), world=world)
    views = []
    for k, pose in enumerate(poses):
        views.append(DepthcalView(inject(cam.render(pose), err), pose @ MOUNT.inv(), f"pose {k}"))
    return views, cam


def bow_error(kind: str, bow: float, width: int, height: int, **terms: float) -> SystematicError:
    """A systematic error with a radial bow ``bow`` at the image corner (order 2: ``u²`` and ``v²`` only)."""
    a2 = (width / height) ** 2
    coeffs = (0.0, 0.0, bow * a2 / (a2 + 1.0), 0.0, bow / (a2 + 1.0))
    return SystematicError(kind, field_order=2, field_coeffs=coeffs, **terms)  # type: ignore[arg-type]
