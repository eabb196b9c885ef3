"""``cellcal track`` over every camera of a ``[[cameras]]`` cell: each tracked as one is, one arm read by all.

Design (issue #40, ADR 0061): each camera has its own :class:`~cellcal.core.track.run.TrackRun` (its
tracker, its pairing, its files); a camera on the flange is tracked as a one-camera cell's is (mount and
plane), a fixed one (``on = "base"``) for its view of the plane (``TrackRun(fixed_pose=...)``).

Policy, stated in ``docs/commands/track.md``:

- The cameras are read in turn, one frame of each per round, in the configuration's order, on the
  calling thread (no threads): each capture waits at most its own camera's deadline
  (``default_timeout_s``), so a round lasts at most the sum of the deadlines.
- A camera that fails (its capture, or a check that ends its tracking, such as a camera on the flange
  whose view does not follow the arm) is that camera's failure: it is said once, the camera is not read
  again, its files are written with what it saw (``meta.failed``) and the other cameras go on; the run
  then exits 1. When every camera has failed the run ends.
- The arm is shared: an arm read that fails ends the run for every camera, as with one camera.

A fixed camera's one view cannot tell its own move from the plane's (:func:`attribute`): its change is
the camera's when the cameras on the arm saw no change of the plane around it, the plane's when one of
them did, and undecided without a camera on the arm that tracked the plane then.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

from cellcal.core.track.detector import KIND_EITHER, KIND_PLANE
from cellcal.core.track.run import TrackOutcome, TrackRun
from cellcal.devices.errors import CellcalError, OutputError

__all__ = ["ATTRIBUTION_WINDOW_S", "Attribution", "CameraFailure", "CameraTrack", "CellOutcome", "CellTrack",
           "attribute"]

#: A fixed camera's change and a change of the plane seen from the arm are one when they started this close, s.
ATTRIBUTION_WINDOW_S = 5.0
#: Causes of a fixed camera's change.
CAUSE_CAMERA = "camera moved"
CAUSE_PLANE = "plane moved"
CAUSE_UNDECIDED = "undecided"


@dataclass(frozen=True)
class CameraTrack:
    """One camera of the cell and its tracking session.

    Attributes:
        name: Its name in ``[[cameras]]``.
        place: ``"flange"`` or ``"base"``.
        run: Its session (not started).
    """

    name: str
    place: str
    run: TrackRun


@dataclass(frozen=True)
class CameraFailure:
    """A camera that stopped: its name, the time of its last frame (s since the run's first frame), why."""

    name: str
    t_s: float
    message: str


@dataclass(frozen=True)
class Attribution:
    """What a fixed camera's change was.

    Attributes:
        camera: The fixed camera.
        started_at_s: When its change started, s.
        cause: ``"camera moved"``, ``"plane moved"`` or ``"undecided"``.
        text: One line saying it, naming the cameras that decided it.
    """

    camera: str
    started_at_s: float
    cause: str
    text: str

    def to_dict(self) -> dict[str, object]:
        """JSON form."""
        return {"camera": self.camera, "started_at_s": self.started_at_s, "cause": self.cause, "text": self.text}


@dataclass
class CellOutcome:
    """The end of a run over several cameras: each camera's outcome, place (``flange``/``base``) and files
    (written in ``out_dir``), the failures and what each fixed camera's change was."""

    outcomes: dict[str, TrackOutcome]
    places: dict[str, str]
    files: dict[str, tuple[str, str]]
    failures: list[CameraFailure] = field(default_factory=list)
    attributions: list[Attribution] = field(default_factory=list)
    interrupted: bool = False


class CellTrack:
    """Track every camera of a cell, one frame of each in turn (the module's policy).

    Args:
        cameras: The cameras and their sessions, in the order they are read.
        on_failure: Called once when a camera fails (e.g. to print it).
    """

    def __init__(self, cameras: Sequence[CameraTrack], on_failure: Callable[[CameraFailure], None] | None = None
                 ) -> None:
        if not cameras:
            raise ValueError("CellTrack needs at least one camera")
        self.cameras = list(cameras)
        self.on_failure = on_failure
        self._last_t: dict[str, float] = {}

    def run(self, duration_s: float | None = None, max_frames: int | None = None) -> CellOutcome:
        """Track until ``duration_s`` seconds of frames (the latest camera's), ``max_frames`` rounds, Ctrl-C, or
        every camera failed; then write every camera's files.

        Raises:
            CellcalError: The arm failed, or a file could not be written (every camera's earlier files stay).
        """
        for camera in self.cameras:
            camera.run.start()
        failures: dict[str, CameraFailure] = {}
        interrupted = False
        try:
            index = 0
            active = list(self.cameras)
            while active and (max_frames is None or index < max_frames):
                latest = self._round(active, index, failures)
                index += 1
                if duration_s is not None and latest >= duration_s:
                    break
        except KeyboardInterrupt:
            interrupted = True
        except BaseException:
            for camera in self.cameras:
                camera.run.abandon()
            raise
        outcomes = {}
        for camera in self.cameras:
            failed = failures.get(camera.name)
            outcomes[camera.name] = camera.run.finish(interrupted, None if failed is None else failed.message)
        places = {c.name: c.place for c in self.cameras}
        files = {c.name: c.run.filenames for c in self.cameras}
        return CellOutcome(outcomes, places, files, list(failures.values()),
                           attribute(outcomes, places, {f.name: f.t_s for f in failures.values()}), interrupted)

    def _round(self, active: list[CameraTrack], index: int, failures: dict[str, CameraFailure]) -> float:
        """One frame of every active camera; a camera that fails leaves ``active``. The latest frame time, s."""
        latest = -math.inf
        for camera in list(active):
            try:
                t_s = camera.run.frame(index)
            except OutputError:
                raise
            except CellcalError as exc:
                if camera.run.arm_failed:
                    raise
                failure = CameraFailure(camera.name, self._last_t.get(camera.name, 0.0), str(exc).splitlines()[0])
                failures[camera.name] = failure
                active.remove(camera)
                if self.on_failure is not None:
                    self.on_failure(failure)
                continue
            self._last_t[camera.name] = t_s
            latest = max(latest, t_s)
            if index == 0:
                self._share_origin()
        return latest

    def _share_origin(self) -> None:
        """Every camera counts its frames' times from the first frame of the run (one time line for the events)."""
        origin = next((c.run.t0 for c in self.cameras if c.run.t0 is not None), None)
        if origin is None:
            return
        for camera in self.cameras:
            if camera.run.t0 is None:
                camera.run.t0 = origin


def attribute(outcomes: Mapping[str, TrackOutcome], places: Mapping[str, str],
              failed_at: Mapping[str, float] | None = None, window_s: float = ATTRIBUTION_WINDOW_S
              ) -> list[Attribution]:
    """Say, for every change a fixed camera saw, whether the camera or the plane moved.

    The cameras on the arm that used frames and had not failed by then are the witnesses: one of them
    with a change of the plane (``"plane"`` or ``"mount or plane"``) starting within ``window_s`` of the
    fixed camera's means the plane moved; none means the fixed camera moved; no witness: undecided.

    Args:
        outcomes: Every camera's outcome by name.
        places: ``"flange"`` or ``"base"`` by name.
        failed_at: When a camera failed (s), by name.
        window_s: How close the two changes' starts must be, s.
    """
    failed_at = failed_at or {}
    out = []
    for name, outcome in outcomes.items():
        if places.get(name) != "base":
            continue
        for event in outcome.state.events:
            start = event.started_at_s if event.started_at_s is not None else event.detected_at_s
            witnesses = [m for m, o in outcomes.items() if places.get(m) == "flange" and o.state.frames_used
                         and failed_at.get(m, math.inf) >= start + window_s]
            saw_plane = [m for m in witnesses if any(
                e.kind in (KIND_PLANE, KIND_EITHER)
                and abs((e.started_at_s if e.started_at_s is not None else e.detected_at_s) - start) <= window_s
                for e in outcomes[m].state.events)]
            moved = _view_words(event.size)
            if not witnesses:
                cause, text = CAUSE_UNDECIDED, (f"camera {name!r}: the plane moved in its view{moved} at "
                                                f"t={start:.1f} s; no camera on the arm tracked the plane then: the "
                                                "camera or the plane")
            elif saw_plane:
                cause, text = CAUSE_PLANE, (f"camera {name!r}: the plane moved at t={start:.1f} s{moved} (camera(s) "
                                            f"on the arm saw it too: {', '.join(saw_plane)})")
            else:
                cause, text = CAUSE_CAMERA, (f"camera {name!r} was moved at t={start:.1f} s: the plane moved in its "
                                             f"view{moved} while the camera(s) on the arm ({', '.join(witnesses)}) "
                                             "saw no change of the plane")
            out.append(Attribution(name, start, cause, text))
    return out


def _view_words(size: Mapping[str, float]) -> str:
    """`` by X deg and Y mm`` of a fixed camera's change size, or ``""`` before it is sized."""
    if "view_tilt_deg" not in size:
        return ""
    return f" by {size['view_tilt_deg']:.3f} deg and {size.get('view_shift_m', math.nan) * 1e3:.2f} mm"
