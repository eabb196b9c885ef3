"""``--method charuco|both`` for a fixed camera: a ChArUco board the gripper holds, OpenCV's eye-to-hand solvers.

The arm shows the fixed camera the board (printed on the ``[plate]``'s face; the ``[handeye]
charuco_*`` board) at the plate plan's poses. Eye-to-hand is the flange camera's AX = XB with the
flange poses inverted: given ``T_flange_base`` for OpenCV's gripper-to-base, ``cv2.calibrateHandEye``
returns ``T_base_camera`` for its camera-to-gripper, and each view's board mapped through it,
``F_i⁻¹ X B_i``, is the board in the flange frame, the same at every view: its spread is the
residual (:func:`~cellcal.core.handeye.charuco_run.charuco_estimates`, reused as it is). The
covariance is the best method's leave-one-out, a turn about the base axes and a shift along them as
the plate fit's. ``both`` fits the plate's plane on the same frames and compares the two poses
against their combined 1-sigma (ADR 0018, ADR 0061). No journal: the board views are not journaled.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from cellcal.core.calibration.config import CellConfig
from cellcal.core.calibration.outlock import OutputLock
from cellcal.core.calibration.report import write_json_atomic
from cellcal.core.handeye.charuco import BoardView, detect_board
from cellcal.core.handeye.charuco_run import BoardWatcher, board_spec, charuco_estimates, charuco_section, compare
from cellcal.core.handeye.estimator import rpy_with_sigma_deg
from cellcal.core.handeye.fixed_plan import FIXED_PARAMETERS
from cellcal.core.handeye.fixed_run import (
    FIXED_SCHEMA,
    FixedCalibrator,
    fixed_filename,
    plate_document,
)
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import CalibrationQualityError
from cellcal.devices.pose import Pose
from cellcal.devices.safety import SafeArm
from cellcal.devices.version import cellcal_version

__all__ = ["board_document", "fixed_board_estimates", "run_fixed_board"]

#: 95 % two-sided normal quantile for the board's intervals (its covariance is a jackknife's, not scaled).
Z_95 = 1.959963984540054


def fixed_board_estimates(flanges: Sequence[Pose], views: Sequence[BoardView | None]) -> dict[str, Any]:
    """Every OpenCV method's ``T_base_camera`` (key ``mount``, as for the flange) from the views with the board.

    Raises:
        CalibrationQualityError: As :func:`~cellcal.core.handeye.charuco_run.charuco_estimates` (gates
            ``charuco_views``, ``motion``, ``charuco_methods``).
    """
    return charuco_estimates([f.inv() for f in flanges], views)   # eye-to-hand: T_flange_base for gripper-to-base


def _board_pose_section(config: CellConfig, found: dict[str, Any]) -> dict[str, Any]:
    """The best method's camera pose as the plate fit states its own: steps from the configured pose, intervals."""
    best: Pose = found["methods"][found["best"]]["mount"]
    cov = np.asarray(found["covariance"], dtype=np.float64)
    configured = config.camera_entry.pose_base
    assert configured is not None                                # a fixed camera's run
    turn = (best.rotation * configured.rotation.inv()).as_rotvec()  # about the base axes, rad
    rpy, sigma = rpy_with_sigma_deg(best, cov[:3, :3])
    return {"camera_base": best.to_dict(), "parameters": list(FIXED_PARAMETERS[:6]),
            "steps": [*map(float, turn), *map(float, best.translation - configured.translation)],
            "covariance": cov.tolist(), "confidence": 0.95, "interval_z": Z_95,
            "half_widths": {k: float(Z_95 * np.sqrt(max(cov[i, i], 0.0))) for i, k in enumerate(FIXED_PARAMETERS[:6])},
            "camera_base_rpy_deg": [float(v) for v in rpy], "camera_base_rpy_sigma_deg": [float(v) for v in sigma]}


def board_document(config: CellConfig, calibrator: FixedCalibrator, measured: dict[str, Any],
                   views: Sequence[BoardView | None], method: str) -> dict[str, Any]:
    """The ``handeye-NAME.json`` of ``--method charuco`` (the board's pose) or ``both`` (the plate's, compared).

    Raises:
        CalibrationQualityError: As :func:`fixed_board_estimates` (too few views with the board: what to check
            said), or the plate fit's refusals with ``both``.
    """
    flanges = [Pose.from_dict(p["reported_flange_pose"]) for p in measured["poses"]]
    try:
        found = fixed_board_estimates(flanges, views)
    except CalibrationQualityError as exc:
        if exc.gate != "charuco_views":
            raise
        raise CalibrationQualityError(exc.gate, exc.value, exc.threshold, f"{str(exc).partition('; ')[2]}; "
                                      f"{_missing_board(config)}", unit=exc.unit) from None
    section = charuco_section(found, views)
    board = _board_pose_section(config, found)
    line = (f"charuco (eye-to-hand): board in {len(found['used'])}/{len(views)} poses; " + ", ".join(
        f"{k} {1000 * r['residual_rms_m']:.2f} mm" for k, r in found["methods"].items())
        + f" (RMS spread of the board in the flange); best {found['best']}")
    if method == "charuco":
        entry = config.camera_entry
        assert entry.pose_base is not None
        return {"schema": FIXED_SCHEMA, "cellcal_version": cellcal_version(),
                "created_utc": datetime.now(UTC).isoformat(timespec="seconds"), "config_source": config.source,
                "method": "charuco", "camera": config.camera_name, "on": "base", **board,
                "plate": "not fitted (board method)", "noise_model": {}, "observability": {},
                "configured_camera_base": entry.pose_base.to_dict(),
                "commanded_flange_poses": [p.to_dict() for p in calibrator.poses],
                "reported_flange_poses": [p["reported_flange_pose"] for p in measured["poses"]],
                "left_out": list(calibrator.left_out), "charuco": section, "notes": [line]}
    document = plate_document(calibrator, measured, method="both")
    plane_pose = Pose.from_dict(document["camera_base"])
    cmp = compare(plane_pose, np.asarray(document["covariance"]), Pose.from_dict(board["camera_base"]),
                  np.asarray(board["covariance"]))
    cmp["rotation_deg_about_base_xyz"] = cmp.pop("rotation_deg_about_flange_xyz")   # a turn on the left: base axes
    verdict = "agree" if cmp["agree_95"] else "DISAGREE"
    document |= {"charuco": section | {"camera_base": board}, "comparison": cmp,
                 "notes": [*document["notes"], line,
                           f"plate - charuco ({found['best']}): translation "
                           + ", ".join(f"{1000 * v:+.3f}" for v in cmp["translation_m"]) + " mm, turn "
                           + ", ".join(f"{v:+.4f}" for v in cmp["rotation_deg_about_base_xyz"]) + " deg = "
                           + ", ".join(f"{v:+.1f}" for v in cmp["in_sigmas"]) + f" combined sigmas; {verdict} at 95 %"]}
    return document


def _missing_board(config: CellConfig) -> str:
    """What to check when the board was found in too few views of a fixed camera (one clause)."""
    from cellcal.core.handeye.board_config import sim_board

    spec = board_spec(config)
    what = f"{spec.squares[0]}x{spec.squares[1]} squares of {1000 * spec.square_m:g} mm, DICT_{spec.dictionary}"
    board = sim_board(config)
    if config.camera_section.get("backend") == "sim" and (board is None or board.get("on") != "plate"):
        return (f"the simulated fixed camera sees a board only with [sim.charuco] on = \"plate\" (printed on the "
                f"held [sim.plate]; the detector looks for {what})")
    return (f"the detector looks for {what} ([handeye] charuco_*): is that board, printed at 100 %, flat on the plate "
            "the gripper holds, and inside the camera's view?")


def run_fixed_board(config: CellConfig, camera: Camera3D, arm: SafeArm, poses: Sequence[Pose], out_dir: str | Path,
                    *, method: str, progress: Callable[[int], Any] | None = None, left_out: Sequence[str] = ()
                    ) -> dict[str, Any]:
    """Show the board at the plate plan's poses, estimate, write ``DIR/handeye-NAME.json`` atomically.

    Raises:
        ConfigError: The ``[sim.charuco]`` board differs from ``[handeye]``'s (before anything moves).
        CellcalError, KeyboardInterrupt: As :meth:`Calibrator.run`; CalibrationQualityError as :func:`board_document`.
    """
    spec = board_spec(config)
    watcher = BoardWatcher(camera, spec)
    calibrator = FixedCalibrator(config, watcher, arm, poses, progress, left_out=left_out)
    out = Path(out_dir) / fixed_filename(config.camera_name)
    with OutputLock.for_directory(out.parent):
        measured = calibrator.run()
        per_pose = config.plan.frames_per_pose
        frames = watcher.frames[-len(measured["poses"]) * per_pose:]      # the table's view comes first: not these
        views = [detect_board(frame, spec) for frame in frames[::per_pose]]
        document = board_document(config, calibrator, measured, views, method)
        write_json_atomic(out, document)
    return document
