"""``cellcal track``: keep the camera mount and the plane calibrated from the frames of the cell's own work.

Exit status: 0 the run ended with no open change; 1 a change was detected and the frames
after it have not yet shown everything again (or a device failed); 2 bad input; 130 Ctrl-C
(the files are written first).
"""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cellcal.core.cli.argtypes import integer, path_arg, real
from cellcal.core.cli.exits import EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_OK
from cellcal.core.cli.options import add_viz_port_option, check_viz_options

if TYPE_CHECKING:  # the tracker (numpy, scipy, the fit) is imported by run(), not by `cellcal --help`
    from cellcal.core.calibration.config import CellConfig
    from cellcal.core.track.cell import CameraFailure, CellOutcome
    from cellcal.core.track.run import TrackOutcome, TrackProgress
    from cellcal.devices.pose import Pose

#: The packaged configuration tracked without --config, and how long, in seconds of frames.
DEFAULT_CONFIG = "sim_track.toml"
DEFAULT_SIM_DURATION_S = 90.0
EPILOG = ("exit status: 0 no change left open; 1 a change was detected and is not resolved yet (or a device "
          "failed); 2 bad configuration or usage; 130 stopped with Ctrl-C (after the files are written).")


def register(sub: Any) -> None:
    """Add the ``track`` subcommand."""
    p = sub.add_parser("track", help="keep the mount and the plane calibrated from the cell's normal work",
                       description="Read the arm (never move it: the cell's own program does) and the camera, "
                       "pair each frame with the arm pose at its time, fit the plane and keep a running estimate "
                       "of the camera mount and the base-frame plane with 95 % intervals for what the work has "
                       "shown; detect a knocked camera or a moved table and say which. Writes DIR/track.json "
                       "and DIR/track.jsonl. A cell with [[cameras]]: every camera is tracked (a fixed one for "
                       "its view of the plane), the first on the flange into DIR/track.json, each other into "
                       "DIR/track-NAME.json. With no --config, tracks the built-in simulated cell "
                       f"({DEFAULT_CONFIG}: its arm works on its own, its camera is knocked halfway) for "
                       f"{DEFAULT_SIM_DURATION_S:g} s.", epilog=EPILOG)
    p.add_argument("--config", metavar="PATH", type=path_arg,
                   help=f"cell configuration (TOML); default: the packaged {DEFAULT_CONFIG}")
    p.add_argument("--camera", metavar="NAME",
                   help="with [[cameras]]: track this camera only, on the flange or fixed (default: every camera)")
    p.add_argument("--duration", metavar="S", type=real(gt=0),
                   help="stop after S seconds of frames (default: until Ctrl-C; the built-in cell: "
                   f"{DEFAULT_SIM_DURATION_S:g})")
    p.add_argument("--frames", metavar="N", type=integer(ge=1), help="stop after N frames")
    p.add_argument("--decimate", metavar="K", type=_decimation, default=None,
                   help="fit every K-th pixel in each direction (K^2 fewer points) to keep up with a large image at "
                   "a high frame rate; default auto: at most 115 000 pixels for a stereo camera's fit, 300 000 for "
                   "a ToF camera's (640x400 stereo: K=2; 1280x800: K=3); its cost is stated in "
                   "benchmarks/track_cell.py")
    p.add_argument("--out", metavar="DIR", default="cellcal-out", type=path_arg,
                   help="output directory: track.json, track.jsonl (default: %(default)s)")
    p.add_argument("--apply", action="store_true",
                   help="when the run ends with every mount parameter seen, no change open and intervals given, "
                   "write DIR/calibration.json (versioned; the file it replaces is kept in DIR/history); "
                   "[mount] from_handeye reads it")
    p.add_argument("--record", metavar="FILE.mcap", type=path_arg,
                   help="also record the session (config, frames, arm reads, result) to one MCAP file")
    p.add_argument("--replay", metavar="FILE.mcap", type=path_arg,
                   help="track a session recorded with --record, from the file alone")
    p.add_argument("--quiet", action="store_true", help="print only change events and the summary")
    add_viz_port_option(p)
    p.set_defaults(func=run)


def _decimation(text: str) -> int | None:
    """``--decimate``: ``auto`` (None) or an integer 1-8."""
    if text == "auto":
        return None
    try:
        value: int = integer(ge=1, le=8)(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected 'auto' or an integer from 1 to 8, got {text!r}") from None
    return value


# ---------------------------------------------------------------------- run
def run(args: argparse.Namespace) -> int:
    """Run ``cellcal track``; returns the exit status."""
    from cellcal.core.calibration.calibrator import build_devices
    from cellcal.core.calibration.config import load_config
    from cellcal.devices.errors import ConfigError

    check_viz_options(args)
    if args.replay and args.config:
        raise ConfigError("--replay takes the configuration recorded in the file; drop --config")
    if args.replay and args.record:
        raise ConfigError("--record records a live run; a --replay is one already")
    if args.replay and args.camera:
        raise ConfigError("--replay tracks the camera recorded in the file; drop --camera")
    duration = args.duration
    if args.replay:
        from cellcal.core.calibration.replay import replay_session

        config, camera, arm = replay_session(args.replay, strict=True)
    else:
        from importlib import resources  # here: tempfile and random with it, not at `cellcal --help`

        path = args.config or str(resources.files("cellcal.configs").joinpath(DEFAULT_CONFIG))
        if args.config is None and duration is None and args.frames is None:
            duration = DEFAULT_SIM_DURATION_S
        config = load_config(path, args.camera, allow_fixed=args.camera is not None)
        if args.camera is None and len(config.cameras) > 1:
            if args.record:
                raise ConfigError("--record records one camera: with [[cameras]], add --camera NAME")
            return _track_cell(args, path, config, duration)
        camera, arm = build_devices(config)
    from cellcal.core.track.run import FrameClock, device_clock

    if args.replay:  # a replay's clock is its frames' own stamps
        camera = FrameClock(camera)
        now = camera.now
    else:  # the backend camera's clock, taken before any recording wrapper hides it
        now = device_clock(camera)
    options = _one_of_several(config)
    with contextlib.ExitStack() as stack:
        if args.record:
            from cellcal.core.calibration.replay import recorded_devices
            from cellcal.core.cli.record import open_recorder

            recorder = open_recorder(stack, args.record, config, args.config)
            camera, arm = recorded_devices(recorder, camera, arm)
        outcome = _track(args, config, camera, arm, duration, now, options)
        if args.record:
            recorder.log_result(outcome.document)
    return _report(args, outcome, options)


def _track(args: argparse.Namespace, config: Any, camera: Any, arm: Any, duration: float | None,
           now: Any, options: dict[str, Any]) -> TrackOutcome:
    """Connect, track until the end of the run, close; the outcome (files written)."""
    from cellcal.core.liveview import live_view_session
    from cellcal.core.track.run import ReadOnlyArm, TrackRun

    reader = ReadOnlyArm(arm)
    with live_view_session(args.viz_port, track=True, wait_s=args.viz_wait) as view:
        fixed = options.get("fixed_pose")
        printer = _Printer(args.quiet, view, fixed_pose=fixed)
        if view is not None and fixed is not None:
            view.place_camera(printer.frame_id, fixed)
        with camera, reader:
            if not args.quiet:
                print(f"tracking {config.camera_section.get('backend')} camera, {config.arm_section.get('backend')} "
                      f"arm ({config.source}); the arm is read, never moved; Ctrl-C to stop", flush=True)
            session = TrackRun(config, camera, reader, out_dir=args.out, now=now, on_progress=printer,
                               decimation=args.decimate, **options)
            printer.tracker = session.tracker
            outcome = session.run(duration, args.frames)
        if view is not None and args.viz_linger and not outcome.interrupted:
            from cellcal.core.liveview import linger

            linger(view, args.viz_linger)
    return outcome


def _report(args: argparse.Namespace, outcome: TrackOutcome, options: dict[str, Any]) -> int:
    """Print the summary and where the files are, apply if asked; the exit status."""
    from cellcal.core.track.result import FIXED_TRACK_SCHEMA, TRACK_FILENAME, track_filenames
    from cellcal.core.track.words import fixed_summary_lines, summary_lines

    fixed = outcome.document["schema"] == FIXED_TRACK_SCHEMA
    for line in fixed_summary_lines(outcome) if fixed else summary_lines(outcome):
        print(line)
    out = Path(args.out)
    files = options.get("filenames") or track_filenames(None)
    print(f"written: {out / files[0]}, {out / files[1]}")
    _apply(args, outcome, files[0] == TRACK_FILENAME and not fixed)
    if args.record:
        print(f"session recorded to {args.record}")
    if outcome.interrupted:
        return EXIT_INTERRUPTED
    return EXIT_FAILURE if outcome.document["change_unresolved"] else EXIT_OK


# ---------------------------------------------------------------------- several cameras
def _track_cell(args: argparse.Namespace, path: str, config: CellConfig, duration: float | None) -> int:
    """Track every camera of ``[[cameras]]`` (:mod:`cellcal.core.track.cell`); the exit status."""
    from cellcal.core.calibration.build import build_cell
    from cellcal.core.liveview import linger, live_view_session
    from cellcal.core.track.cell import CellTrack
    from cellcal.core.track.run import ReadOnlyArm

    cameras, arm = build_cell(config)
    reader = ReadOnlyArm(arm)
    unconnected: list[str] = []
    with live_view_session(args.viz_port, track=True, wait_s=args.viz_wait, cameras=list(cameras)) as view, \
            contextlib.ExitStack() as stack:
        stack.enter_context(reader)
        if not args.quiet:
            where = ", ".join(f"{c.name} ({c.on})" for c in config.cameras)
            print(f"tracking {len(cameras)} cameras: {where}; {config.arm_section.get('backend')} arm "
                  f"({config.source}); the arm is read, never moved; Ctrl-C to stop", flush=True)
        tracks = _camera_tracks(args, path, config, cameras, reader, view, stack, unconnected)
        outcome = CellTrack(tracks, on_failure=_say_failure).run(duration, args.frames)
        if view is not None and args.viz_linger and not outcome.interrupted:
            linger(view, args.viz_linger)
    return _report_cell(args, outcome, unconnected)


def _camera_tracks(args: argparse.Namespace, path: str, config: CellConfig, cameras: dict[str, Any], reader: Any,
                   view: Any, stack: contextlib.ExitStack, unconnected: list[str]) -> list[Any]:
    """Connect each camera and make its session; a camera that cannot connect is said and left out."""
    from cellcal.core.calibration.config import load_config
    from cellcal.core.track.cell import CameraTrack
    from cellcal.core.track.result import track_filenames
    from cellcal.core.track.run import TrackRun, device_clock
    from cellcal.devices.errors import DeviceError

    tracks = []
    for entry in config.cameras:
        camera = cameras[entry.name]
        try:
            stack.enter_context(camera)
        except DeviceError as exc:
            print(f"[{entry.name}] cannot connect: {str(exc).splitlines()[0]}; the others are tracked", flush=True)
            unconnected.append(entry.name)
            continue
        own = config if entry.name == config.camera_name else load_config(path, entry.name, allow_fixed=True)
        fixed = entry.pose_base if entry.on == "base" else None
        printer = _Printer(args.quiet, view, label=entry.name, fixed_pose=fixed)
        if view is not None and fixed is not None:
            view.place_camera(printer.frame_id, fixed)
        session = TrackRun(own, camera, reader, out_dir=args.out, now=device_clock(camera), on_progress=printer,
                           decimation=args.decimate, name=entry.name, fixed_pose=fixed,
                           filenames=track_filenames(None if entry.name == config.camera_name else entry.name))
        printer.tracker = session.tracker
        tracks.append(CameraTrack(entry.name, entry.on, session))
    if not tracks:
        raise DeviceError("no camera of the cell could be connected: nothing tracked")
    return tracks


def _say_failure(failure: CameraFailure) -> None:
    print(f"[{failure.name}] t={failure.t_s:.1f} s: the camera failed ({failure.message}); it is not read again, "
          "the other cameras go on", flush=True)


def _report_cell(args: argparse.Namespace, cell: CellOutcome, unconnected: list[str]) -> int:
    """Each camera's summary, which camera moved, the files; the exit status.

    1 when a camera failed or could not connect, a change is open on a camera on the flange, or a fixed
    camera was moved (or may have been: its configured pose no longer holds; ``cellcal handeye --camera``).
    """
    from cellcal.core.track.cell import CAUSE_PLANE
    from cellcal.core.track.result import TRACK_FILENAME
    from cellcal.core.track.words import fixed_summary_lines, summary_lines

    out = Path(args.out)
    for name, outcome in cell.outcomes.items():
        fixed = cell.places[name] == "base"
        print(f"camera {name!r} ({'fixed' if fixed else 'on the flange'}):")
        for line in fixed_summary_lines(outcome) if fixed else summary_lines(outcome):
            print(f"  {line}")
    for failure in cell.failures:
        print(f"camera {failure.name!r} failed at t={failure.t_s:.1f} s: {failure.message}")
    for name in unconnected:
        print(f"camera {name!r} could not be connected: not tracked")
    for attribution in cell.attributions:
        print(attribution.text)
    moved = [a.camera for a in cell.attributions if a.cause != CAUSE_PLANE]
    if moved:
        print(f"calibrate again: {', '.join(sorted(set(moved)))} (cellcal handeye --camera NAME)")
    print(f"written: {', '.join(str(out / f) for files in cell.files.values() for f in files)}")
    first = next((o for n, o in cell.outcomes.items() if cell.files[n][0] == TRACK_FILENAME), None)
    if first is not None:  # --apply: the first camera on the flange's mount (DIR/track.json)
        _apply(args, first, True)
    if cell.interrupted:
        return EXIT_INTERRUPTED
    open_change = any(o.document["change_unresolved"] for n, o in cell.outcomes.items() if cell.places[n] == "flange")
    return EXIT_FAILURE if open_change or moved or cell.failures or unconnected else EXIT_OK


def _apply(args: argparse.Namespace, outcome: TrackOutcome, applicable: bool) -> None:
    """``--apply``: the mount of a one-camera cell's camera, or of the first camera on the flange, only."""
    if not args.apply or outcome.interrupted:
        return
    if not applicable:
        print("not applied: --apply writes DIR/calibration.json for the first camera on the flange only; "
              "this camera's estimate is in its own file")
        return
    from cellcal.core.track.apply import apply

    applied = apply(Path(args.out), outcome.document)
    if isinstance(applied, str):
        print(f"not applied: {applied}")
    else:
        print(f"applied: {applied[0]} (version {applied[1]})")


def _one_of_several(config: CellConfig) -> dict[str, Any]:
    """``TrackRun``'s name, files and fixed pose for one camera of ``[[cameras]]`` (``--camera``); {} for one."""
    from cellcal.core.track.result import track_filenames

    if len(config.cameras) <= 1:
        return {}
    entry = config.camera_entry
    first = next((c.name for c in config.cameras if c.on == "flange"), None)
    return {"name": entry.name, "filenames": track_filenames(None if entry.name == first else entry.name),
            "fixed_pose": entry.pose_base if entry.on == "base" else None}


class _Printer:
    """Prints change events as they come (and a status line every 10 s of frames); feeds the live view.

    ``label``: the camera's name when it is one of several (its lines start ``[NAME]``, its frame id is
    ``camera_NAME``); ``fixed_pose``: a fixed camera's ``T_base_camera``.
    """

    STATUS_EVERY_S = 10.0

    def __init__(self, quiet: bool, view: Any, *, label: str | None = None, fixed_pose: Pose | None = None) -> None:
        from cellcal.devices.recording.scene import CAMERA_FRAME_ID

        self.quiet = quiet
        self.view = view
        self.prefix = "" if label is None else f"[{label}] "
        self.frame_id = CAMERA_FRAME_ID if label is None else f"{CAMERA_FRAME_ID}_{label}"
        self.fixed_pose = fixed_pose
        self._next_status = self.STATUS_EVERY_S
        self._used = 0
        self.tracker: Any = None

    def __call__(self, progress: TrackProgress) -> None:
        step = progress.step
        if progress.outcome == "accepted":
            self._used += 1
        if step is not None and step.event is not None:
            from cellcal.core.track.words import event_line

            print(self.prefix + event_line(step.event, final=False, fixed=self.fixed_pose is not None), flush=True)
        if not self.quiet and progress.t_s >= self._next_status:
            print(f"{self.prefix}t={progress.t_s:.1f} s: {progress.index + 1} frames, {self._used} used", flush=True)
            self._next_status += self.STATUS_EVERY_S
        if self.view is not None and progress.fit is not None and step is not None and self.view.has_subscribers():
            self._publish(progress)

    def _publish(self, progress: TrackProgress) -> None:
        from cellcal.core.liveview import track_scene

        step = progress.step
        assert step is not None and progress.fit is not None and progress.flange is not None
        assert progress.frame is not None
        state = self.tracker.state
        if self.fixed_pose is not None:  # a fixed camera: no mount; the plane's distance in its view
            values = {"t_s": progress.t_s, "outcome": progress.outcome, "chi2": step.chi2,
                      "view_offset_m": self.tracker.view_plane().offset_m, "change_open": state.change_unresolved,
                      "event": step.event.to_dict() if step.event else None}
            self.view.publish(track_scene(progress.frame, progress.fit, None, None, values,
                                          camera_frame_id=self.frame_id))
            return
        values = {"t_s": progress.t_s, "outcome": progress.outcome, "chi2": step.chi2,
                  "mount_translation_m": state.mount.translation.tolist(),
                  "mount_rpy_deg": state.mount_rpy_deg.tolist(), "change_open": state.change_unresolved,
                  "event": step.event.to_dict() if step.event else None}
        self.view.publish(track_scene(progress.frame, progress.fit, progress.flange, state.mount, values,
                                      camera_frame_id=self.frame_id))
