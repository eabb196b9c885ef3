"""Kit rules that run a camera through what ``cellcal calibrate`` needs from it (ADR 0044).

``camera.calibrate-image``: the default plan's P1-P9 grid, with its sampling windows, lies
inside the image. ``camera.calibrate-frames``: cellcal's own full-frame fit, with the default
gates and the camera's measurement model, accepts the frames of the test scene: a plane
filling the image, found where the vendor declares it (the ``expected_plane`` gate), with
the noise the camera states (``residual_floor``, ``residual_rms_m``). Both call the code
``calibrate`` runs, so a refusal here reads as the run's would.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from cellcal.core.methods.fullframe import check_gates, fit_full_frame
from cellcal.core.methods.fullframe.expected import (
    DEFAULT_SEARCH_TOLERANCE_DEG,
    DEFAULT_SEARCH_TOLERANCE_M,
    ExpectedPlane,
)
from cellcal.core.methods.grid import DEFAULT_PERIMETERS_PX, DEFAULT_WINDOW_PX, perimeter_problem
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import CalibrationError, CalibrationQualityError

from ._runner import Check, Violation, connected, expect, make
from .camera_options import CameraOptions

__all__ = ["calibrate_checks"]

Factory = Callable[[], Camera3D]


#: What a vendor is told when the kit does not know the test scene's plane.
HOW_TO_DECLARE_THE_SCENE = (
    "point the camera at a flat surface filling the image and declare it, e.g. CameraOptions(scene_plane="
    "ScenePlane(normal=(0.0, 0.0, 1.0), axis_distance_m=1.2)) for a wall 1.2 m ahead (camera frame: x right, "
    "y down, z forward); a backend whose test scene cannot be one opts out with CameraOptions(scene_reason='why')")

#: Gate -> what a vendor can do about a refusal by it.
_GATE_HINTS = {
    "residual_floor": "the frames are less noisy than the camera's measurement model says: state the noise it "
                      "has (docs/extending.md, 'Stating how the camera measures')",
    "residual_rms_m": "the frames are noisier than the camera's measurement model says: state the noise it has "
                      "(docs/extending.md, 'Stating how the camera measures')",
    "expected_plane": "the plane in the frames is not the declared scene plane: check that xyz is in the OpenCV "
                      "camera frame with rows top to bottom and columns left to right (an image read out upside "
                      "down mirrors every plane), or the declared ScenePlane",
}
_SCENE_HINT = "the test scene must be one flat surface filling the image, as a cell's measuring plane does"


def _perimeters(o: CameraOptions) -> tuple[int, ...]:
    return DEFAULT_PERIMETERS_PX if o.perimeters_px is None else tuple(o.perimeters_px)


def _calibrate_image(factory: Factory, o: CameraOptions) -> None:
    camera = make(factory, Camera3D)
    try:
        configured = camera.configured_intrinsics()
        camera.connect(o.connect_timeout_s)
        intr = camera.intrinsics
    finally:
        camera.close()
    perimeters = _perimeters(o)
    why = perimeter_problem(intr, perimeters, DEFAULT_WINDOW_PX)
    plan = f"perimeters_px = [{', '.join(str(p) for p in perimeters)}], window_px = {DEFAULT_WINDOW_PX}"
    expect(why is None, f"`cellcal calibrate` with [plan] {plan} refuses this camera before the arm moves: {why}")
    if configured is not None:
        same = (configured.width, configured.height) == (intr.width, intr.height) and \
            max(abs(configured.cx - intr.cx), abs(configured.cy - intr.cy)) <= 0.5
        expect(same, f"configured_intrinsics() before connect() says a {configured.width}x{configured.height} image "
                     f"centred at ({configured.cx:g}, {configured.cy:g}) px, the connected camera a "
                     f"{intr.width}x{intr.height} image centred at ({intr.cx:g}, {intr.cy:g}) px; `calibrate "
                     "--check` would judge the plan on the wrong image")


def _calibrate_frames(factory: Factory, o: CameraOptions) -> None:
    with connected(factory, Camera3D, o.connect_timeout_s) as cam:
        if o.scene_plane is None:
            expect(o.scene_reason is not None, "the kit cannot run calibrate's full-frame fit on this camera's "
                                               f"frames without knowing its test scene: {HOW_TO_DECLARE_THE_SCENE}")
            return
        frames = [cam.capture(o.capture_timeout_s) for _ in range(o.frames)]
    expected = ExpectedPlane(o.scene_plane.plane(), math.radians(DEFAULT_SEARCH_TOLERANCE_DEG),
                             DEFAULT_SEARCH_TOLERANCE_M)
    for i, frame in enumerate(frames):
        try:
            check_gates(fit_full_frame(frame, expected=expected))
        except CalibrationQualityError as exc:
            hint = _GATE_HINTS.get(exc.gate, _SCENE_HINT)
            raise _refusal(i, f"{exc}; {hint}") from None
        except CalibrationError as exc:
            raise _refusal(i, str(exc)) from None


def _refusal(index: int, why: str) -> Violation:
    return Violation(f"`cellcal calibrate` with the default [full_frame] gates refuses frame #{index} of the test "
                     f"scene: {why}")


def calibrate_checks() -> tuple[Check[Camera3D, CameraOptions], ...]:
    """The two rules, in the order they run."""
    return (
        Check("camera.calibrate-image", "the image holds the default plan's P1-P9 grid with its sampling windows "
                                        "(what `cellcal calibrate` checks before the arm moves)", _calibrate_image),
        Check("camera.calibrate-frames", "`cellcal calibrate`'s full-frame fit accepts the frames of the test scene "
                                         "with the default gates: the declared plane, the noise the camera states",
              _calibrate_frames),
    )
