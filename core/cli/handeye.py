"""``cellcal handeye``: drive a hand-eye plan, estimate the camera mount, write ``DIR/handeye.json``."""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path
from typing import Any

from cellcal.core.cli.argtypes import path_arg
from cellcal.core.cli.exits import EXIT_FAILURE, EXIT_OK
from cellcal.core.cli.options import add_config_option, load_cell
from cellcal.core.cli.report import add_no_report_option
from cellcal.core.cli.resumable import resume_command, run_resumable
from cellcal.core.cli.text import one_line


def register(sub: Any) -> None:
    """Add the ``handeye`` subcommand."""
    p = sub.add_parser("handeye", help="estimate the camera mount ([mount]) from the measuring plane",
                       description="Drive the arm through a hand-eye plan, fit the measuring plane at every pose "
                       "and estimate the camera in the flange frame together with the plane in the base frame, "
                       "with 95 % intervals, per-pose residuals and an observability report. Writes "
                       "DIR/handeye.json and prints a [mount] table ready to paste.")
    add_config_option(p)
    p.add_argument("--out", metavar="DIR", default="cellcal-out", type=path_arg,
                   help="output directory (default: %(default)s); one run at a time")
    p.add_argument("--plan", choices=("auto", "config"), default="auto",
                   help="auto: inclinations x rolls from [handeye] (default); config: the [plan] table as it is")
    p.add_argument("--method", choices=("plane", "charuco", "both"), default="plane",
                   help="plane: the measuring plane (default); charuco: a ChArUco board and OpenCV's "
                   "calibrateHandEye; both: the two, compared")
    p.add_argument("--quiet", action="store_true", help="no progress bar or report; only the result path")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run from DIR/handeye.json.journal.jsonl (same configuration)")
    p.add_argument("--record", metavar="FILE.mcap", type=path_arg,
                   help="also record the session (config, frames, arm calls, result) to one MCAP file")
    p.add_argument("--replay", metavar="FILE.mcap", type=path_arg,
                   help="re-run a session recorded with --record from the file alone; says whether the result "
                   "is identical")
    p.add_argument("--dry-run", action="store_true",
                   help="print every move of the plan with its safety checks and what it can observe; "
                   "connect and move nothing")
    add_no_report_option(p)
    p.set_defaults(func=run)


def _dry_run(config: Any, poses: list[Any], seen: Any) -> int:
    """Print every move with its checks and the observability of the plan."""
    from cellcal.core.calibration.dryrun import check_moves, describe
    from cellcal.core.calibration.reach import arm_reach

    plan = config.plan
    limits = config.safety_limits()
    reach = arm_reach(config)
    print(f"dry run of cellcal handeye on {config.source}: {len(poses)} moves; arm class '{reach}'; "
          "no device is connected, nothing moves")
    for check in check_moves(limits, poses, plan.speed_m_s, plan.acceleration_m_s2, reach=reach):
        print(describe(check, len(poses), limits, plan.speed_m_s, plan.acceleration_m_s2, reach))
    if seen is not None:
        print(f"observability: {seen.message()}")
    print(f"dry run OK: all {len(poses)} moves inside the safety envelope and reachable")
    return EXIT_OK


def run(args: argparse.Namespace) -> int:
    """Run ``cellcal handeye``; returns the exit status."""
    from cellcal.core.handeye.plan import plan_poses
    from cellcal.core.handeye.run import check_observability
    from cellcal.devices.errors import CellcalError, ConfigError, OutputError

    if args.replay and args.config:
        raise ConfigError("--replay takes the configuration recorded in the file; drop --config")
    if args.replay:
        from cellcal.core.calibration.replay import replay_session
        from cellcal.core.handeye.fixed_record import records_fixed_camera

        if records_fixed_camera(args.replay):  # a fixed camera's recording (ADR 0061)
            from cellcal.core.cli.handeye_fixed import replay_fixed

            return replay_fixed(args)
        config, camera, arm = replay_session(args.replay)
    else:
        config, camera, arm = load_cell(args, allow_fixed=True), None, None
        if config.camera_entry.on == "base":  # a fixed camera: the arm shows it the plate (ADR 0061)
            from cellcal.core.cli.handeye_fixed import run_fixed

            return run_fixed(args, config)
    poses = plan_poses(config, args.plan)
    # an unobservable plan is refused before anything moves (the board method has no such limit)
    seen = None if args.method == "charuco" else check_observability(config, poses)
    if args.dry_run:
        return _dry_run(config, poses, seen)
    report = None
    if not args.no_report:  # the run's pictures and words (ADR 0037)
        from cellcal.core.report.runs import RunReport, camera_name

        report = RunReport("handeye", args.out, camera_name(config), config.source)
    try:
        if args.method != "plane":
            return _run_charuco(args, config, poses, report)
        return _run_plane(args, config, camera, arm, poses, report)
    except CellcalError as exc:
        if report is not None and not isinstance(exc, (ConfigError, OutputError)):  # a run that failed, not bad input
            report.failed(exc, one_line(f"cellcal: error: {exc}"))
            report.write(quiet=True)
        raise


def _run_plane(args: argparse.Namespace, config: Any, camera: Any, arm: Any, poses: list[Any],
               report: Any) -> int:
    """``--method plane``: the journaled plan run (with ``--record`` / ``--replay``)."""
    from cellcal.core.calibration.replay import recorded_devices
    from cellcal.core.cli.progress import progress_factory
    from cellcal.core.handeye.run import plan_calibrator
    from cellcal.devices.errors import CellcalError

    others = None
    if not args.replay:
        camera, arm, others = _devices(args, config)
    with contextlib.ExitStack() as stack:
        if args.record:  # the backend arm is recorded inside the safety wrapper, as by 'cellcal record'
            recorder = _recorder(stack, args, config)
            camera, arm = recorded_devices(recorder, camera, arm)
        if others is not None:  # the other cameras on the flange stay connected for the plan, closed after it
            others.connect(stack)
        calibrator = plan_calibrator(config, camera, arm, poses, progress_factory("poses", "pose", args.quiet),
                                     others=others)
        try:
            document = _run(args, calibrator, len(poses), others)
        except CellcalError:  # e.g. the driven camera's estimate refused: the others' files are written
            _print_others(others)
            raise
        if args.record and isinstance(document, dict):
            recorder.log_result(document)
    if isinstance(document, int):
        return document
    with _tee(report, document):
        _print_result(args, document)
        failed = _print_others(others)
        if args.record:
            print(f"session recorded to {args.record}")
        if args.replay:
            from cellcal.core.calibration.replay import compare_with_recording

            print(compare_with_recording(args.replay, document))
    if report is not None:
        report.write(quiet=args.quiet)
    return EXIT_FAILURE if failed else EXIT_OK


def _devices(args: argparse.Namespace, config: Any) -> tuple[Any, Any, Any]:
    """The driven camera, the arm and the cell's other cameras on the flange (None: none, or ``--record``).

    Fixed cameras are left out, and said (each has ``cellcal handeye --camera NAME``).
    """
    from cellcal.core.calibration.build import build_cell
    from cellcal.core.calibration.calibrator import build_devices
    from cellcal.core.handeye.several import FlangeCameras, split_cell_cameras

    if len(config.cameras) == 1:
        return (*build_devices(config), None)
    cameras, arm = build_cell(config)
    camera = cameras.pop(config.camera_name)
    flange, fixed = split_cell_cameras(config, cameras)
    if fixed:
        print(f"fixed camera(s) {', '.join(fixed)}: not part of a hand-eye run of the cameras on the flange "
              "(each has its own: cellcal handeye --camera NAME)")
    if flange and args.record:
        print(f"camera(s) {', '.join(flange)} on the flange: not captured (--record records the driven camera "
              f"'{config.camera_name}' alone)")
        return camera, arm, None
    return camera, arm, (FlangeCameras(config, flange) if flange else None)


def _print_others(others: Any) -> bool:
    """One line per other camera on the flange (its mount, or why none); whether any got no mount."""
    if others is None:
        return False
    for outcome in others.outcomes:
        print(outcome.line())
    return any(o.document is None for o in others.outcomes)


def _tee(report: Any, document: dict[str, Any]) -> Any:
    """While active, the printed words are the report's too (nothing without a report)."""
    if report is None:
        return contextlib.nullcontext()
    report.section["result"] = document
    return report.tee()


def _print_result(args: argparse.Namespace, document: dict[str, Any]) -> None:
    """The terminal report (unless ``--quiet``) and where the result is."""
    from cellcal.core.calibration.budget import handeye_budget_line
    from cellcal.core.handeye.result import HANDEYE_FILENAME, format_report

    if not args.quiet:
        print(format_report(document))
        budget = handeye_budget_line(document)        # when the result has its error budget (ADR 0059)
        if budget:
            print(budget)
    print(f"result written to {Path(args.out) / HANDEYE_FILENAME}")


def _run_charuco(args: argparse.Namespace, config: Any, poses: list[Any], report: Any) -> int:
    """``--method charuco|both``: the board views and the planes of one plan run (no journal, no recording)."""
    from cellcal.core.cli.progress import progress_factory
    from cellcal.core.handeye.charuco_run import run_charuco
    from cellcal.devices.errors import ConfigError

    if args.resume or args.record or args.replay:
        raise ConfigError("--resume, --record and --replay work with --method plane only (board views are not "
                          "journaled or replayed)")
    flange = [e.name for e in config.cameras if e.on == "flange" and e.name != config.camera_name]
    if flange:
        print(f"camera(s) {', '.join(flange)} on the flange: not captured (--method {args.method} runs the driven "
              f"camera '{config.camera_name}'; --method plane captures every camera on the flange)")
    document = run_charuco(config, poses, args.out, method=args.method, plan_kind=args.plan,
                           progress=progress_factory("poses", "pose", args.quiet))
    with _tee(report, document):
        _print_result(args, document)
    if report is not None:
        report.write(quiet=args.quiet)
    return EXIT_OK


def _recorder(stack: contextlib.ExitStack, args: argparse.Namespace, config: Any) -> Any:
    """A session recorder writing ``--record``, entered on ``stack`` (the file locked for the run)."""
    from cellcal.core.cli.record import open_recorder

    return open_recorder(stack, args.record, config, args.config)


def _run(args: argparse.Namespace, calibrator: Any, n_poses: int, others: Any = None) -> dict[str, Any] | int:
    """Run the plan into ``DIR/handeye.json`` (and each other flange camera's ``DIR/handeye-NAME.json``); the
    document, or the exit status of an interrupted run."""
    from cellcal.core.handeye.result import HANDEYE_FILENAME
    from cellcal.core.handeye.run import run_handeye

    return run_resumable(lambda: run_handeye(calibrator, args.out, plan_kind=args.plan, resume=args.resume,
                                             others=others),
                         calibrator, n_poses, Path(args.out) / HANDEYE_FILENAME,
                         resume_command("handeye", args, f"--plan {args.plan}"))
