"""``--method charuco|both``: the plan measured once, the mount by the board and by the plane, compared.

A :class:`BoardWatcher` wraps the camera and finds the board in every captured frame
while the calibrator measures the planes, so both methods use the same poses and
frames. The ChArUco estimate is the OpenCV method whose boards agree best in the base
frame (smallest RMS residual); every method's result is reported. ``both`` compares
the plane and board estimates against their combined uncertainty (ADR 0018).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from cellcal.core.calibration.calibrator import Calibrator, build_devices
from cellcal.core.calibration.config import CellConfig
from cellcal.core.calibration.outlock import OutputLock
from cellcal.core.calibration.report import write_json_atomic
from cellcal.core.handeye.charuco import (
    METHODS,
    BoardSpec,
    BoardView,
    board_residuals,
    check_motion,
    detect_board,
    hand_eye,
    jackknife_covariance,
)
from cellcal.core.handeye.result import HANDEYE_FILENAME, handeye_document, plane_sections
from cellcal.core.handeye.run import check_observability, estimate_from_document, mount_covariance, plan_calibrator
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import CalibrationError, CalibrationQualityError
from cellcal.devices.forwarding import ForwardingCamera
from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame
from cellcal.devices.version import cellcal_version

#: Fewest views with a board pose the hand-eye solvers need.
MIN_VIEWS = 3


#: Most frames a :class:`BoardWatcher` keeps (a plan has at most 1000 poses).
MAX_FRAMES = 1000


class BoardWatcher(ForwardingCamera):
    """A camera that keeps every frame it passes on, to look for the ChArUco board after the run.

    The search runs after the run (:meth:`views`), outside the capture's time budget.
    """

    def __init__(self, inner: Camera3D, spec: BoardSpec) -> None:
        super().__init__(inner)
        self.spec = spec
        self.frames: list[Frame] = []

    def _capture(self, timeout: float) -> Frame:
        frame = self.inner.capture(timeout)
        if len(self.frames) >= MAX_FRAMES:
            raise CalibrationError(f"more than {MAX_FRAMES} frames for one hand-eye run")
        self.frames.append(frame)
        return frame

    def views(self, every: int = 1) -> list[BoardView | None]:
        """Per ``every``-th captured frame, the board seen (None where it was not found)."""
        return [detect_board(frame, self.spec) for frame in self.frames[::every]]


def board_spec(config: CellConfig) -> BoardSpec:
    """The board of ``[handeye] charuco_*`` (a differing ``[sim.charuco]`` refused: :mod:`.board_config`)."""
    from cellcal.core.handeye.board_config import board_spec as checked_spec

    return checked_spec(config)


def charuco_estimates(flanges: Sequence[Pose], views: Sequence[BoardView | None]) -> dict[str, Any]:
    """Every OpenCV method's mount from the views where the board was found, and the best method's covariance.

    Raises:
        CalibrationQualityError: Gate ``charuco_views`` (fewer than :data:`MIN_VIEWS` views with the
            board), ``motion`` (the views do not turn about two axes) or ``charuco_methods`` (every
            OpenCV method failed).
    """
    used = [i for i, v in enumerate(views) if v is not None]
    if len(used) < MIN_VIEWS:
        raise CalibrationQualityError("charuco_views", len(used), MIN_VIEWS,
                                      f"the ChArUco board was found in {len(used)} of {len(views)} poses")
    a = [flanges[i] for i in used]
    b = [views[i].board_in_camera for i in used]  # type: ignore[union-attr]
    check_motion(a)  # too little rotation fails every method the same way: say so once
    methods: dict[str, Any] = {}
    failed: dict[str, str] = {}
    for name in METHODS:
        try:
            mount = hand_eye(a, b, name)
        except CalibrationError as exc:  # one solver failing on these motions leaves the others
            failed[name] = str(exc)
            continue
        res = board_residuals(mount, a, b)
        methods[name] = {"mount": mount, "residual_rms_deg": float(np.sqrt(np.mean([r[0] ** 2 for r in res]))),
                         "residual_rms_m": float(np.sqrt(np.mean([r[1] ** 2 for r in res]))), "residuals": res}
    if not methods:
        raise CalibrationQualityError("charuco_methods", 0, 1, "every calibrateHandEye method failed: "
                                      + "; ".join(failed.values()))
    best = min(methods, key=lambda k: methods[k]["residual_rms_m"])  # the boards agree best in the base frame
    return {"used": used, "methods": methods, "failed": failed, "best": best,
            "covariance": jackknife_covariance(a, b, best, methods[best]["mount"])}


def charuco_section(found: dict[str, Any], views: Sequence[BoardView | None]) -> dict[str, Any]:
    """The document's ``charuco`` entry: every method's mount and residuals, the views."""
    return {"best_method": found["best"], "views_used": found["used"], "failed_methods": found["failed"],
            "views": [None if v is None else {"corners": v.corners, "reprojection_px": v.reprojection_px,
                                              "board_in_camera": v.board_in_camera.to_dict()} for v in views],
            "methods": {name: {"translation_m": r["mount"].translation.tolist(),
                               "rpy_deg": np.degrees(r["mount"].as_xyz_rpy()[3:]).tolist(),
                               "residual_rms_deg": r["residual_rms_deg"], "residual_rms_m": r["residual_rms_m"],
                               "per_pose": [{"deg": d, "m": m} for d, m in r["residuals"]]}
                        for name, r in found["methods"].items()}}


def compare(plane: Pose, plane_cov: np.ndarray, board: Pose, board_cov: np.ndarray) -> dict[str, Any]:
    """Plane minus board estimate per axis against the combined 1-sigma (turn about flange axes, translation)."""
    turn = (plane.rotation * board.rotation.inv()).as_rotvec()  # about the flange axes, rad
    diff = np.concatenate([turn, plane.translation - board.translation])
    sigma = np.sqrt(np.diag(plane_cov) + np.diag(board_cov))
    return {"rotation_deg_about_flange_xyz": np.degrees(diff[:3]).tolist(), "translation_m": diff[3:].tolist(),
            "combined_sigma_rotation_deg": np.degrees(sigma[:3]).tolist(), "combined_sigma_translation_m":
            sigma[3:].tolist(), "in_sigmas": (diff / sigma).tolist(),
            "agree_95": bool(np.all(np.abs(diff / sigma) <= 1.96))}


def measure_with_board(config: CellConfig, poses: Sequence[Pose], progress: Callable[[int], Any] | None = None
                       ) -> tuple[dict[str, Any], list[BoardView | None]]:
    """Measure the plan's planes with a board watcher on the camera; the result document and the views per pose.

    No resume journal: the board views are not journaled, so a resumed run could not use them.
    """
    camera, arm = build_devices(config)
    watcher = BoardWatcher(camera, board_spec(config))
    calibrator: Calibrator = plan_calibrator(config, watcher, arm, poses, progress)
    measured = calibrator.run()
    per_pose = config.plan.frames_per_pose
    return measured, watcher.views(every=per_pose)  # the first frame of each pose


def charuco_document(config: CellConfig, method: str, plan_kind: str, measured: dict[str, Any],
                     views: Sequence[BoardView | None]) -> dict[str, Any]:
    """The ``handeye.json`` of ``--method charuco`` or ``both``."""
    flanges = [Pose.from_dict(p["reported_flange_pose"]) for p in measured["poses"]]
    try:
        found = charuco_estimates(flanges, views)
    except CalibrationQualityError as exc:
        if exc.gate != "charuco_views":
            raise
        from cellcal.core.handeye.board_config import missing_board_hint

        raise CalibrationQualityError(exc.gate, exc.value, exc.threshold, f"{str(exc).partition('; ')[2]}; "
                                      f"{missing_board_hint(config)}", unit=exc.unit) from None
    best = found["methods"][found["best"]]["mount"]
    header = {"cellcal_version": cellcal_version(), "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
              "config_source": config.source, "plan": plan_kind, "method": method}
    sections: dict[str, Any] = {"charuco": charuco_section(found, views)}
    lines = [f"charuco: board in {len(found['used'])}/{len(views)} poses; " + ", ".join(
        f"{k} {1000 * r['residual_rms_m']:.2f} mm" for k, r in found["methods"].items())
        + f" (RMS board residual); best {found['best']}"]
    if method == "charuco":
        return {**handeye_document(best, found["covariance"], config.handeye.confidence, config.mount.pose(),
                                   header=header, sections=sections), "report_lines": lines}
    plane = estimate_from_document(config, measured)
    cmp = compare(plane.mount, mount_covariance(plane), best, found["covariance"])
    sections |= plane_sections(plane, flanges) | {"comparison": cmp}
    lines.append(f"plane - charuco ({found['best']}): rotation {_fmt(cmp['rotation_deg_about_flange_xyz'], 4)} deg, "
                 f"translation {_fmt([1000 * v for v in cmp['translation_m']], 3)} mm = "
                 f"{_fmt(cmp['in_sigmas'], 1)} combined sigmas; {'agree' if cmp['agree_95'] else 'DISAGREE'} at 95 %")
    return {**handeye_document(plane.mount, mount_covariance(plane), plane.confidence, config.mount.pose(),
                               header=header, sections=sections, z=plane.z, interval_scale=plane.interval_scale),
            "report_lines": lines}


def _fmt(values: Sequence[float], digits: int) -> str:
    return "[" + ", ".join(f"{v:+.{digits}f}" for v in values) + "]"


def run_charuco(config: CellConfig, poses: Sequence[Pose], out_dir: str | Path, *, method: str, plan_kind: str,
                progress: Callable[[int], Any] | None = None) -> dict[str, Any]:
    """``--method charuco|both``: measure with the board watcher, estimate, write ``DIR/handeye.json`` atomically.

    Raises:
        CellcalError, KeyboardInterrupt: As :meth:`Calibrator.run`; CalibrationQualityError as
            :func:`charuco_estimates`.
    """
    out = Path(out_dir) / HANDEYE_FILENAME
    board_spec(config)  # a board the camera does not show is refused before anything moves
    with OutputLock.for_directory(out.parent):
        measured, views = measure_with_board(config, poses, progress)
        document = charuco_document(config, method, plan_kind, measured, views)
        write_json_atomic(out, document)
    return document


def compare_methods(configs: Sequence[CellConfig], truth: Callable[[CellConfig], Pose]) -> str:
    """The benchmark table: plane method vs every OpenCV method, same poses, mean errors over ``configs``."""
    from cellcal.core.handeye.plan import auto_plan

    errors: dict[str, list[np.ndarray]] = {}
    failures: dict[str, int] = {}
    for config in configs:
        poses = auto_plan(config)
        check_observability(config, poses)
        measured, views = measure_with_board(config, poses)
        flanges = [Pose.from_dict(p["reported_flange_pose"]) for p in measured["poses"]]
        found = charuco_estimates(flanges, views)
        results = {"plane (cellcal)": estimate_from_document(config, measured).mount}
        results |= {f"OpenCV {k}": r["mount"] for k, r in found["methods"].items()}
        for k in found["failed"]:
            failures[f"OpenCV {k}"] = failures.get(f"OpenCV {k}", 0) + 1
        true = truth(config)
        for name, mount in results.items():
            rot = math.degrees(float(np.linalg.norm((true.inv() @ mount).rotation.as_rotvec())))
            errors.setdefault(name, []).append(np.concatenate([[rot], 1000 * np.abs(mount.translation
                                                                                   - true.translation)]))
    n = len(configs)
    rows = [f"{n} simulated runs x {len(poses)} poses, the same frames for every method; mean (max) error",
            "| method | rotation ° | x mm | y mm | z mm |", "|---|---|---|---|---|"]
    for name, errs in errors.items():
        e = np.asarray(errs)
        rows.append(f"| {name} | " + " | ".join(f"{e[:, k].mean():.4f} ({e[:, k].max():.4f})" if k == 0
                                                 else f"{e[:, k].mean():.3f} ({e[:, k].max():.3f})"
                                                 for k in range(4)) + " |")
    rows += [f"| {name} | failed in {k} of {n} runs | | | |" for name, k in failures.items()]
    return "\n".join(rows)


__all__ = ["BoardWatcher", "board_spec", "charuco_document", "charuco_estimates", "compare", "compare_methods",
           "measure_with_board", "run_charuco"]
