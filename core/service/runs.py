"""A run of the service: its record (state, progress, result), its cancellation and the three kinds it can run.

A run calls the commands' own library functions (``run_to_file``, ``run_handeye``,
``run_depthcal``: the same output lock, journal and safety envelope as ``cellcal calibrate``,
``handeye`` and ``depthcal``) in a worker thread. Cancelling sets a flag that the run's
progress display checks at its safe points (the start of the plan, after each pose); there it
raises :class:`RunCancelled`, a ``BaseException`` the calibrator treats as it treats Ctrl-C:
it tells the arm to stop, closes the devices and leaves the journal (the poses measured so
far) and any earlier result file as they were. No move starts after a cancel is seen.
"""

from __future__ import annotations

import threading
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from cellcal.devices.errors import ConfigError

__all__ = ["KINDS", "STATES", "Outcome", "Progress", "Run", "RunCancelled", "RunOptions", "execute", "plan_size"]

#: The kinds of run the service starts.
KINDS = ("calibrate", "handeye", "depthcal")
#: A run's states, in the order they can come; the last three are final.
STATES = ("queued", "running", "ok", "failed", "cancelled")


class RunCancelled(BaseException):
    """Raised in a run's thread at a safe point once the run is cancelled (handled like Ctrl-C: the arm is stopped)."""


@dataclass(frozen=True)
class RunOptions:
    """What a run may be asked besides its kind and camera.

    Attributes:
        report: Write the run's report (``report.html`` or ``depthcal-report.html``) beside its result.
        resume: Continue the interrupted (or cancelled) run of this kind from its journal.
        plan: ``handeye`` only: ``auto`` (inclinations x rolls of ``[handeye]``) or ``config`` (the ``[plan]``).
    """

    report: bool = True
    resume: bool = False
    plan: str = "auto"

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> RunOptions:
        """From a request's ``options`` object.

        Raises:
            ConfigError: An unknown option or a value of the wrong type.
        """
        data = dict(data or {})
        unknown = sorted(set(data) - {"report", "resume", "plan"})
        if unknown:
            raise ConfigError(f"unknown run option {unknown[0]!r} (known: plan, report, resume)")
        for key in ("report", "resume"):
            if key in data and not isinstance(data[key], bool):
                raise ConfigError(f"run option {key!r} must be true or false")
        if data.get("plan", "auto") not in ("auto", "config"):
            raise ConfigError("run option 'plan' must be 'auto' or 'config'")
        return cls(**data)


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


@dataclass(eq=False)
class Run:
    """One run: what was asked, where it stands, what it gave. Changed by its worker; read by anyone (under ``lock``).

    Attributes:
        id: Its identifier.
        cell, camera, kind: What runs where.
        options: Its options.
        out_dir: The camera's output directory it writes into.
        state: One of :data:`STATES`.
        poses_done, poses_total: Progress of the plan (poses measured, including resumed ones; 0 total until known).
        error: The one-line reason of a failed run.
        result: The result document of a run that ended ``ok``.
        result_file, report_file: Where the result and the report were written (None: not written).
        cancel_requested: Whether a cancel was asked (a run past its last move still ends ``ok``).
        history_id: Its number in the service's history store (None: no history kept, or not written).
    """

    cell: str
    camera: str
    kind: str
    options: RunOptions
    out_dir: Path
    id: str = field(default_factory=lambda: uuid.uuid4().hex[:16])
    state: str = "queued"
    poses_done: int = 0
    poses_total: int = 0
    error: str | None = None
    result: dict[str, Any] | None = None
    result_file: Path | None = None
    report_file: Path | None = None
    cancel_requested: bool = False
    history_id: int | None = None
    created_utc: str = field(default_factory=_now)
    started_utc: str | None = None
    finished_utc: str | None = None
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    done: threading.Event = field(default_factory=threading.Event, repr=False)

    @property
    def final(self) -> bool:
        """Whether the run has ended (ok, failed or cancelled)."""
        return self.state in STATES[2:]

    def to_dict(self) -> dict[str, Any]:
        """JSON form (without the result document)."""
        with self.lock:
            return {"id": self.id, "cell": self.cell, "camera": self.camera, "kind": self.kind,
                    "options": {"report": self.options.report, "resume": self.options.resume,
                                "plan": self.options.plan},
                    "state": self.state, "progress": {"poses_done": self.poses_done, "poses_total": self.poses_total},
                    "error": self.error, "cancel_requested": self.cancel_requested,
                    "result_file": None if self.result_file is None else str(self.result_file),
                    "report_file": None if self.report_file is None else str(self.report_file),
                    "created_utc": self.created_utc, "started_utc": self.started_utc,
                    "finished_utc": self.finished_utc}


class Progress:
    """The tqdm-like display the calibrator drives (``update`` after each pose), reporting to the run; the safe
    point where a cancel is seen.

    Args:
        run: The run.
        total: Poses this run measures (the plan less any resumed poses).
        changed: Called (on the run's thread) after each change of the progress.
    """

    def __init__(self, run: Run, total: int, changed: Callable[[Run], None]) -> None:
        self.run = run
        self.changed = changed
        with run.lock:
            run.poses_done = max(0, run.poses_total - total)  # resumed poses count as done
        self._check()
        changed(run)

    def _check(self) -> None:
        if self.run.cancel_requested:
            raise RunCancelled

    def update(self, n: int = 1) -> None:
        """``n`` more poses measured; raises :class:`RunCancelled` if the run was cancelled meanwhile."""
        with self.run.lock:
            self.run.poses_done += n
        self.changed(self.run)
        self._check()

    def close(self) -> None:
        """Nothing to clear."""


Builder = Callable[[Any], tuple[Any, Any]]


def _report_failure(report: Any, exc: Exception, poses: Any = None) -> None:
    """Write the report of a run that failed at run time (not bad input); never raises."""
    from cellcal.devices.errors import CellcalError, OutputError

    if report is None or isinstance(exc, (ConfigError, OutputError)) or not isinstance(exc, CellcalError):
        return
    line = f"cellcal: error: {exc}".replace("\n", " ")
    if poses is not None:
        report.failed_run(exc, line, poses)
    else:
        report.failed(exc, line)
    report.write(quiet=True)


def _calibrate(config: Any, out: Path, options: RunOptions, build: Builder, progress: Any) -> tuple[Any, Any, Any]:
    from cellcal.core.calibration.calibrator import Calibrator, run_to_file
    from cellcal.core.calibration.report import RESULT_FILENAME

    camera, arm = build(config)
    report = None
    if options.report:
        from cellcal.core.report.runs import CalibrationReport

        report = CalibrationReport(config, camera, out)
    calibrator = Calibrator(config, camera if report is None else report.camera, arm,  # type: ignore[arg-type]
                            progress=progress,
                            observer=None if report is None else report.observer())
    try:
        document = run_to_file(calibrator, out / RESULT_FILENAME, resume=options.resume)
    except Exception as exc:
        _report_failure(report, exc, calibrator.poses)
        raise
    if report is not None:
        report.finished(document)
    return document, out / RESULT_FILENAME, None if report is None else report.write(quiet=True)


def _handeye(config: Any, out: Path, options: RunOptions, build: Builder, progress: Any) -> tuple[Any, Any, Any]:
    from cellcal.core.handeye.plan import plan_poses
    from cellcal.core.handeye.result import HANDEYE_FILENAME
    from cellcal.core.handeye.run import check_observability, plan_calibrator, run_handeye

    poses = plan_poses(config, options.plan)
    check_observability(config, poses)  # an unobservable plan is refused before anything moves
    report = None
    if options.report:
        from cellcal.core.report.runs import RunReport, camera_name

        report = RunReport("handeye", out, camera_name(config), config.source)
    camera, arm = build(config)
    calibrator = plan_calibrator(config, camera, arm, poses, progress)
    try:
        document = run_handeye(calibrator, out, plan_kind=options.plan, resume=options.resume)
    except Exception as exc:
        _report_failure(report, exc)
        raise
    if report is not None:
        report.section["result"] = document
    return document, out / HANDEYE_FILENAME, None if report is None else report.write(quiet=True)


def _depthcal(config: Any, out: Path, options: RunOptions, build: Builder, progress: Any) -> tuple[Any, Any, Any]:
    from cellcal.core.depthcal.plan import depthcal_plan, plan_coverage
    from cellcal.core.depthcal.run import (
        DEPTHCAL_FILENAME,
        FRAMES_DIRNAME,
        DepthcalCalibrator,
        raw_camera,
        run_depthcal,
    )

    views = depthcal_plan(config)
    plan_coverage(config, views).check(len(views))  # a plan that cannot see a term is refused before any move
    camera, arm = build(config)
    calibrator = DepthcalCalibrator(config, raw_camera(camera), arm, views, out / FRAMES_DIRNAME, progress)
    document, result, fitted = run_depthcal(calibrator, out, resume=options.resume)
    page = None
    if options.report:
        from cellcal.core.report.depthcal import write_report

        page = write_report(out, config, document, result, fitted)
    return document, out / DEPTHCAL_FILENAME, page


_KIND_FUNCTIONS = {"calibrate": _calibrate, "handeye": _handeye, "depthcal": _depthcal}


def plan_size(kind: str, config: Any, options: RunOptions) -> int:
    """Poses in the plan of a run of ``kind`` (0 if it cannot be told before the run)."""
    from cellcal.devices.errors import CellcalError

    try:
        if kind == "calibrate":
            from cellcal.core.calibration.reach import reachable_plan_poses

            return len(reachable_plan_poses(config))
        if kind == "handeye":
            from cellcal.core.handeye.plan import plan_poses

            return len(plan_poses(config, options.plan))
        from cellcal.core.depthcal.plan import depthcal_plan

        return len(depthcal_plan(config))
    except CellcalError:
        return 0  # the run itself says why


@dataclass(frozen=True)
class Outcome:
    """How a run ended, before anyone is told (see ``settle`` of :func:`execute`).

    Attributes:
        state: ``ok``, ``failed`` or ``cancelled``.
        error: The one-line reason of a run that did not end ``ok``.
        result: The result document of a run that ended ``ok``.
        result_file, report_file: Where its result and report were written.
        finished_utc: When it ended (ISO 8601).
    """

    state: str
    error: str | None = None
    result: dict[str, Any] | None = None
    result_file: Path | None = None
    report_file: Path | None = None
    finished_utc: str = field(default_factory=_now)


def _outcome(run: Run, config: Any, build: Builder, changed: Callable[[Run], None]) -> Outcome:
    """Run the kind's library function to its end; how it ended (never raises)."""
    from cellcal.devices.errors import CellcalError

    try:
        def progress(total: int) -> Progress:
            return Progress(run, total, changed)

        document, result_file, page = _KIND_FUNCTIONS[run.kind](config, run.out_dir, run.options, build, progress)
    except RunCancelled:
        return Outcome("cancelled", "cancelled: the arm was told to stop; poses measured so far are in the journal "
                       "(options.resume continues the run)")
    except CellcalError as exc:
        return Outcome("failed", str(exc).replace("\n", " "))
    except Exception as exc:  # a bug: the run fails with one line, the service stays up
        return Outcome("failed", f"internal error: {type(exc).__name__}: {exc}".replace("\n", " "))
    return Outcome("ok", result=document, result_file=Path(result_file), report_file=page)


def execute(run: Run, config: Any, build: Builder, changed: Callable[[Run], None],
            settle: Callable[[Run, Outcome], None] | None = None) -> None:
    """Run ``run`` to its end on this thread: its state, result or error set, ``changed`` called on each change.

    Never raises: a failure is the run's ``failed`` state with its one-line error; a cancel its
    ``cancelled`` state (the arm told to stop by the calibrator).

    Args:
        run: The run (``queued``).
        config: The camera's configuration.
        build: ``config -> (camera, SafeArm)``.
        changed: Called after each change of the run (its state, its progress).
        settle: Called with the outcome before the run shows it (its history written, the cell freed),
            so whoever sees the run ended also sees what followed; it must not raise.
    """
    with run.lock:
        run.state, run.started_utc = "running", _now()
        run.poses_total = plan_size(run.kind, config, run.options)
    changed(run)
    outcome = _outcome(run, config, build, changed)
    if settle is not None:
        settle(run, outcome)
    with run.lock:
        run.state, run.error, run.finished_utc = outcome.state, outcome.error, outcome.finished_utc
        if outcome.state == "ok":
            run.result, run.result_file, run.report_file = outcome.result, outcome.result_file, outcome.report_file
    run.done.set()
    changed(run)
