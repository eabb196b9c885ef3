"""What every simulated camera shares: the world, the noise stream, frame pacing, resume, faults.

:class:`SimCameraShell` is the device half of a simulated camera; a subclass renders
(:meth:`SimCameraShell.render`) and states how it measures. The ToF camera
(:class:`~cellcal.sims.camera.SimCamera`) and the stereo camera
(:class:`~cellcal.sims.stereo.SimStereoCamera`) are its two kinds. ADR 0014, ADR 0029.
"""

from __future__ import annotations

import threading
from abc import abstractmethod
from collections.abc import Callable
from typing import Any

from cellcal.devices.base import BackendContext, CameraPlacement
from cellcal.devices.camera import Camera3D
from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame

from .world import SimWorld, world_from_context

__all__ = ["SimCameraShell"]


class SimCameraShell(Camera3D):
    """A simulated camera rendering the shared :class:`SimWorld` from the arm's true camera pose.

    Randomness comes from one numpy Generator per camera (stream ``"camera"``), seeded from
    ``seed`` or the world's seed, so equal seeds give identical frame sequences. Frames are
    paced by the simulated clock: each capture advances it to the next frame period
    (``1 / frame_rate_hz``) and stamps the frame with the simulated time.

    A camera of ``[[cameras]]`` built with a placement (``context.placement``, ADR 0061) renders
    from its own true pose (:meth:`camera_pose_at`): fixed in the base frame, or its own mount on
    the true flange; it draws its noise from its own stream (``"camera:NAME"``), and when it connects
    the world's ``[[sim.cameras]]`` entries must name the cell's cameras
    (:meth:`~cellcal.sims.world.SimWorld.check_camera_truths`). Every capture sees the plate the arm
    holds (``[sim.plate]``) at the true flange pose of that frame.

    Fault injection (tests): :attr:`fault_hook`, if set, is called as ``hook("connect", n)``
    on the n-th connect and ``hook("capture", n)`` before the n-th frame is rendered, on the
    thread that captures.

    Args:
        context: Backend context (gives the shared world); None makes a private one.
        world: Use this world instead of the context's (emulators, tests).
        seed: Noise seed; None: the world's seed.
        frame_rate_hz: Frame rate, Hz (> 0).
    """

    backend_name = "sim"

    def __init__(self, context: BackendContext | None, world: SimWorld | None, seed: int | None,
                 frame_rate_hz: float) -> None:
        super().__init__()
        self.world = world if world is not None else world_from_context(context)
        #: Where this camera of ``[[cameras]]`` is configured to stand, or None (the camera a run drives).
        self.placement: CameraPlacement | None = None if context is None else context.placement
        if context is not None and context.camera_names:
            self.world.cell_camera_names = tuple(context.camera_names)
        self._source = None if context is None else context.source
        placed = self.placement
        # its true T_flange_camera (on the flange) or T_base_camera (fixed); None: the world's mount
        self._true_pose = None if placed is None else self.world.place_camera(placed)
        if placed is None:
            self.world.driven_cameras += 1
        self._rng = self.world.rng("camera" if placed is None else f"camera:{placed.name}", seed)
        self._lock = threading.Lock()
        self._sequence = 0
        self._last_frame_elapsed: float | None = None
        self._frame_period_s = 1.0 / frame_rate_hz
        #: Fault-injection hook ``hook(event, n)``, see the class docstring.
        self.fault_hook: Callable[[str, int], None] | None = None
        self.connects = 0

    @abstractmethod
    def render(self, camera_pose: Pose, *, timestamp: float | None = None, sequence: int = 0,
               flange_pose: Pose | None = None) -> Frame:
        """Render one frame from a camera pose (``T_base_camera``), without moving the arm.

        Draws from this camera's noise stream; usable before :meth:`connect`.

        Args:
            camera_pose: Camera pose in the world/base frame.
            timestamp: Frame time, seconds since the epoch; None uses the simulated clock.
            sequence: Sequence number to stamp.
            flange_pose: True ``T_base_flange`` the held plate is drawn at (``[sim.plate]``); None: the
                flange's true pose now (read only when there is a plate).
        """

    def _on_connect(self) -> None:
        """Work done once per connect, after the fault hook (override; default nothing)."""

    def camera_pose_at(self, flange: Pose) -> Pose:
        """This camera's true ``T_base_camera`` when the flange truly stands at ``flange``.

        The camera a run drives: ``flange @ world.mount`` (:meth:`SimWorld.on_flange`); a placed
        camera on the flange: ``flange @`` its own true mount; a fixed one: its true pose, whatever
        the flange does (its ``[[sim.events]]`` pose once one naming it has come).
        """
        placed, own = self.placement, self._true_pose
        if placed is None or own is None:
            return self.world.on_flange(flange, self.world.mount)
        own = self.world.moved.get(placed.name, own)  # a [[sim.events]] entry naming it moved it
        return own if placed.on == "base" else self.world.on_flange(flange, own)

    def camera_pose(self) -> Pose:
        """This camera's true ``T_base_camera`` now (the world's events applied, the clock brought up)."""
        self.world.apply_events()
        return self.camera_pose_at(self.world.true_flange_pose())

    # ------------------------------------------------------------------ backend hooks
    def _connect(self, timeout: float) -> None:
        self.connects += 1
        if self.fault_hook is not None:
            self.fault_hook("connect", self.connects)
        if self.placement is not None or self.world.cell_camera_names:  # every camera is built by now
            self.world.check_camera_truths(self._source)
        self._on_connect()

    def _close(self) -> None:
        return None

    def _capture(self, timeout: float) -> Frame:
        if self.fault_hook is not None:
            self.fault_hook("capture", self._sequence + 1)
        with self._lock:
            clock = self.world.clock
            if self._last_frame_elapsed is not None:
                # the next frame period on the simulated clock
                clock.advance_to(self._last_frame_elapsed + self._frame_period_s)
            self._last_frame_elapsed = clock.elapsed_s
            self._sequence += 1
            world = self.world
            world.apply_events()
            flange = world.true_flange_pose()  # also brings the simulated clock up to the motion under way
            return self.render(self.camera_pose_at(flange), sequence=self._sequence, flange_pose=flange)

    def resume_state(self) -> dict[str, Any]:
        """JSON-able state of the noise stream and frame pacing (restored when a run resumes)."""
        with self._lock:
            return {"rng": self._rng.bit_generator.state, "sequence": self._sequence,
                    "last_frame_elapsed_s": self._last_frame_elapsed, "clock_elapsed_s": self.world.clock.elapsed_s}

    def restore_resume_state(self, state: dict[str, Any]) -> None:
        """Continue from :meth:`resume_state`'s output: the next frame draws the noise it would have."""
        with self._lock:
            self._rng.bit_generator.state = state["rng"]
            self._sequence = int(state["sequence"])
            last = state["last_frame_elapsed_s"]
            self._last_frame_elapsed = None if last is None else float(last)
            self.world.clock.advance_to(float(state["clock_elapsed_s"]))

    @property
    def sequence(self) -> int:
        """Sequence number of the last captured frame (0 before the first)."""
        return self._sequence
