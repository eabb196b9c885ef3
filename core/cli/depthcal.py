"""``cellcal depthcal``: drive the depth-calibration plan, fit the camera's systematic depth error, write
``DIR/depthcal.json``."""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path
from typing import Any

from cellcal.core.cli.argtypes import path_arg
from cellcal.core.cli.exits import EXIT_OK
from cellcal.core.cli.options import add_config_option, load_cell
from cellcal.core.cli.report import add_no_report_option
from cellcal.core.cli.resumable import resume_command, run_resumable

HELP = "calibrate the camera's systematic depth error from the plane and the arm's motion"


def register(sub: Any) -> None:
    """Add the ``depthcal`` subcommand."""
    p = sub.add_parser("depthcal", help=HELP,
                       description="Drive the arm through a plan of heights, inclinations and tool rolls over the "
                       "measuring plane, capture the camera's raw frames and fit its systematic depth error (stereo: "
                       "f*B scale, disparity offset, image field; ToF: range scale, offset, wiggling, image field) "
                       "jointly with the plane in the base frame, the arm's known motion fixing the scale. Views held "
                       "out of the fit give the error before and after. Writes DIR/depthcal.json (apply it with "
                       "[camera.correction] file = \"DIR/depthcal.json\") and DIR/depthcal-report.html.")
    add_config_option(p)
    p.add_argument("--out", metavar="DIR", default="cellcal-out", type=path_arg,
                   help="output directory (default: %(default)s); one run at a time")
    p.add_argument("--check", action="store_true",
                   help="validate the configuration and the plan and show what would connect to what; touch no "
                   "device")
    p.add_argument("--dry-run", action="store_true",
                   help="print every move of the plan with its safety checks and what it can observe; "
                   "connect and move nothing")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary; only the result path")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run from DIR/depthcal.json.journal.jsonl and DIR/depthcal.frames "
                   "(same configuration)")
    p.add_argument("--record", metavar="FILE.mcap", type=path_arg,
                   help="also record the session (config, frames, arm calls, result) to one MCAP file")
    p.add_argument("--replay", metavar="FILE.mcap", type=path_arg,
                   help="re-run a session recorded with --record from the file alone; says whether the result "
                   "is identical")
    add_no_report_option(p)
    p.set_defaults(func=run)


def _plan(config: Any) -> tuple[list[Any], Any]:
    """The checked plan and what it covers; a plan that cannot see a term is refused here (gate ``observability``)."""
    from cellcal.core.depthcal.plan import depthcal_plan, plan_coverage

    views = depthcal_plan(config)
    coverage = plan_coverage(config, views)
    coverage.check(len(views))
    return views, coverage


def _dry_run(config: Any, views: list[Any], coverage: Any) -> int:
    """Print every move with its checks and what the plan can see."""
    from cellcal.core.calibration.dryrun import check_moves, describe
    from cellcal.core.calibration.reach import arm_reach

    plan = config.plan
    limits = config.safety_limits()
    reach = arm_reach(config)
    poses = [v.pose for v in views]
    print(f"dry run of cellcal depthcal on {config.source}: {len(poses)} moves; arm class '{reach}'; "
          "no device is connected, nothing moves")
    for view, check in zip(views, check_moves(limits, poses, plan.speed_m_s, plan.acceleration_m_s2, reach=reach),
                           strict=True):
        print(f"{describe(check, len(poses), limits, plan.speed_m_s, plan.acceleration_m_s2, reach)} "
              f"[{view.label()}]")
    print(f"coverage: {coverage.message()}")
    print(f"dry run OK: all {len(poses)} moves inside the safety envelope and reachable")
    return EXIT_OK


def _check(args: argparse.Namespace, config: Any, views: list[Any], coverage: Any) -> int:
    """``--check``: the configuration, the devices it names and the plan; no device touched."""
    from cellcal.core.calibration.calibrator import build_devices
    from cellcal.core.cli.calibrate import _where
    from cellcal.core.depthcal.plan import depthcal_heights
    from cellcal.core.depthcal.run import raw_camera

    camera, arm = build_devices(config)
    raw = raw_camera(camera)
    dc = config.depthcal
    print(f"config:  {config.source} (cell '{config.cell.name}')")
    print(f"camera:  backend '{raw.backend_name}'{_where(raw)} ({type(raw).__module__}.{type(raw).__qualname__})"
          + ("; its [camera.correction] is not applied: depthcal fits the raw frames" if raw is not camera else ""))
    print(f"arm:     backend '{arm.inner.backend_name}'{_where(arm.inner)} "
          f"({type(arm.inner).__module__}.{type(arm.inner).__qualname__}), behind the safety envelope")
    heights = ", ".join(f"{h:.3f}" for h in depthcal_heights(config))
    print(f"plan:    {len(views)} poses x {dc.frames_per_pose} frames (heights {heights} m; inclinations "
          f"{', '.join(f'{i:g}' for i in dc.inclinations_deg)} deg); every pose inside the safety envelope and "
          "reachable")
    print(f"fit:     field orders 0-{dc.field_max_order}, every {dc.holdout_every}th view held out, at most "
          f"{dc.max_points_per_view} points a view")
    print(f"sees:    {coverage.message()}")
    print("config OK (no device was touched)")
    return EXIT_OK


def run(args: argparse.Namespace) -> int:
    """Run ``cellcal depthcal``; returns the exit status."""
    from cellcal.devices.errors import ConfigError

    if args.replay and args.config:
        raise ConfigError("--replay takes the configuration recorded in the file; drop --config")
    camera = arm = None
    if args.replay:
        from cellcal.core.calibration.replay import replay_session

        config, camera, arm = replay_session(args.replay)
    else:
        config = load_cell(args)
    views, coverage = _plan(config)  # every pose checked before anything connects
    if args.dry_run:
        return _dry_run(config, views, coverage)
    if args.check:
        return _check(args, config, views, coverage)
    return _run(args, config, camera, arm, views)


def _run(args: argparse.Namespace, config: Any, camera: Any, arm: Any, views: list[Any]) -> int:
    """The journaled plan run (with ``--record`` / ``--replay``), the fit, the summary and the report."""
    from cellcal.core.calibration.calibrator import build_devices
    from cellcal.core.calibration.replay import recorded_devices
    from cellcal.core.cli.progress import progress_factory
    from cellcal.core.depthcal.run import FRAMES_DIRNAME, DepthcalCalibrator, raw_camera

    corrected = False
    if not args.replay:
        camera, arm = build_devices(config)
        raw = raw_camera(camera)
        corrected, camera = raw is not camera, raw
    with contextlib.ExitStack() as stack:
        if args.record:
            from cellcal.core.cli.record import open_recorder

            recorder = open_recorder(stack, args.record, config, args.config)
            camera, arm = recorded_devices(recorder, camera, arm)
        calibrator = DepthcalCalibrator(config, camera, arm, views, Path(args.out) / FRAMES_DIRNAME,
                                        progress_factory("poses", "pose", args.quiet))
        outcome = _measure(args, calibrator)
        if isinstance(outcome, int):
            return outcome
        document, result, fitted = outcome
        if args.record:
            recorder.log_result(document)
    _finish(args, config, document, result, fitted, corrected)
    return EXIT_OK


def _measure(args: argparse.Namespace, calibrator: Any) -> Any:
    """Run the plan into ``DIR/depthcal.json``; (document, result, views), or the exit status of an interrupted run."""
    from cellcal.core.depthcal.run import DEPTHCAL_FILENAME, run_depthcal

    return run_resumable(lambda: run_depthcal(calibrator, args.out, resume=args.resume),
                         calibrator, len(calibrator.poses), Path(args.out) / DEPTHCAL_FILENAME,
                         resume_command("depthcal", args))


def _compare(path: str, document: dict[str, Any]) -> str:
    """One line saying whether ``document`` equals the depthcal result recorded in ``path`` exactly."""
    from cellcal.core.calibration.replay import exact_part
    from cellcal.devices.recording import read_recording

    recorded = read_recording(path).result
    if not recorded or not recorded.get("ok") or not isinstance(recorded.get("result"), dict):
        return "replay: the recording holds no successful result to compare with"
    want, got = exact_part(recorded["result"]), exact_part(document)
    if want == got:
        return f"replay: identical to the recorded result ({len(got.get('plan', []))} poses, the correction and " \
               "every figure)"
    keys = sorted(k for k in set(want) | set(got) if want.get(k) != got.get(k))
    return f"replay: DIFFERS from the recorded result: {', '.join(keys)}"


def _finish(args: argparse.Namespace, config: Any, document: dict[str, Any], result: Any, views: list[Any],
            corrected: bool) -> None:
    """The terminal summary, the replay's comparison and the report."""
    from cellcal.core.depthcal.report import format_summary
    from cellcal.core.depthcal.run import DEPTHCAL_FILENAME

    out = Path(args.out) / DEPTHCAL_FILENAME
    if not args.quiet:
        if corrected:
            print("note: the configured [camera.correction] was not applied; the fit is on the raw frames")
        print(format_summary(document, out))
    print(f"result written to {out}")
    if args.replay:
        print(_compare(args.replay, document))
    if not args.no_report:
        from cellcal.core.report.depthcal import write_report

        page = write_report(args.out, config, document, result, views)
        if page is not None and not args.quiet:
            print(f"report written to {page}")
