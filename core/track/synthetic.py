"""Synthetic frames of normal work: the hand-eye scenario's views visited in turn, dwelling at each.

Each frame is an independent noisy observation (:func:`cellcal.core.handeye.synthetic.observations`)
of the view the arm dwells at; a change replaces the scenario's true mount or plane while
the arm keeps its program (the same flange poses). For the tests and ``benchmarks/track_estimator.py``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator, Sequence

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import Plane
from cellcal.core.handeye.model import PlaneObservation
from cellcal.core.handeye.synthetic import Scenario, observations
from cellcal.devices.pose import Pose

FloatArray = NDArray[np.float64]
#: Frames per second of the simulated camera.
FPS = 30.0


def frame(scenario: Scenario, view: int, rng: np.random.Generator) -> PlaneObservation:
    """One noisy observation of ``scenario``'s view ``view``."""
    single = dataclasses.replace(scenario, flanges=(scenario.flanges[view],))
    return observations(single, rng)[0]


def work(scenario: Scenario, rng: np.random.Generator, n_frames: int, *, dwell: int = 15, start_frame: int = 0,
         views: Sequence[int] | None = None) -> Iterator[tuple[float, PlaneObservation]]:
    """``(t_s, observation)`` of ``n_frames`` frames at :data:`FPS`, ``dwell`` frames per view, views in turn.

    Args:
        scenario: The truth and the views.
        rng: Noise source.
        n_frames: Frames to give.
        dwell: Frames at each view before the arm moves to the next.
        start_frame: Frame number of the first frame (time and place in the work plan continue from it).
        views: Indices of the views visited (default: all, in order).
    """
    order = list(range(len(scenario.flanges))) if views is None else list(views)
    for k in range(start_frame, start_frame + n_frames):
        yield k / FPS, frame(scenario, order[(k // dwell) % len(order)], rng)


def knocked_mount(mount: Pose, turn_deg: float, axis: Sequence[float] = (1.0, 0.0, 0.0)) -> Pose:
    """``mount`` turned by ``turn_deg`` about a flange axis (a knock on the camera)."""
    from scipy.spatial.transform import Rotation

    a = np.asarray(axis, dtype=np.float64)
    turn = Rotation.from_rotvec(math.radians(turn_deg) * a / np.linalg.norm(a))
    return Pose(turn * mount.rotation, mount.translation)


def shifted_plane(plane: Plane, shift_m: float) -> Plane:
    """``plane`` moved by ``shift_m`` along its normal (a table raised or lowered)."""
    return Plane(plane.normal, plane.offset_m - shift_m)


__all__ = ["FPS", "frame", "knocked_mount", "shifted_plane", "work"]
