"""``cellcal calibrate``: run the configured plan and write ``DIR/result.json``."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cellcal.core.cli.argtypes import path_arg
from cellcal.core.cli.exits import EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_OK
from cellcal.core.cli.options import add_config_option, add_viz_port_option, check_viz_options, load_cell
from cellcal.core.cli.progress import progress_factory
from cellcal.core.cli.report import add_no_report_option
from cellcal.core.cli.resumable import resume_command, run_resumable
from cellcal.core.cli.text import one_line
from cellcal.core.console import say
from cellcal.devices.errors import CellcalError, ConfigError, OutputError

if TYPE_CHECKING:  # the calibration (numpy, OpenCV) is imported when the command runs, not by `cellcal --help`
    from cellcal.core.calibration.config import CellConfig
    from cellcal.core.liveview import LiveView
    from cellcal.devices.camera import Camera3D
    from cellcal.devices.safety import SafeArm


def register(sub: Any) -> None:
    """Add the ``calibrate`` subcommand."""
    p = sub.add_parser("calibrate", help="run the calibration plan and write DIR/result.json",
                       description="Drive the arm through the plan, capture the 3D camera at each pose, "
                       "compute the measuring plane and report the camera's pose relative to it. "
                       "With no --config, runs the built-in simulated cell (the paper's experiment).")
    add_config_option(p)
    p.add_argument("--out", metavar="DIR", default="cellcal-out", type=path_arg,
                   help="output directory (default: %(default)s); one run at a time")
    p.add_argument("--check", action="store_true",
                   help="validate the configuration and show what would connect to what; touch no device")
    p.add_argument("--quiet", action="store_true", help="no progress bar or table; only the result path")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run from DIR/result.json.journal.jsonl: recorded poses are not "
                   "moved to or captured again (the configuration must be unchanged)")
    p.add_argument("--dry-run", action="store_true",
                   help="print every move of the plan with its safety checks; connect and move nothing")
    p.add_argument("--strict", action="store_true",
                   help="fail the run (exit 1, result still written) when the poses' planes disagree in the base "
                   "frame: cross-pose verdict 'inconsistent' or 'failed' (e.g. a wrong [mount]; a camera that does "
                   "not move with the arm stops every run, gate view_follows_arm)")
    add_viz_port_option(p)
    p.add_argument("--replay", metavar="FILE.mcap", type=path_arg,
                   help="re-run a session recorded with 'cellcal record' from the file alone (its recorded "
                   "configuration, replay camera and arm); reports whether the result is identical")
    add_no_report_option(p)
    p.set_defaults(func=run)


def _session(args: argparse.Namespace) -> tuple[CellConfig, Camera3D, SafeArm, dict[str, Camera3D]]:
    """The configuration, the driven camera, the arm and the cell's other cameras (``[[cameras]]``; ADR 0061):
    from ``--config``, or from a recording with ``--replay`` (its one camera)."""
    from cellcal.core.calibration.build import build_cell
    from cellcal.core.calibration.calibrator import build_devices

    if getattr(args, "replay", None):
        if args.config:
            raise ConfigError("--replay takes the configuration recorded in the file; drop --config")
        from cellcal.core.calibration.replay import replay_session  # the recording's reader, only here

        return (*replay_session(args.replay), {})
    config = load_cell(args)
    if len(config.cameras) == 1:
        return (config, *build_devices(config), {})
    cameras, arm = build_cell(config)
    driven = cameras.pop(config.camera_name)
    return config, driven, arm, cameras


#: Config keys that say where a device is, shown by ``--check``.
ADDRESS_KEYS = ("host", "xmlrpc_port", "tcp_port", "port", "pcic_port", "device_id", "baudrate", "axes", "file")
#: Keys that only mean something on a serial line (left out when the device is reached by ``host``).
_SERIAL_KEYS = ("baudrate",)


def _where(device: Any) -> str:
    config = getattr(device, "config", None)
    if config is None or not dataclasses.is_dataclass(config):
        return ""
    networked = bool(getattr(config, "host", None))
    parts = [f"{k}={getattr(config, k)!r}" for k in ADDRESS_KEYS
             if getattr(config, k, None) is not None and not (networked and k in _SERIAL_KEYS)]
    return f" at {', '.join(parts)}" if parts else ""


def _check(args: argparse.Namespace) -> int:
    from cellcal.core.calibration.calibrator import Calibrator
    from cellcal.core.calibration.plan_image import describe_plan_image

    config, camera, arm, _others = _session(args)
    calibrator = Calibrator(config, camera, arm)
    calibrator.check_plan(None)
    image = describe_plan_image(config, camera.configured_intrinsics())  # refuses an image too small for the plan
    poses = calibrator.poses
    plan = config.plan
    print(f"config:  {config.source} (cell '{config.cell.name}')")
    from cellcal.devices.correction import CorrectedCamera

    shown = camera.raw if isinstance(camera, CorrectedCamera) else camera
    print(f"camera:  backend '{camera.backend_name}'{_where(shown)} "
          f"({type(shown).__module__}.{type(shown).__qualname__})")
    if isinstance(camera, CorrectedCamera):
        print(f"correction: {camera.describe_correction()} (applied to every frame)")
    print(f"arm:     backend '{arm.inner.backend_name}'{_where(arm.inner)} "
          f"({type(arm.inner).__module__}.{type(arm.inner).__qualname__}), behind the safety envelope")
    print(f"plan:    {len(poses)} poses x {len(plan.perimeters_px)} perimeters x {len(plan.methods)} methods "
          f"({', '.join(plan.methods)}); every target pose inside the safety envelope")
    print(f"image:   {image}")
    print("config OK (no device was touched)")
    return EXIT_OK


def _print_report(document: dict[str, Any]) -> None:
    """The per-measurement table, the mean error per method, the full-frame block and the run time."""
    from cellcal.core.calibration.report import format_full_frame, format_table

    rows = [row for pose in document["poses"] for row in pose["measurements"]]
    print(format_table(rows))
    print()
    for method, groups in document["summary"]["methods"].items():
        err = groups["all"]["mean_error_pct"]
        text = f"{err:.3f} %" if err is not None else "n/a (no reference)"
        print(f"{method:<18} mean |error| {text} over {groups['all']['n']} estimates")
    full_frame = format_full_frame(document)
    if full_frame:
        print()
        print(full_frame)
    print(f"total {document['timings_s']['total']:.2f} s")


#: Cross-pose verdicts that say the poses' planes disagree (``--strict`` fails the run on them).
DISAGREEING_VERDICTS = ("inconsistent", "failed")


def _disagreement(document: dict[str, Any]) -> str:
    """``"<verdict>: <interpretation>"`` when the poses disagree on the plane, else ""."""
    cons = (document.get("summary") or {}).get("plane_consistency") or {}
    verdict = cons.get("verdict")
    return f"{verdict}: {cons.get('interpretation', '')}" if verdict in DISAGREEING_VERDICTS else ""


def run(args: argparse.Namespace) -> int:
    """Run ``cellcal calibrate``; returns the exit status."""
    check_viz_options(args)
    if args.check:
        return _check(args)
    if getattr(args, "dry_run", False):
        from cellcal.core.calibration.dryrun import dry_run

        dry_run(load_cell(args))
        return EXIT_OK
    config, camera, arm, others = _session(args)
    if getattr(args, "viz_port", None) is None:  # the live view's imports only when it is asked for
        return _calibrate(args, config, camera, arm, None, others)
    from cellcal.core.liveview import linger, live_view_session

    # a cell's several cameras: each on its own topics with its frame camera_NAME in /tf (ADR 0061)
    names = [config.camera_name, *others] if others else []
    with live_view_session(args.viz_port, wait_s=getattr(args, "viz_wait", None), cameras=names) as view:
        status = _calibrate(args, config, camera, arm, view, others)
        if view is not None and getattr(args, "viz_linger", None) and status != EXIT_INTERRUPTED:
            linger(view, args.viz_linger)
    return status


def _calibrate(args: argparse.Namespace, config: CellConfig, camera: Camera3D, arm: SafeArm,
               view: LiveView | None, others: dict[str, Camera3D] | None = None) -> int:
    """Run the plan into ``DIR/result.json`` (publishing to ``view``; the ``others`` captured at each pose into
    ``DIR/result-NAME.json``), print the report; the exit status."""
    import contextlib

    from cellcal.core.calibration.calibrator import Calibrator, run_to_file
    from cellcal.core.calibration.cell_capture import OtherCameras
    from cellcal.core.calibration.report import RESULT_FILENAME

    out = Path(args.out) / RESULT_FILENAME
    report = None
    if not getattr(args, "no_report", False):  # the run's pictures and words (ADR 0037)
        from cellcal.core.report.runs import CalibrationReport

        report = CalibrationReport(config, camera, args.out)
    extra = OtherCameras(config, others) if others else None
    live = None if view is None else view.observe_pose(config.mount.pose(), config.camera_name if extra else None)
    if view is not None and extra is not None:  # every camera drawn in the one scene
        from cellcal.core.liveview import camera_frame_id

        for name, (on, pose) in extra.places.items():
            if on == "base":
                view.place_camera(camera_frame_id(name), pose)
            extra.observers[name] = view.observe_pose(pose if on == "flange" else None, name)
    calibrator = Calibrator(config, camera if report is None else report.camera, arm,  # type: ignore[arg-type]
                            progress=progress_factory("poses", "pose", args.quiet),
                            observer=_chain(live if report is None else report.observer(live), extra),
                            companion=extra)  # the other cameras start with the driven one at each pose
    try:
        with contextlib.ExitStack() as stack:
            if extra is not None:  # the other cameras stay connected for the plan, closed after it
                extra.connect(stack)
            document = run_resumable(lambda: run_to_file(calibrator, out, resume=getattr(args, "resume", False)),
                                     calibrator, len(calibrator.poses), out, resume_command("calibrate", args))
            if extra is not None and not isinstance(document, int):
                for path in extra.write(args.out, calibrator._reference_plane(), calibrator._arm_model()):
                    print(f"camera {path.stem.removeprefix('result-')!r}: result written to {path}")
    except CellcalError as exc:
        if report is not None and not isinstance(exc, (ConfigError, OutputError)):  # a run that failed, not bad input
            report.failed_run(exc, one_line(f"cellcal: error: {exc}"), calibrator.poses)
            report.write(quiet=True)
        raise
    if report is not None and not isinstance(document, int):
        report.finished(document)
        with report.tee():
            status = _summarize(args, calibrator, document, out)
        report.write(quiet=args.quiet)
        return status
    if isinstance(document, int):  # interrupted: the exit status
        return document
    return _summarize(args, calibrator, document, out)


def _chain(first: Any, then: Any) -> Any:
    """A pose observer calling ``first`` then ``then`` (either may be None)."""
    if first is None or then is None:
        return then if first is None else first

    def both(record: Any, frames: Any, result: Any) -> None:
        first(record, frames, result)
        then(record, frames, result)

    return both


def _summarize(args: argparse.Namespace, calibrator: Any, document: dict[str, Any], out: Path) -> int:
    """Print the report and the result's path; the exit status (``--strict`` fails a disagreement)."""
    if not args.quiet:
        _print_report(document)
    disagree = _disagreement(document)
    print(f"result written to {out}" + (f"; cross-pose verdict {disagree}" if disagree else ""))
    strict = "--strict" if getattr(args, "strict", False) else "[cell] strict" if calibrator.config.cell.strict else ""
    if disagree and strict:
        say(f"cellcal: {strict}: the poses' planes disagree (cross-pose verdict {disagree})")
        return EXIT_FAILURE
    if getattr(args, "replay", None):
        from cellcal.core.calibration.replay import compare_with_recording

        print(compare_with_recording(args.replay, document))
    return EXIT_OK
