"""``cellcal monitor``: watch one or more cameras for drift of the measuring plane.

Exit status: 0 no drift flagged during the run; 1 drift flagged, or a device failed;
2 bad input (configuration, baseline file, usage); 130 Ctrl-C (after the summary).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cellcal.core.cli.argtypes import integer, path_arg, real
from cellcal.core.cli.exits import EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_OK
from cellcal.core.cli.options import add_viz_port_option, check_input_file, check_viz_options
from cellcal.core.cli.report import add_no_report_option

if TYPE_CHECKING:  # the monitor (numpy, the fit) is imported by run(), not by `cellcal --help`
    from cellcal.core.calibration.config import CellConfig
    from cellcal.core.monitor import Baseline, DriftEvent, Monitor, MonitorStatus, MonitorSummary

#: Largest baseline file read (a --save-baseline file or a result.json), bytes.
MAX_BASELINE_BYTES = 50 << 20
EPILOG = ("exit status: 0 no drift flagged during the run; 1 drift flagged (or a device failed); "
          "2 bad configuration, baseline file or usage; 130 stopped with Ctrl-C (after the summary).")


def register(sub: Any) -> None:
    """Add the ``monitor`` subcommand."""
    p = sub.add_parser("monitor", help="watch cameras for drift of the measuring plane (tilt, height)",
                       description="Capture continuously from one camera per configuration, fit the measuring "
                       "plane in every frame and report drift of its tilt or height beyond the [monitor] "
                       "thresholds, with hysteresis. The arm is never moved. With no --config, watches the "
                       "built-in simulated cell. Stop with Ctrl-C.", epilog=EPILOG)
    p.add_argument("--config", metavar="PATH", action="append", type=path_arg,
                   help="cell configuration (TOML), one camera each; repeat for several cameras "
                   "(default: packaged sim.toml)")
    p.add_argument("--duration", metavar="S", type=real(gt=0), help="stop after S seconds (scripted runs)")
    p.add_argument("--frames", metavar="N", type=integer(ge=1), help="stop after N frames per camera (scripted runs)")
    p.add_argument("--baseline", metavar="FILE", type=path_arg,
                   help="expected plane: a --save-baseline file, or a calibrate result.json (its plane in the "
                   "base frame, seen from the arm's current pose; the arm is connected only to read that pose). "
                   "Default: the mean of the first frames")
    p.add_argument("--save-baseline", metavar="FILE", type=path_arg,
                   help="write the baselines in use at the end of the run")
    p.add_argument("--quiet", action="store_true", help="print only drift events and the summary")
    p.add_argument("--out", metavar="DIR", type=path_arg,
                   help="write the run's report there on exit (also on Ctrl-C): DIR/report.html with tilt and "
                   "height over time, the thresholds and flagged drift, report.txt, report-data.json")
    add_no_report_option(p)
    add_viz_port_option(p)
    p.set_defaults(func=run)


# ---------------------------------------------------------------------- formatting
def _deg(rad: float | None) -> str:
    return "n/a" if rad is None else f"{math.degrees(rad):.3f} deg"


def _mm(m: float | None, digits: int = 2) -> str:
    return "n/a" if m is None else f"{m * 1000:.{digits}f} mm"


def format_event(event: DriftEvent, t0: float) -> str:
    """One line for a drift event (times relative to the camera's first frame)."""
    what = "DRIFT STARTED" if event.kind == "drift_started" else "drift cleared"
    causes = f" ({' and '.join(event.causes)})" if event.causes else ""
    return (f"[{event.label}] t=+{event.timestamp - t0:.2f} s {what}{causes}: "
            f"tilt {_deg(event.tilt_deviation_rad)} (threshold {_deg(event.tilt_threshold_rad)}), "
            f"height {_mm(event.height_deviation_m)} (threshold {_mm(event.height_threshold_m)})")


def format_baseline(label: str, b: Baseline, tilt_thr: float | None, height_thr: float | None) -> str:
    """One line describing an established baseline and the effective thresholds."""
    return (f"[{label}] baseline tilt_x {_deg(b.tilt_x_rad)}, tilt_y {_deg(b.tilt_y_rad)}, "
            f"height {_mm(b.height_m)}; noise {_deg(b.tilt_noise_rad)}, {_mm(b.height_noise_m, 4)} (1 sigma); "
            f"thresholds {_deg(tilt_thr)}, {_mm(height_thr)}")


def format_summary(summary: MonitorSummary) -> list[str]:
    """The closing lines: one per camera."""
    how = "interrupted" if summary.interrupted else "finished"
    lines = [f"monitor {how} after {summary.elapsed_s:.1f} s"]
    for c in summary.cameras:
        starts = sum(e.kind == "drift_started" for e in c.events)
        state = "DRIFTING" if c.drifting else ("ok" if c.baseline is not None else "no baseline yet")
        lines.append(f"  {c.label}: {c.frames} frames, {c.errors} failed, {starts} drift event(s), "
                     f"now {state}; largest deviation tilt {_deg(c.max_tilt_deviation_rad)}, "
                     f"height {_mm(c.max_height_deviation_m)}")
    return lines


class _Printer:
    """The per-frame callback: event lines, baseline lines, a periodic status line."""

    def __init__(self, monitor_period_s: dict[str, float], quiet: bool) -> None:
        self.quiet = quiet
        self.every = monitor_period_s
        self.t0: dict[str, float] = {}
        self.last_line: dict[str, float] = {}
        self.announced: set[str] = set()
        self.monitor: Monitor | None = None

    def __call__(self, status: MonitorStatus) -> None:
        label = status.label
        d = status.detector
        if d is not None:
            self.t0.setdefault(label, d.sample.timestamp)
        if d is not None and d.event is not None:
            print(format_event(d.event, self.t0[label]), flush=True)
        if self.quiet:
            return
        if d is not None and d.phase != "baseline" and label not in self.announced and self.monitor is not None:
            self.announced.add(label)
            cam = next(c for c in self.monitor.summary().cameras if c.label == label)
            if cam.baseline is not None:
                print(format_baseline(label, cam.baseline, cam.tilt_threshold_rad, cam.height_threshold_m),
                      flush=True)
        now = time.monotonic()
        if now - self.last_line.get(label, -math.inf) < self.every[label]:
            return
        self.last_line[label] = now
        if d is None:
            print(f"[{label}] frame {status.index}: failed: {status.error}", flush=True)
        elif d.phase == "baseline":
            print(f"[{label}] frame {status.index}: measuring the baseline", flush=True)
        else:
            print(f"[{label}] frame {status.index}: {d.phase:<5} tilt {_deg(d.tilt_deviation_rad)}, "
                  f"height {_mm(d.height_deviation_m)} from baseline", flush=True)


# ---------------------------------------------------------------------- cameras
def _cameras_of(path: str | None, taken: set[str]) -> list[tuple[str, CellConfig]]:
    """Every camera of one configuration, labelled: one ``[camera]`` as the file's stem, ``[[cameras]]`` as
    ``STEM.NAME`` each (on the flange or fixed: each watches the measuring plane from where it is)."""
    from cellcal.core.calibration.config import load_every_camera

    configs = load_every_camera(path)  # the file read once
    stem = _label(path, taken)
    if len(configs) == 1:
        return [(stem, configs[0])]
    return [(f"{stem}.{c.camera_name}", c) for c in configs]


def _label(path: str | None, taken: set[str]) -> str:
    base = "sim" if path is None else Path(path).stem
    label, n = base, 2
    while label in taken:
        label, n = f"{base}-{n}", n + 1
    taken.add(label)
    return label


# ---------------------------------------------------------------------- run
def run(args: argparse.Namespace) -> int:
    """Run ``cellcal monitor``; returns the exit status."""
    from cellcal.core.monitor import monitored_cameras

    check_viz_options(args)
    if args.baseline:
        check_input_file(args.baseline, MAX_BASELINE_BYTES)
    paths: list[str | None] = list(args.config) if args.config else [None]
    taken: set[str] = set()
    configs = [labelled for p in paths for labelled in _cameras_of(p, taken)]
    specs = monitored_cameras(configs, args.baseline)
    printer = _Printer({label: config.monitor.status_every_s for label, config in configs}, args.quiet)
    report, capture = _monitor_report(args, configs)
    callback: Any = printer if capture is None else _chain(capture, printer)
    with contextlib.nullcontext() if report is None else report.tee():
        code, summary = _watch(args, configs, specs, callback, printer)
    if report is not None:
        report.section["cameras"] = {c.label: _camera_report(c, capture) for c in summary.cameras}
        report.data["status"] = "interrupted" if summary.interrupted else (
            "drift flagged" if summary.drift_detected else "ok")
        report.write(quiet=args.quiet)
    return code


def _monitor_report(args: argparse.Namespace, configs: list[tuple[str, CellConfig]]) -> tuple[Any, Any]:
    """With ``--out`` (and no ``--no-report``): the run's report and the capture of its drift values."""
    if not args.out or args.no_report:
        return None, None
    from cellcal.core.report import MonitorCapture
    from cellcal.core.report.runs import RunReport, camera_name

    report = RunReport("monitor", args.out, ", ".join(f"{label}: {camera_name(c)}" for label, c in configs),
                       ", ".join(str(c.source) for _, c in configs))
    return report, MonitorCapture()


def _chain(first: Any, then: Any) -> Any:
    """A status callback that calls ``first`` then ``then``."""

    def both(status: MonitorStatus) -> None:
        first(status)
        then(status)

    return both


def _camera_report(c: Any, capture: Any) -> dict[str, Any]:
    """A monitored camera's part of the report data (SI units, as the summary has them)."""
    return {"frames": c.frames, "errors": c.errors, "drift_events": sum(e.kind == "drift_started" for e in c.events),
            "drifting": c.drifting, "max_tilt_deviation_rad": c.max_tilt_deviation_rad,
            "max_height_deviation_m": c.max_height_deviation_m, "tilt_threshold_rad": c.tilt_threshold_rad,
            "height_threshold_m": c.height_threshold_m, "series": capture.series.get(c.label, {})}


def _watch(args: argparse.Namespace, configs: list[tuple[str, CellConfig]], specs: Any, callback: Any,
           printer: _Printer) -> tuple[int, MonitorSummary]:
    """Watch the cameras until the run ends; the exit status and the summary."""
    from cellcal.core.liveview import MonitorFeed, camera_frame_id, linger, live_view_session
    from cellcal.core.monitor import Monitor, write_baselines

    labels = [label for label, _ in configs]
    several = labels if len(labels) > 1 else []  # each camera on its own topics, its frame camera_LABEL in /tf
    with live_view_session(getattr(args, "viz_port", None), drift=True, wait_s=getattr(args, "viz_wait", None),
                           cameras=several) as view:
        feed = None if view is None else MonitorFeed(view, callback, labels)
        for label, config in configs if several else ():
            pose = config.camera_entry.pose_base
            if view is not None and config.camera_entry.on == "base" and pose is not None:
                view.place_camera(camera_frame_id(label), pose)
        monitor = Monitor(specs, callback) if feed is None else Monitor(specs, feed.on_status, fit=feed.fit)
        printer.monitor = monitor
        if not args.quiet:
            where = ", ".join(f"{label} ({c.camera_section['backend']}, {c.source})" for label, c in configs)
            print(f"monitoring {where}; Ctrl-C to stop", flush=True)
        summary = monitor.run(args.duration, args.frames)
        for line in format_summary(summary):
            print(line)
        if args.save_baseline:
            print(f"baselines written to {write_baselines(args.save_baseline, summary.cameras)}")
        sys.stdout.flush()
        if summary.interrupted:
            return EXIT_INTERRUPTED, summary
        if view is not None and getattr(args, "viz_linger", None):
            linger(view, args.viz_linger)
    return (EXIT_FAILURE if summary.drift_detected else EXIT_OK), summary
