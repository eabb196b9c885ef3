"""``cellcal handeye --camera NAME`` for a fixed camera (``on = "base"``): the plate plan, its fit, the result file."""

from __future__ import annotations

import argparse
import contextlib
import math
from pathlib import Path
from typing import Any

from cellcal.core.cli.exits import EXIT_OK
from cellcal.core.cli.resumable import resume_command, run_resumable
from cellcal.core.console import say
from cellcal.core.handeye.fixed_run import fixed_filename


def run_fixed(args: argparse.Namespace, config: Any) -> int:
    """Run the fixed camera's calibration; returns the exit status (dry run: every move and what the plan sees).

    Raises:
        ConfigError: An option the fixed camera's run does not take (one line).
        CellcalError: As the run.
    """
    from cellcal.core.calibration.build import build_cell

    poses, dropped, seen = _plan(args, config)
    if args.dry_run:
        return _dry_run(config, poses, seen)
    cameras, arm = build_cell(config)
    return _run(args, config, cameras[config.camera_name], arm, poses, dropped)


def replay_fixed(args: argparse.Namespace) -> int:
    """``cellcal handeye --replay FILE.mcap`` of a fixed camera's recording: the run again from the file alone,
    then whether its result is the recorded one exactly.

    Raises:
        ConfigError: ``--config`` given (the recording holds it), or an option the fixed run does not take.
        RecordingFileError: The file is not a fixed camera's recording.
        CellcalError: As the run (a replay that strays from the recording says where).
    """
    from cellcal.core.handeye.fixed_record import fixed_replay_session
    from cellcal.devices.errors import ConfigError

    if args.config:
        raise ConfigError("--replay takes the configuration recorded in the file; drop --config")
    config, camera, arm = fixed_replay_session(args.replay)
    poses, dropped, seen = _plan(args, config)
    if args.dry_run:
        return _dry_run(config, poses, seen)
    return _run(args, config, camera, arm, poses, dropped)


def _plan(args: argparse.Namespace, config: Any) -> tuple[list[Any], list[str], Any]:
    """The plate plan, the poses left out and what it sees; refused before anything moves if it cannot see all."""
    from cellcal.core.handeye.fixed_run import check_fixed_plan, fixed_plan
    from cellcal.devices.errors import ConfigError

    if args.plan != "auto":
        raise ConfigError(f"camera {config.camera_name!r} is fixed: its plan shows it the [plate] (--plan auto)")
    if args.method != "plane" and (args.resume or args.record or args.replay):
        raise ConfigError("--resume, --record and --replay work with --method plane only (board views are not "
                          "journaled or replayed)")
    if args.method != "plane":
        from cellcal.core.handeye.charuco_run import board_spec

        board_spec(config)          # a simulated board the detector does not look for is refused here
    poses, dropped = fixed_plan(config)
    if dropped:
        say(f"note: {len(dropped)} of {len(poses) + len(dropped)} plate poses left out (envelope or reach); "
            f"first: {dropped[0]}")
    return poses, dropped, check_fixed_plan(config, poses)      # an unobservable plan is refused here


def _dry_run(config: Any, poses: list[Any], seen: Any) -> int:
    from cellcal.core.calibration.dryrun import check_moves, describe
    from cellcal.core.calibration.reach import arm_reach

    plan, limits, reach = config.plan, config.safety_limits(), arm_reach(config)
    print(f"dry run of cellcal handeye for fixed camera {config.camera_name!r} on {config.source}: {len(poses)} "
          f"moves showing the plate; arm class '{reach}'; no device is connected, nothing moves")
    for check in check_moves(limits, poses, plan.speed_m_s, plan.acceleration_m_s2, reach=reach):
        print(describe(check, len(poses), limits, plan.speed_m_s, plan.acceleration_m_s2, reach))
    print(f"observability: {seen.message()}")
    print(f"dry run OK: all {len(poses)} moves inside the safety envelope and reachable")
    return EXIT_OK


def _run(args: argparse.Namespace, config: Any, camera: Any, arm: Any, poses: list[Any], dropped: list[str]) -> int:
    """The plate plan on ``camera`` and ``arm`` (recorded with ``--record``), its result and report."""
    from cellcal.core.cli.text import one_line
    from cellcal.core.report.fixed import FixedReport
    from cellcal.devices.errors import CellcalError, ConfigError, OutputError

    report = None if args.no_report else FixedReport(args.out, config.camera_name, config.source)
    try:
        document = _measure(args, config, camera, arm, poses, dropped)
    except CellcalError as exc:
        if report is not None and not isinstance(exc, (ConfigError, OutputError)):  # a run that failed, not bad input
            report.failed(exc, one_line(f"cellcal: error: {exc}"))
            report.write(quiet=True)
        raise
    if isinstance(document, int):
        return document
    if report is not None:
        report.section["result"] = document
    with report.tee() if report is not None else contextlib.nullcontext():
        if not args.quiet:
            print(format_fixed(document))
        print(f"result written to {Path(args.out) / fixed_filename(config.camera_name)}")
        if args.record:
            print(f"session recorded to {args.record}")
        if args.replay:
            from cellcal.core.handeye.fixed_record import compare_fixed_with_recording

            print(compare_fixed_with_recording(args.replay, document))
    if report is not None:
        report.write(quiet=args.quiet)
    return EXIT_OK


def _measure(args: argparse.Namespace, config: Any, camera: Any, arm: Any, poses: list[Any], dropped: list[str]
             ) -> dict[str, Any] | int:
    """The journaled plate run into ``DIR/handeye-NAME.json``; the document, or the exit status of an interrupted
    run. With ``--record`` the camera and the backend arm are recorded (inside the safety wrapper) with the result."""
    from cellcal.core.calibration.replay import recorded_devices
    from cellcal.core.cli.progress import progress_factory
    from cellcal.core.handeye.fixed_run import FixedCalibrator, run_fixed_handeye

    out = Path(args.out) / fixed_filename(config.camera_name)
    if args.method != "plane":          # the board the gripper holds (eye-to-hand), and with both the plate too
        from cellcal.core.handeye.fixed_charuco import run_fixed_board

        return run_fixed_board(config, camera, arm, poses, args.out, method=args.method, left_out=dropped,
                               progress=progress_factory("poses", "pose", args.quiet))
    with contextlib.ExitStack() as stack:
        recorder = _recorder(stack, args, config) if args.record else None
        if recorder is not None:
            camera, arm = recorded_devices(recorder, camera, arm)
        calibrator = FixedCalibrator(config, camera, arm, poses, progress_factory("poses", "pose", args.quiet),
                                     left_out=dropped)
        document = run_resumable(lambda: run_fixed_handeye(calibrator, args.out, resume=args.resume),
                                 calibrator, len(poses), out, resume_command("handeye", args))
        if recorder is not None and isinstance(document, dict):
            recorder.log_result(document)
    return document


def _recorder(stack: contextlib.ExitStack, args: argparse.Namespace, config: Any) -> Any:
    """A session recorder writing ``--record`` (locked for the run), entered on ``stack``: the configuration as
    read with the fixed camera alone in ``[[cameras]]`` (:func:`recorded_fixed_document`), its text for humans."""
    import tomllib

    from cellcal.core.calibration.config import read_config_text
    from cellcal.core.calibration.outlock import OutputLock
    from cellcal.core.handeye.fixed_record import recorded_fixed_document
    from cellcal.devices.recording import SessionRecorder, read_recording

    text: str | None = None
    if args.replay:          # a replay recorded again: the recording's own configuration
        raw = read_recording(args.replay).config_document or {}
    else:
        text = read_config_text(args.config)[0]
        raw = tomllib.loads(text)
    document = recorded_fixed_document(raw, config.camera_name)
    stack.enter_context(OutputLock.for_file(args.record))
    return stack.enter_context(SessionRecorder(args.record, config_document=document, config_source=config.source,
                                               config_text=text))


def format_fixed(document: dict[str, Any]) -> str:
    """The terminal report of a fixed camera's result: its pose in the base frame with intervals (mm, degrees)."""
    t = document["camera_base"]["translation_m"]
    half = document["half_widths"]
    rpy, conf = document["camera_base_rpy_deg"], 100 * document["confidence"]
    lines = [f"camera {document['camera']!r} (fixed) in the base frame ({document.get('method', 'plate')} method), "
             f"{conf:g} % intervals:",
             "  translation " + ", ".join(f"{a} {1000 * v:+.2f} ± {1000 * half[f't{a}']:.2f} mm"
                                          for a, v in zip("xyz", t, strict=True)),
             "  roll/pitch/yaw " + ", ".join(f"{v:+.3f}" for v in rpy) + " deg; turn about the base axes ± "
             + ", ".join(f"{math.degrees(half[k]):.3f}" for k in ("rot_x", "rot_y", "rot_z")) + " deg",
             f"  plate in the flange: {document['plate']}; "
             f"chi2/dof {document['noise_model'].get('chi2_per_dof') or math.nan:.2f}"]
    lines += [f"  note: {n}" for n in document.get("notes", [])]
    return "\n".join(lines)
