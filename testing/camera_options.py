"""What a vendor declares about a camera backend to the kit: :class:`CameraOptions`, :class:`ScenePlane`.

The camera rules (:mod:`.camera`) and the rules that run calibrate's own code on the camera
(:mod:`.readiness`) both read these options, so they live apart from either set of rules.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cellcal.core.geometry.planes import Plane
from cellcal.devices.errors import CellcalError

from .lifecycle import CommonOptions

__all__ = ["CameraOptions", "ScenePlane"]


@dataclass(frozen=True)
class ScenePlane:
    """The plane a camera sees in the kit's test scene, in the camera frame (OpenCV: x right, y down, z forward).

    Attributes:
        normal: The plane's normal, either orientation (it need not be a unit vector).
        axis_distance_m: Where the optical axis meets the plane, metres from the camera.
    """

    normal: tuple[float, float, float]
    axis_distance_m: float

    def __post_init__(self) -> None:
        n = np.asarray(self.normal, dtype=np.float64).reshape(-1)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or not np.linalg.norm(n) > 0:
            raise CellcalError(f"ScenePlane.normal must be a finite, non-zero 3-vector, got {self.normal!r}")
        d = self.axis_distance_m
        if isinstance(d, bool) or not isinstance(d, (int, float)) or not (math.isfinite(d) and d > 0):
            raise CellcalError(f"ScenePlane.axis_distance_m must be a positive number of metres, got {d!r}")
        if abs(n[2]) < 1e-6 * float(np.linalg.norm(n)):
            raise CellcalError("ScenePlane.normal is across the optical axis: the axis never meets the plane")

    def plane(self) -> Plane:
        """As a :class:`~cellcal.core.geometry.planes.Plane`, normal toward the camera, metres."""
        return Plane.from_point_normal((0.0, 0.0, self.axis_distance_m), self.normal).oriented_toward_origin()


@dataclass(frozen=True)
class CameraOptions(CommonOptions):
    """What the kit may assume about a camera backend under test.

    Attributes:
        distance_range_m: ``(min, max)`` radial distance, metres, the backend can report;
            every valid pixel must lie inside it.
        capture_timeout_s: Timeout passed to ``capture()`` where a frame is required, seconds.
        frames: Frames captured by the sequence check (>= 2).
        xyz_tolerance_m: Allowed ``| |xyz| - distance |`` on valid pixels, metres.
        reprojection_tolerance_px: Allowed distance, pixels, between a valid pixel and its
            xyz projected through the intrinsics (95th percentile); None skips that check.
        min_valid_fraction: Fraction of valid pixels a frame of the test scene must have.
        model_unknown_reason: Why the backend states no measurement model (``unknown``): a
            camera that cannot tell how it measures opts out of that part of
            ``camera.measurement-model`` by saying why here (users then state the model in
            ``[camera.model]``); None (default) requires a stated model.
        perimeters_px: The P1-P9 grid perimeters the image must hold (``camera.calibrate-image``),
            pixels; None (default): the default plan's, (20, 30, 40, 50). A camera whose cells
            will use smaller ones says so here (and they go into its cells' ``[plan]``).
        scene_plane: The plane the camera sees in the test scene (:class:`ScenePlane`, camera
            frame): ``camera.calibrate-frames`` runs calibrate's full-frame fit on the frames
            and requires every default gate to pass, the fitted plane to lie within the default
            ``[reference]`` search tolerances (15 deg, 100 mm) of this one among them.
        scene_reason: Why the test scene cannot be a plane filling the image (a mocked SDK that
            sends a constant depth): ``camera.calibrate-frames`` is then not run. One of
            ``scene_plane`` and ``scene_reason`` is required.

    The shared attributes (``connect_timeout_s``, ``short_timeout_s``, ``timing_slack_s``,
    ``check_resources``) are described in :class:`CommonOptions`.
    """

    distance_range_m: tuple[float, float] = (0.01, 50.0)
    capture_timeout_s: float = 5.0
    frames: int = 3
    xyz_tolerance_m: float = 1e-4
    reprojection_tolerance_px: float | None = 0.5
    min_valid_fraction: float = 0.01
    model_unknown_reason: str | None = None
    perimeters_px: tuple[int, ...] | None = None
    scene_plane: ScenePlane | None = None
    scene_reason: str | None = None

    def __post_init__(self) -> None:
        self._require_positive("capture_timeout_s", "xyz_tolerance_m")
        if self.model_unknown_reason is not None and not (isinstance(self.model_unknown_reason, str)
                                                          and self.model_unknown_reason.strip()):
            raise CellcalError("CameraOptions.model_unknown_reason must say why the camera states no model "
                               f"(a non-empty string), got {self.model_unknown_reason!r}")
        if self.scene_reason is not None and not (isinstance(self.scene_reason, str) and self.scene_reason.strip()):
            raise CellcalError("CameraOptions.scene_reason must say why the test scene cannot be a plane "
                               f"(a non-empty string), got {self.scene_reason!r}")
        if self.scene_plane is not None and not isinstance(self.scene_plane, ScenePlane):
            raise CellcalError(f"CameraOptions.scene_plane must be a ScenePlane, got {type(self.scene_plane).__name__}")
        if self.perimeters_px is not None and not (
                len(self.perimeters_px) > 0 and all(isinstance(p, (int, float)) and not isinstance(p, bool)
                                                    and math.isfinite(p) and p > 0 for p in self.perimeters_px)):
            raise CellcalError(f"CameraOptions.perimeters_px must be positive numbers of pixels, got "
                               f"{self.perimeters_px!r}")
        lo, hi = self.distance_range_m
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo < hi):
            raise CellcalError(f"CameraOptions.distance_range_m must be 0 <= min < max metres, got {(lo, hi)}")
        if self.frames < 2:
            raise CellcalError(f"CameraOptions.frames must be >= 2, got {self.frames}")
