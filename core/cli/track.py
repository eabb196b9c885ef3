"""``cellcal track``: keep the camera mount and the plane calibrated from the frames of the cell's own work.

Exit status: 0 the run ended with no open change; 1 a change was detected and the frames
after it have not yet shown everything again (or a device failed); 2 bad input; 130 Ctrl-C
(the files are written first).
"""

from __future__ import annotations

import argparse
import contextlib
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cellcal.core.cli.argtypes import integer, path_arg, real
from cellcal.core.cli.exits import EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_OK
from cellcal.core.cli.options import add_viz_port_option, check_viz_options

if TYPE_CHECKING:  # the tracker (numpy, scipy, the fit) is imported by run(), not by `cellcal --help`
    from cellcal.core.track.run import TrackOutcome, TrackProgress
    from cellcal.core.track.state import ChangeEvent

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
                       "and DIR/track.jsonl. With no --config, tracks the built-in simulated cell "
                       f"({DEFAULT_CONFIG}: its arm works on its own, its camera is knocked halfway) for "
                       f"{DEFAULT_SIM_DURATION_S:g} s.", epilog=EPILOG)
    p.add_argument("--config", metavar="PATH", type=path_arg,
                   help=f"cell configuration (TOML); default: the packaged {DEFAULT_CONFIG}")
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


# ---------------------------------------------------------------------- words
def _mm(v: float | None) -> str:
    return "n/a" if v is None or not math.isfinite(v) else f"{v * 1e3:.3f} mm"


def _event_line(event: ChangeEvent, *, final: bool = True) -> str:
    """One line for a change event: when, which, how large, resolved or not.

    While the run goes on (``final=False``) the size is the first fit's, from one or two poses:
    the rotation is told, the translation only once the whole run has been seen.
    """
    size = event.size
    later = "" if final else " (its size is refined as the work shows more)"
    if event.kind == "mount" and "rotation_deg" in size:
        moved = _mm(size.get("translation_m")) if final else ""
        what = f"the mount moved: {size['rotation_deg']:.3f} deg{', ' + moved if moved else ''}{later}"
    elif event.kind == "plane" and "plane_tilt_deg" in size:
        shift = f", {_mm(size.get('plane_shift_m'))} along its normal" if final else ""
        what = f"the plane moved: {size['plane_tilt_deg']:.3f} deg{shift}{later}"
    else:
        what = "mount or plane: cannot tell yet"
    state = f"; resolved at t={event.resolved_at_s:.1f} s" if event.resolved_at_s is not None else ""
    return f"t={event.detected_at_s:.1f} s: change detected ({what}){state}"


def summary_lines(outcome: TrackOutcome) -> list[str]:
    """The end-of-run summary: frames, the mount with its intervals, the plane, what is not seen, events."""
    from cellcal.core.calibration.report import ABOVE_NOTE, plane_height_mm

    doc = outcome.document
    c = doc["counters"]
    why = {k: v for k, v in sorted(c.items()) if k.startswith(("skipped", "refused", "no plane"))}
    reasons = ", ".join(f"{k.split(': ', 1)[-1]} {v}" for k, v in why.items()) or "none"
    lines = [f"frames: {c.get('frames', 0)}, used {c.get('accepted', 0)}, held out {c.get('held out', 0)}, "
             f"skipped {sum(why.values())} ({reasons})"]
    iv = doc["intervals"]
    conf = f"{iv['confidence'] * 100:g} %"
    mount = doc["mount"]
    axes = ("x", "y", "z")
    t_int, r_int = iv["mount_translation_m"], iv["mount_rpy_deg"]
    parts = []
    for i, a in enumerate(axes):
        lo_hi = t_int[i]
        span = f" [{lo_hi[0] * 1e3:.3f}, {lo_hi[1] * 1e3:.3f}]" if lo_hi else " (not seen)"
        parts.append(f"{a} {mount['translation_m'][i] * 1e3:.3f}{span}")
    lines.append(f"mount translation, mm ({conf}): " + ", ".join(parts))
    parts = []
    for i, a in enumerate(("roll", "pitch", "yaw")):
        lo_hi = r_int[i]
        span = f" [{lo_hi[0]:.4f}, {lo_hi[1]:.4f}]" if lo_hi else " (not seen)"
        parts.append(f"{a} {mount['rpy_deg'][i]:.4f}{span}")
    lines.append(f"mount rotation, deg ({conf}): " + ", ".join(parts))
    plane = doc["plane"]
    lines.append(f"plane (base frame): normal [{', '.join(f'{v:.5f}' for v in plane['normal'])}], "
                 f"{plane_height_mm(plane):+.3f} mm above the base origin")
    lines.append(ABOVE_NOTE)
    if iv.get("withheld"):
        lines.append(f"intervals withheld: {iv['withheld']}")
    for text in doc["unseen"]:
        lines.append(f"not seen yet: {text}")
    for event in outcome.state.events:
        lines.append(_event_line(event))
    if doc["change_unresolved"]:
        lines.append("a change is open: the frames after it have not shown every parameter again")
    return lines


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
    duration = args.duration
    if args.replay:
        from cellcal.core.calibration.replay import replay_session

        config, camera, arm = replay_session(args.replay, strict=True)
    else:
        from importlib import resources  # here: tempfile and random with it, not at `cellcal --help`

        path = args.config or str(resources.files("cellcal.configs").joinpath(DEFAULT_CONFIG))
        if args.config is None and duration is None and args.frames is None:
            duration = DEFAULT_SIM_DURATION_S
        config = load_config(path)
        camera, arm = build_devices(config)
    from cellcal.core.track.run import FrameClock, device_clock

    if args.replay:  # a replay's clock is its frames' own stamps
        camera = FrameClock(camera)
        now = camera.now
    else:  # the backend camera's clock, taken before any recording wrapper hides it
        now = device_clock(camera)
    with contextlib.ExitStack() as stack:
        if args.record:
            from cellcal.core.calibration.replay import recorded_devices
            from cellcal.core.cli.record import open_recorder

            recorder = open_recorder(stack, args.record, config, args.config)
            camera, arm = recorded_devices(recorder, camera, arm)
        outcome = _track(args, config, camera, arm, duration, now)
        if args.record:
            recorder.log_result(outcome.document)
    return _report(args, outcome)


def _track(args: argparse.Namespace, config: Any, camera: Any, arm: Any, duration: float | None,
           now: Any) -> TrackOutcome:
    """Connect, track until the end of the run, close; the outcome (files written)."""
    from cellcal.core.liveview import live_view_session
    from cellcal.core.track.run import ReadOnlyArm, TrackRun

    reader = ReadOnlyArm(arm)
    with live_view_session(args.viz_port, track=True, wait_s=args.viz_wait) as view:
        printer = _Printer(args.quiet, view)
        with camera, reader:
            if not args.quiet:
                print(f"tracking {config.camera_section.get('backend')} camera, {config.arm_section.get('backend')} "
                      f"arm ({config.source}); the arm is read, never moved; Ctrl-C to stop", flush=True)
            session = TrackRun(config, camera, reader, out_dir=args.out, now=now, on_progress=printer,
                               decimation=args.decimate)
            printer.tracker = session.tracker
            outcome = session.run(duration, args.frames)
        if view is not None and args.viz_linger and not outcome.interrupted:
            from cellcal.core.liveview import linger

            linger(view, args.viz_linger)
    return outcome


def _report(args: argparse.Namespace, outcome: TrackOutcome) -> int:
    """Print the summary and where the files are, apply if asked; the exit status."""
    for line in summary_lines(outcome):
        print(line)
    out = Path(args.out)
    print(f"written: {out / 'track.json'}, {out / 'track.jsonl'}")
    if args.apply and not outcome.interrupted:
        from cellcal.core.track.apply import apply

        applied = apply(out, outcome.document)
        if isinstance(applied, str):
            print(f"not applied: {applied}")
        else:
            print(f"applied: {applied[0]} (version {applied[1]})")
    if args.record:
        print(f"session recorded to {args.record}")
    if outcome.interrupted:
        return EXIT_INTERRUPTED
    return EXIT_FAILURE if outcome.document["change_unresolved"] else EXIT_OK


class _Printer:
    """Prints change events as they come (and a status line every 10 s of frames); feeds the live view."""

    STATUS_EVERY_S = 10.0

    def __init__(self, quiet: bool, view: Any) -> None:
        self.quiet = quiet
        self.view = view
        self._next_status = self.STATUS_EVERY_S
        self._used = 0
        self.tracker: Any = None

    def __call__(self, progress: TrackProgress) -> None:
        step = progress.step
        if progress.outcome == "accepted":
            self._used += 1
        if step is not None and step.event is not None:
            print(_event_line(step.event, final=False), flush=True)
        if not self.quiet and progress.t_s >= self._next_status:
            print(f"t={progress.t_s:.1f} s: {progress.index + 1} frames, {self._used} used", flush=True)
            self._next_status += self.STATUS_EVERY_S
        if self.view is not None and progress.fit is not None and step is not None and self.view.has_subscribers():
            self._publish(progress)

    def _publish(self, progress: TrackProgress) -> None:
        from cellcal.core.liveview import track_scene

        step = progress.step
        assert step is not None and progress.fit is not None and progress.flange is not None
        assert progress.frame is not None
        state = self.tracker.state
        values = {"t_s": progress.t_s, "outcome": progress.outcome, "chi2": step.chi2,
                  "mount_translation_m": state.mount.translation.tolist(),
                  "mount_rpy_deg": state.mount_rpy_deg.tolist(), "change_open": state.change_unresolved,
                  "event": step.event.to_dict() if step.event else None}
        self.view.publish(track_scene(progress.frame, progress.fit, progress.flange, state.mount, values))
