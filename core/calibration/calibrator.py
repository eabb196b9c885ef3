"""The calibrator: drive the arm through the plan, capture, measure, report.

Per plan pose: move (through the safety wrapper), settle, capture, read the arm's pose
back and run each configured method (:mod:`cellcal.core.methods.measure`); with a
reference plane every estimate gets an error (the paper's Tables 3 and 4). Devices
come from the registry (:mod:`.build`): this module never names a driver or a simulator.
What one pose yields is a :class:`~cellcal.core.calibration.record.PoseRecord`.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import time
from collections.abc import Callable, Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol

from cellcal.core.calibration.build import build_camera, build_devices
from cellcal.core.calibration.config import CellConfig
from cellcal.core.calibration.journal import (
    JournalEntry,
    JournalWriter,
    journal_path,
    plan_fingerprint,
    read_journal,
    remove_journal,
)
from cellcal.core.calibration.outlock import OutputLock
from cellcal.core.calibration.plan_image import check_plan_image
from cellcal.core.calibration.reach import check_reach, reachable_plan_poses
from cellcal.core.calibration.record import PoseRecord
from cellcal.core.calibration.region import expected_plane, region_document, region_mask
from cellcal.core.calibration.report import RESULT_SCHEMA, summarize_poses, write_json_atomic
from cellcal.core.geometry.consistency import noise_plane_covariance
from cellcal.core.geometry.planes import Plane
from cellcal.core.geometry.view_follows import ViewFollowsArm, ViewSample
from cellcal.core.methods.fullframe import FullFrameResult, fit_full_frame
from cellcal.core.methods.measure import (
    FULL_FRAME,
    expected_geometry,
    full_frame_document,
    measure_frames,
    measure_full_frame,
)
from cellcal.devices.arm_model import ArmModel
from cellcal.devices.blocking import DeadlineGuard
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import (
    CalibrationError,
    CalibrationQualityError,
    CellcalError,
    VendorError,
)
from cellcal.devices.pose import Pose
from cellcal.devices.safety import SafeArm, format_pose
from cellcal.devices.types import Frame
from cellcal.devices.version import cellcal_version

__all__ = [
    "CLOSE_ALLOWANCE_S",
    "GUARD_GRACE_S",
    "STOP_TIMEOUT_S",
    "Calibrator",
    "PoseCompanion",
    "PoseObserver",
    "PoseRecord",
    "ProgressFactory",
    "build_camera",  # built in core.calibration.build; named here too for the many callers that import them here
    "build_devices",
    "poses_saved",
    "run_to_file",
]

ProgressFactory = Callable[[int], Any]
#: Called after each measured plan pose with its record, its frames and the full-frame fit (None
#: when the method is not run), e.g. to draw the scene live or write it to a bag (ADR 0020).
PoseObserver = Callable[["PoseRecord", Sequence[Frame], FullFrameResult | None], None]


class PoseCompanion(Protocol):
    """Other cameras that capture at each pose beside the driven one (ADR 0061; e.g. ``OtherCameras``).

    :meth:`begin` is called once the arm has settled at a pose, just before the driven camera captures; what
    it starts is collected by the observer, and :meth:`end` (after the pose, however it went) waits, bounded,
    for anything still running, so no capture outlives its pose.
    """

    def begin(self, index: int) -> None:
        """The arm is at rest at plan pose ``index`` (0-based): start the captures that run beside the driven one."""

    def end(self) -> None:
        """The pose is over: join what :meth:`begin` started (each within its deadline); never raises."""


#: Seconds the calibrator allows the arm's stop command when a run fails.
STOP_TIMEOUT_S = 1.0
#: Seconds a backend call may run beyond its own timeout before the run gives up on it (ADR 0022).
GUARD_GRACE_S = 2.0
#: Seconds a backend's close() may take (it has no timeout) before it is abandoned.
CLOSE_ALLOWANCE_S = 3.0


class Calibrator:
    """Runs a configuration's plan on a camera and an arm.

    Args:
        config: The validated configuration.
        camera: A camera (connected or not; the calibrator connects it).
        arm: The arm, already wrapped in :class:`SafeArm`.
        progress: Optional factory ``total -> tqdm-like`` for a progress bar.
        observer: Optional :data:`PoseObserver`, called after each measured pose.
        companion: Optional :class:`PoseCompanion`: started at each pose once the arm is at rest,
            before the driven camera captures (its results are the observer's to collect).
    """

    def __init__(self, config: CellConfig, camera: Camera3D, arm: SafeArm,
                 progress: ProgressFactory | None = None, observer: PoseObserver | None = None,
                 companion: PoseCompanion | None = None):
        self.config = config
        self.camera = camera
        self.arm = arm
        self.progress = progress
        self.observer = observer
        self.companion = companion
        self.poses: Sequence[Pose] = reachable_plan_poses(config)  # generated views moved within the arm's reach
        #: Every backend call runs under one of these: a backend that ignores its timeout ends the run.
        self.guards = {"camera": DeadlineGuard(f"camera backend '{camera.backend_name}'", GUARD_GRACE_S),
                       "arm": DeadlineGuard(f"arm backend '{arm.backend_name}'", GUARD_GRACE_S)}
        #: The journal writer of the last :meth:`run` (None without a journal).
        self.journal_writer: JournalWriter | None = None
        #: Whether the camera's view follows the arm, fed each pose measured by the last :meth:`run` (ADR 0045).
        self.view_check: ViewFollowsArm | None = None

    def check_plan(self, start: Pose | None = None) -> None:
        """Check every move of the plan against the safety envelope (nothing moves).

        Raises:
            SafetyError: Naming the first offending pose.
        """
        plan = self.config.plan
        check_reach(self.config, self.poses)  # names the pose an arm of this class cannot take
        self.arm.limits.check_plan(start, self.poses, plan.speed_m_s, plan.acceleration_m_s2)

    def run(self, *, journal: str | Path | None = None, resume: bool = False) -> dict[str, Any]:
        """Run the plan and return the result document (not yet written).

        Args:
            journal: Resume journal to append each measured pose to (see
                :mod:`cellcal.core.calibration.journal`); None keeps no journal.
            resume: Continue the run recorded in ``journal``: its poses are taken from
                it (no move, no capture), the rest are measured.

        Raises:
            ConfigError: When resuming, if the journal was written for another
                configuration or plan.
            SafetyError: If a move of the plan leaves the envelope (before any move).
            VendorError: If the arm reports an error before the first move or after a pose.
            CellcalError: Any other device or calibration failure. Once the arm is
                connected, any failure (and KeyboardInterrupt) tells it to stop first.
        """
        self.check_plan(None)
        fingerprint = plan_fingerprint(self.config.document, self.poses)
        done = self._journal_entries(journal, fingerprint) if resume else []
        he = self.config.handeye  # the arm's read-back noise, as the hand-eye fit states it
        self.view_check = ViewFollowsArm(self.config.mount.pose(), arm_translation_sigma_m=he.arm_translation_sigma_m,
                                         arm_rotation_sigma_rad=math.radians(he.arm_rotation_sigma_deg))
        self.journal_writer = None if journal is None else JournalWriter(journal, fingerprint, len(self.poses),
                                                                         append=resume, resumed=len(done))
        started = time.perf_counter()
        created = datetime.now(UTC).isoformat(timespec="seconds")
        measured: dict[int, tuple[PoseRecord, dict[str, Any]]] = {
            e.index: (PoseRecord.from_dict(e.pose), e.pose) for e in done}
        todo = [i for i in range(len(self.poses)) if i not in measured]
        connect_s = 0.0
        if todo:
            connect_s = self._measure_poses(todo, measured, done[-1].device_state if done else None, started)
        total_s = time.perf_counter() - started
        resumed = sorted(e.index for e in done) if resume else None
        return self._result_document(measured, created, total_s, connect_s, resumed)

    def _journal_entries(self, journal: str | Path | None, fingerprint: str) -> list[JournalEntry]:
        """The poses of the interrupted run recorded in ``journal`` (those inside this plan)."""
        if journal is None:
            raise CalibrationError("resuming needs the journal of the interrupted run")
        return [e for e in read_journal(journal, fingerprint) if 0 <= e.index < len(self.poses)]

    def _measure_poses(self, todo: Sequence[int], measured: dict[int, tuple[PoseRecord, dict[str, Any]]],
                       device_state: Mapping[str, Any] | None, started: float) -> float:
        """Connect, check the moves left, measure the ``todo`` poses into ``measured``, close.

        Args:
            todo: 0-based plan indices still to measure, ascending.
            measured: Filled with ``index -> (record, its result-document entry)``.
            device_state: Device state to restore first (the last journal entry's), or None.
            started: ``time.perf_counter()`` at the start of the run, seconds.

        Returns:
            Seconds from ``started`` until both devices were connected.
        """
        with contextlib.ExitStack() as stack:
            try:
                self._connect(stack, "arm", self.arm)
                self._connect(stack, "camera", self.camera)
                connect_s = time.perf_counter() - started
                self._check_image()
                self._check_arm_ready("before the first move")
                self._check_moves(self._flange_pose(), todo)
                if device_state is not None:
                    self._restore_device_state(device_state)
                bar = self.progress(len(todo)) if self.progress else None
                if bar is not None:
                    stack.callback(bar.close)
                for i in todo:
                    try:
                        measured[i] = self._measure_and_journal(i)
                    finally:  # the companion's captures end with their pose, whatever happened
                        if self.companion is not None:
                            self.companion.end()
                    if bar is not None:
                        bar.update(1)
            except BaseException:
                self._stop_arm()
                raise
        return connect_s

    def _measure_and_journal(self, index: int) -> tuple[PoseRecord, dict[str, Any]]:
        """Measure plan pose ``index``, check the arm is still fine, append the pose to the journal."""
        record = self._measure_pose(index, self.poses[index])
        self._check_arm_ready(f"after plan pose {index + 1}")
        data = record.to_dict()
        if self.journal_writer is not None:
            self.journal_writer.append(index, data, self._device_state())
        return record, data

    def _stop_arm(self) -> None:
        """After a failure: tell a connected arm to stop (bounded by :data:`STOP_TIMEOUT_S`), ignoring errors."""
        if self.arm.connected:
            t = min(STOP_TIMEOUT_S, self.arm.default_timeout_s)
            with contextlib.suppress(Exception):
                self.guards["arm"].call(lambda: self.arm.stop(t), t, f"stop(timeout={t:g} s)")

    def _connect(self, stack: contextlib.ExitStack, kind: str, device: Camera3D | SafeArm) -> None:
        """Connect ``device`` under its guard; ``stack`` closes it (bounded) when it unwinds."""
        connect_guarded(stack, self.guards[kind], device)

    def _check_image(self) -> None:
        """Before the first move: the camera's image must hold the plan's grid (ConfigError naming the perimeters)."""
        t = self.camera.default_timeout_s  # a driver whose intrinsics travel with the frames captures one
        check_plan_image(self.config, self.guards["camera"].call(lambda: self.camera.intrinsics, t, "intrinsics"))

    def _flange_pose(self) -> Pose:
        """The arm's reported flange pose, under the arm's guard."""
        t = self.arm.default_timeout_s
        return self.guards["arm"].call(lambda: self.arm.get_pose(t), t, f"get_pose(timeout={t:g} s)")

    def _result_document(self, measured: Mapping[int, tuple[PoseRecord, dict[str, Any]]], created: str,
                         total_s: float, connect_s: float, resumed: list[int] | None) -> dict[str, Any]:
        """The result document (schema :data:`RESULT_SCHEMA`) of the measured poses, in plan order.

        Args:
            measured: ``index -> (record, its result-document entry)``.
            created: Start of the run, ISO 8601 UTC.
            total_s: Wall time of the run, seconds.
            connect_s: Wall time until the devices were connected, seconds.
            resumed: Indices taken from the journal (a resumed run), else None.
        """
        records = [measured[i][0] for i in sorted(measured)]
        poses = [measured[i][1] for i in sorted(measured)]
        return {
            "schema": RESULT_SCHEMA,
            "cellcal_version": cellcal_version(),
            "created_utc": created,
            "config_source": self.config.source,
            "config": dict(self.config.document),
            "mount": self.config.mount.pose().to_dict(),
            "poses": poses,
            "summary": summarize_poses(poses, self._reference_plane(), arm=self._arm_model()),
            "timings_s": {
                "total": total_s,
                "connect": connect_s,
                "per_pose": [rec.timings_s for rec in records],
            },
            **({"resumed_poses": resumed} if resumed is not None else {}),
        }

    def _arm_model(self) -> ArmModel | None:
        """The arm's stated model for the error budget (None when the backend states none; ADR 0059)."""
        stated = getattr(self.arm, "arm_model", None)
        model = stated() if callable(stated) else None
        return model if isinstance(model, ArmModel) else None

    def _check_arm_ready(self, when: str) -> None:
        """Raise VendorError if the arm reports an error (e.g. a protective stop)."""
        t = self.arm.default_timeout_s
        status = self.guards["arm"].call(lambda: self.arm.status(t), t, f"status(timeout={t:g} s)")
        if status.error_code:
            raise VendorError(self.arm.backend_name, status.error_code,
                              f"{status.message or 'controller error'} ({when}; clear the arm's error first)")

    def _check_moves(self, start: Pose, indices: Sequence[int]) -> None:
        """Check the moves still to make, from ``start`` through ``indices`` (0-based, ascending) in order."""
        plan = self.config.plan
        previous = start
        for _, run in itertools.groupby(enumerate(indices), key=lambda pair: pair[1] - pair[0]):
            block = [i for _, i in run]  # consecutive plan indices, so the messages number them right
            targets = [self.poses[i] for i in block]
            self.arm.limits.check_plan(previous, targets, plan.speed_m_s, plan.acceleration_m_s2,
                                       first_index=block[0] + 1)
            previous = targets[-1]

    def _devices_for_state(self) -> dict[str, Any]:
        return {"camera": self.camera, "arm": self.arm.inner}

    def _device_state(self) -> dict[str, Any]:
        """What the devices save for a resume (simulated devices: their noise streams)."""
        out: dict[str, Any] = {}
        for name, device in self._devices_for_state().items():
            get = getattr(device, "resume_state", None)
            if callable(get):
                out[name] = get()
        return out

    def _restore_device_state(self, state: Mapping[str, Any]) -> None:
        for name, device in self._devices_for_state().items():
            restore = getattr(device, "restore_resume_state", None)
            if callable(restore) and state.get(name) is not None:
                restore(state[name])

    def _reference_plane(self) -> Plane | None:
        ref = self.config.reference
        return None if ref is None else Plane.from_point_normal(ref.plane_point_m, ref.plane_normal)

    def _move_and_capture(self, index: int, target: Pose, n_frames: int
                          ) -> tuple[list[Frame], Pose, dict[str, float]]:
        """Move to plan pose ``index`` (the safety wrapper confirms the arrival), settle, capture, read back.

        Returns:
            The ``n_frames`` frames, the flange pose the arm reports after them (base frame) and the
            seconds each step took (``move``, ``settle``, ``capture``).
        """
        plan = self.config.plan
        t0 = time.perf_counter()
        try:
            self.guards["arm"].call(lambda: self.arm.move_linear(target, speed=plan.speed_m_s,
                                                                 acceleration=plan.acceleration_m_s2,
                                                                 timeout=plan.move_timeout_s),
                                    plan.move_timeout_s, f"move_linear(timeout={plan.move_timeout_s:g} s)")
        except VendorError as exc:  # e.g. a kinematic refusal: say which pose and where
            raise VendorError(exc.vendor, exc.code, f"{exc.meaning} at plan pose {index + 1} "
                              f"({format_pose(target)})") from None
        t1 = time.perf_counter()
        if plan.settle_s > 0:
            time.sleep(plan.settle_s)
        t2 = time.perf_counter()
        if self.companion is not None:  # the other cameras start with the driven one, the arm at rest
            self.companion.begin(index)
        t_cap = plan.capture_timeout_s
        frames = [self.guards["camera"].call(lambda: self.camera.capture(t_cap), t_cap,
                                             f"capture(timeout={t_cap:g} s)") for _ in range(n_frames)]
        reported = self._flange_pose()
        return frames, reported, {"move": t1 - t0, "settle": t2 - t1, "capture": time.perf_counter() - t2}

    def _measure_pose(self, index: int, target: Pose) -> PoseRecord:
        plan = self.config.plan
        frames, reported, timings = self._move_and_capture(index, target, plan.frames_per_pose)
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
        result: FullFrameResult | None = None
        if FULL_FRAME in plan.methods:
            # where the fit looks at this pose: the [region] mask and [reference] seen from the camera
            try:
                region = region_mask(self.config.region, frames[0].intrinsics, camera_pose, source=self.config.source)
            except CalibrationError as exc:
                raise CalibrationError(f"plan pose {index + 1}: {exc}") from None
            search = expected_plane(self.config.search_reference, expected)
            try:
                row, result = measure_full_frame(frames, self.config.full_frame, expected=expected, region=region,
                                                 expected_plane=search)
            except CalibrationQualityError as exc:
                self._check_view(index, reported, frames, None)  # a camera off the arm is the cause to name
                extra = str(exc).partition("; ")[2]
                raise CalibrationQualityError(exc.gate, exc.value, exc.threshold,
                                              f"plan pose {index + 1}" + (f": {extra}" if extra else ""),
                                              unit=exc.unit) from None
            measurements.append(row)
            full_frame = full_frame_document(result, camera_pose, expected, expected_plane=search)
            full_frame["region"] = region_document(self.config.region, region)
        self._check_view(index, reported, frames, result)
        t4 = time.perf_counter()
        record = PoseRecord(index, target, reported, camera_pose, expected, measurements,
                            {**timings, "compute": t4 - t3, "compute_full_frame": t4 - t_ff},
                            frames[0].intrinsics, full_frame)
        if self.observer is not None:
            self.observer(record, frames, result)
        return record

    def _check_view(self, index: int, flange: Pose, frames: Sequence[Frame], fit: FullFrameResult | None) -> None:
        """Feed this pose's plane (fitted here if the method is not run) to :attr:`view_check` (ADR 0045).

        Raises:
            CalibrationQualityError: Gate ``view_follows_arm``; the resume journal is dropped (poses of a
                camera that is not on the arm are no start for a run on the corrected rig).
        """
        if self.view_check is None or self.view_check.decided is not None:
            return  # decided at an earlier pose: no plane to fit for it
        if fit is None:
            try:
                fit = fit_full_frame(list(frames), self.config.full_frame)
            except CalibrationError:
                return  # no plane in the frame: nothing to compare
        # the noise alone: a camera that does not follow the arm sees the same systematic error in every frame
        # (ADR 0055, "Poses combined"); the allowance as if independent per pose would hide it
        cov = noise_plane_covariance(fit)
        try:
            self.view_check.add(ViewSample(str(index + 1), flange, fit.plane.normal, fit.plane.offset_m, cov))
        except CalibrationQualityError:
            writer, self.journal_writer = self.journal_writer, None
            if writer is not None and writer.saved:
                remove_journal(writer.path)
            raise


def connect_guarded(stack: contextlib.ExitStack, guard: DeadlineGuard, device: Camera3D | SafeArm) -> None:
    """Connect ``device`` under ``guard``; ``stack`` closes it (bounded) when it unwinds, a failed connect too."""
    stack.callback(close_guarded, guard, device)
    t = device.connect_timeout_s  # an emulated arm's includes starting its emulator process
    guard.call(lambda: device.connect(t), t, f"connect(timeout={t:g} s)")


def close_guarded(guard: DeadlineGuard, device: Camera3D | SafeArm) -> None:
    """Close ``device``, abandoning a close() that hangs (it has no timeout; failing here would hide the cause)."""
    with contextlib.suppress(CellcalError):
        guard.call(device.close, CLOSE_ALLOWANCE_S - guard.grace_s, "close()")


def run_to_file(calibrator: Calibrator, out: str | Path, *, resume: bool = False) -> dict[str, Any]:
    """Run with a resume journal beside ``out``, write the result atomically, drop the journal.

    The output directory is locked for the whole run (:class:`OutputLock`): a second run
    on it is refused. On failure an earlier ``out`` is untouched; the journal stays (if
    any pose was measured) so ``resume=True`` can continue the run.

    Raises:
        CellcalError, KeyboardInterrupt: As :meth:`Calibrator.run`; OutputError if another
            run holds the directory, or the journal or result cannot be written.
    """
    out = Path(out)
    journal = journal_path(out)
    with OutputLock.for_directory(out.parent):
        document = calibrator.run(journal=journal, resume=resume)
        write_json_atomic(out, document)
        remove_journal(journal)
    return document


def poses_saved(calibrator: Calibrator) -> int:
    """Poses the current run has in its journal (after a failure: what --resume would skip).

    Counted by the run itself (resumed + appended), so the journal of an earlier run that
    this one has not replaced yet is not counted.
    """
    writer = calibrator.journal_writer
    return 0 if writer is None else writer.saved
