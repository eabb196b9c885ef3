"""``cellcal handeye --camera NAME`` for a fixed camera (``on = "base"``): the plate plan, its fit, the result file."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from cellcal.core.cli.exits import EXIT_OK
from cellcal.core.cli.resumable import resume_command, run_resumable
from cellcal.core.console import say


def run_fixed(args: argparse.Namespace, config: Any) -> int:
    """Run the fixed camera's calibration; returns the exit status (dry run: every move and what the plan sees).

    Raises:
        ConfigError: An option the fixed camera's run does not take (one line).
        CellcalError: As the run.
    """
    from cellcal.core.handeye.fixed_run import check_fixed_plan, fixed_plan
    from cellcal.devices.errors import ConfigError

    if args.method != "plane" or args.record or args.plan != "auto":
        raise ConfigError(f"camera {config.camera_name!r} is fixed: its calibration shows it the [plate] "
                          "(--method plane, --plan auto; --record/--replay not yet)")
    poses, dropped = fixed_plan(config)
    if dropped:
        say(f"note: {len(dropped)} of {len(poses) + len(dropped)} plate poses left out (envelope or reach); "
            f"first: {dropped[0]}")
    seen = check_fixed_plan(config, poses)           # an unobservable plan is refused before anything moves
    if args.dry_run:
        return _dry_run(config, poses, seen)
    return _run(args, config, poses)


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


def _run(args: argparse.Namespace, config: Any, poses: list[Any]) -> int:
    from cellcal.core.calibration.build import build_cell
    from cellcal.core.cli.progress import progress_factory
    from cellcal.core.handeye.fixed_run import FixedCalibrator, fixed_filename, run_fixed_handeye

    cameras, arm = build_cell(config)
    calibrator = FixedCalibrator(config, cameras[config.camera_name], arm, poses,
                                 progress_factory("poses", "pose", args.quiet))
    out = Path(args.out) / fixed_filename(config.camera_name)
    document = run_resumable(lambda: run_fixed_handeye(calibrator, args.out, resume=args.resume),
                             calibrator, len(poses), out, resume_command("handeye", args))
    if isinstance(document, int):
        return document
    if not args.quiet:
        print(format_fixed(document))
    print(f"result written to {out}")
    return EXIT_OK


def format_fixed(document: dict[str, Any]) -> str:
    """The terminal report of a fixed camera's result: its pose in the base frame with intervals (mm, degrees)."""
    t = document["camera_base"]["translation_m"]
    half = document["half_widths"]
    rpy, conf = document["camera_base_rpy_deg"], 100 * document["confidence"]
    lines = [f"camera {document['camera']!r} (fixed) in the base frame, {conf:g} % intervals:",
             "  translation " + ", ".join(f"{a} {1000 * v:+.2f} ± {1000 * half[f't{a}']:.2f} mm"
                                          for a, v in zip("xyz", t, strict=True)),
             "  roll/pitch/yaw " + ", ".join(f"{v:+.3f}" for v in rpy) + " deg; turn about the base axes ± "
             + ", ".join(f"{math.degrees(half[k]):.3f}" for k in ("rot_x", "rot_y", "rot_z")) + " deg",
             f"  plate in the flange: {document['plate']}; "
             f"chi2/dof {document['noise_model'].get('chi2_per_dof') or math.nan:.2f}"]
    lines += [f"  note: {n}" for n in document.get("notes", [])]
    return "\n".join(lines)
