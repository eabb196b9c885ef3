"""The calibrator: drive the arm through the plan, capture, measure, report.

For every plan pose: move (through the safety wrapper), settle, capture
``frames_per_pose`` frames, read the arm's pose back, sample the P1-P9 grids and run
each configured method (:mod:`cellcal.core.measure`). When the reference plane and
the hand-eye transform are known, the expected angle, tilts and height follow from
the arm's reported pose, so every estimate gets an error, as in the paper's
Tables 3 and 4.

Devices come from the registry; this module never names a driver or a simulator.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from importlib.metadata import PackageNotFoundError, version
from typing import Any

import numpy as np

from cellcal.devices.arm import RobotArm
from cellcal.devices.base import BackendContext
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import CalibrationQualityError
from cellcal.devices.pose import Pose
from cellcal.devices.registry import Registry, default_registry
from cellcal.devices.safety import SafeArm
from cellcal.devices.types import Intrinsics

from .config import CellConfig, plan_flange_poses
from .measure import (
    FULL_FRAME,
    ExpectedGeometry,
    Measurement,
    expected_geometry,
    full_frame_document,
    measure_frames,
    measure_full_frame,
)
from .planes import Plane
from .report import RESULT_SCHEMA, summarize_poses

ProgressFactory = Callable[[int], Any]


@dataclass
class PoseRecord:
    """Everything measured at one plan pose.

    Attributes:
        index: 0-based index in the plan.
        commanded: Commanded flange pose, base frame.
        reported: Flange pose read back from the arm after the move, base frame.
        camera: Camera pose in the base frame (``reported @ mount``).
        expected: Geometry expected from the reference plane, or None without one.
        measurements: One per perimeter x grid method, plus one ``full_frame`` row.
        timings_s: Wall time of the move, settle, capture and compute steps, seconds
            (``compute_full_frame``: the part of ``compute`` spent on the full-frame fit).
        intrinsics: The lens model the frames were taken with.
        full_frame: The ``full_frame`` section (:func:`full_frame_document`), or None when
            the method is not run.
    """

    index: int
    commanded: Pose
    reported: Pose
    camera: Pose
    expected: ExpectedGeometry | None
    measurements: list[Measurement]
    timings_s: dict[str, float] = field(default_factory=dict)
    intrinsics: Intrinsics | None = None
    full_frame: dict[str, Any] | None = None

    def rows(self) -> list[dict[str, Any]]:
        """Flat rows (one per measurement) for the summary and the table."""
        out = []
        for m in self.measurements:
            row = {"pose_index": self.index, **m.to_dict()}
            if self.expected is not None:
                row["expected_angle_deg"] = float(np.degrees(self.expected.angle_rad))
            out.append(row)
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {
            "index": self.index,
            "commanded_flange_pose": self.commanded.to_dict(),
            "reported_flange_pose": self.reported.to_dict(),
            "camera_pose": self.camera.to_dict(),
            "expected": None if self.expected is None else self.expected.to_dict(),
            "measurements": self.rows(),
            "timings_s": dict(self.timings_s),
            "camera_intrinsics": None if self.intrinsics is None else self.intrinsics.to_dict(),
            "full_frame": self.full_frame,
        }


def build_devices(config: CellConfig, registry: Registry | None = None) -> tuple[Camera3D, SafeArm]:
    """Create the (unconnected) camera and the safety-wrapped arm of a configuration.

    Raises:
        ConfigError: If a backend is unknown or rejects its section.
    """
    registry = registry or default_registry()
    shared: dict[str, Any] = {}

    def ctx(section: str) -> BackendContext:
        return BackendContext(source=config.source, section=section, document=config.document,
                              shared=shared, seed=config.cell.seed)

    camera = registry.create_camera(config.camera_section, ctx("camera"))
    arm: RobotArm = registry.create_arm(config.arm_section, ctx("arm"))
    return camera, SafeArm(arm, config.safety_limits())


def _package_version() -> str:
    try:
        return version("cellcal")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree
        return "unknown"


class Calibrator:
    """Runs a configuration's plan on a camera and an arm.

    Args:
        config: The validated configuration.
        camera: A camera (connected or not; the calibrator connects it).
        arm: The arm, already wrapped in :class:`SafeArm`.
        progress: Optional factory ``total -> tqdm-like`` for a progress bar.
    """

    def __init__(self, config: CellConfig, camera: Camera3D, arm: SafeArm,
                 progress: ProgressFactory | None = None):
        self.config = config
        self.camera = camera
        self.arm = arm
        self.progress = progress
        self.poses: Sequence[Pose] = plan_flange_poses(config)

    def check_plan(self, start: Pose | None = None) -> None:
        """Check every move of the plan against the safety envelope (nothing moves).

        Raises:
            SafetyError: Naming the first offending pose.
        """
        plan = self.config.plan
        self.arm.limits.check_plan(start, self.poses, plan.speed_m_s, plan.acceleration_m_s2)

    def run(self) -> dict[str, Any]:
        """Run the whole plan and return the result document (not yet written).

        Raises:
            CellcalError: Any device, safety or calibration failure; the arm has been
                told to stop before the error propagates.
        """
        self.check_plan(None)
        started = time.perf_counter()
        created = datetime.now(UTC).isoformat(timespec="seconds")
        records: list[PoseRecord] = []
        with contextlib.ExitStack() as stack:
            stack.enter_context(self.arm)
            stack.enter_context(self.camera)
            t_connect = time.perf_counter() - started
            self.check_plan(self.arm.get_pose())
            bar = self.progress(len(self.poses)) if self.progress else None
            if bar is not None:
                stack.callback(bar.close)
            try:
                for i, target in enumerate(self.poses):
                    records.append(self._measure_pose(i, target))
                    if bar is not None:
                        bar.update(1)
            except BaseException:
                with contextlib.suppress(Exception):
                    self.arm.stop()
                raise
        total = time.perf_counter() - started
        return {
            "schema": RESULT_SCHEMA,
            "cellcal_version": _package_version(),
            "created_utc": created,
            "config_source": self.config.source,
            "config": dict(self.config.document),
            "mount": self.config.mount.pose().to_dict(),
            "poses": [rec.to_dict() for rec in records],
            "summary": summarize_poses([rec.to_dict() for rec in records], self._reference_plane()),
            "timings_s": {
                "total": total,
                "connect": t_connect,
                "per_pose": [rec.timings_s for rec in records],
            },
        }

    def _reference_plane(self) -> Plane | None:
        ref = self.config.reference
        return None if ref is None else Plane.from_point_normal(ref.plane_point_m, ref.plane_normal)

    def _measure_pose(self, index: int, target: Pose) -> PoseRecord:
        plan = self.config.plan
        t0 = time.perf_counter()
        self.arm.move_linear(target, speed=plan.speed_m_s, acceleration=plan.acceleration_m_s2,
                             timeout=plan.move_timeout_s)
        t1 = time.perf_counter()
        if plan.settle_s > 0:
            time.sleep(plan.settle_s)
        t2 = time.perf_counter()
        frames = [self.camera.capture(plan.capture_timeout_s) for _ in range(plan.frames_per_pose)]
        reported = self.arm.get_pose()
        t3 = time.perf_counter()
        camera_pose = reported @ self.config.mount.pose()
        expected = None
        if self.config.reference is not None:
            expected = expected_geometry(camera_pose, self.config.reference.plane_point_m,
                                         self.config.reference.plane_normal)
        fov = plan.nominal_fov_deg
        fov_rad = None if fov is None else (math.radians(fov[0]), math.radians(fov[1]))
        measurements = measure_frames(frames, perimeters_px=plan.perimeters_px, methods=plan.methods,
                                      window_px=plan.window_px, expected=expected, nominal_fov_rad=fov_rad)
        t_ff = time.perf_counter()
        full_frame = None
        if FULL_FRAME in plan.methods:
            try:
                row, result = measure_full_frame(frames, self.config.full_frame, expected=expected)
            except CalibrationQualityError as exc:
                extra = str(exc).partition("; ")[2]
                raise CalibrationQualityError(exc.gate, exc.value, exc.threshold,
                                              f"plan pose {index + 1}" + (f": {extra}" if extra else "")) from None
            measurements.append(row)
            full_frame = full_frame_document(result, camera_pose, expected)
        t4 = time.perf_counter()
        return PoseRecord(index, target, reported, camera_pose, expected, measurements,
                          {"move": t1 - t0, "settle": t2 - t1, "capture": t3 - t2, "compute": t4 - t3,
                           "compute_full_frame": t4 - t_ff},
                          frames[0].intrinsics, full_frame)
