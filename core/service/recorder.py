"""What the service keeps of what happens: its history (runs, applied calibrations, events) and its metrics.

A :class:`Recorder` is told of each run's start and end by the cell that runs it, and sees every
event published on an :class:`ObservedBus` (without a subscription of its own: the bus's
subscriber count stays the clients'). Runs are written on the run's own thread; events go
through a bounded queue to one writer thread, so a publisher never waits for the database. A
history write that fails is logged, counted (``cellcal_history_failures_total``) and published
as a ``history.failed`` event (at most one per :data:`FAILURE_EVENT_EVERY_S`); it never fails a
run nor a request.

In the store a camera is named ``<cell>/<camera>`` (one store may keep a fleet's cells), an event
without a camera ``<cell>``, one without a cell :data:`SERVICE_NAME`.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cellcal.core.calibration.outlock import OutputLock
from cellcal.core.service.events import DEFAULT_QUEUE_EVENTS, Event, EventBus
from cellcal.core.service.history import HistoryStore, NewCalibration
from cellcal.devices.errors import CellcalError, OutputError
from cellcal.devices.jsonsafe import json_safe

if TYPE_CHECKING:
    from cellcal.core.service.calibration import CameraCalibration
    from cellcal.core.service.metrics import ServiceMetrics
    from cellcal.core.service.runs import Outcome, Run

__all__ = ["ABANDONED", "FAILURE_EVENT_EVERY_S", "MAX_EVENT_DETAIL_BYTES", "MAX_QUEUED_EVENTS", "SERVICE_NAME",
           "ObservedBus", "Recorder", "abandon_stale_runs", "applied_calibrations", "history_camera"]

log = logging.getLogger(__name__)

#: Largest event detail kept in the history, bytes of JSON; a larger one is kept as its size and keys.
MAX_EVENT_DETAIL_BYTES = 16 << 10
#: Events waiting for the history writer; beyond, new ones are dropped and counted.
MAX_QUEUED_EVENTS = 10_000
#: Seconds between two ``history.failed`` events (the failures between are counted, not published).
FAILURE_EVENT_EVERY_S = 10.0
#: The store's camera name of an event that names no cell.
SERVICE_NAME = "service"
#: Why a run the history still had ``running`` at start-up was marked failed.
ABANDONED = "the service stopped before the run ended (found running when the service started)"
#: Events not written to the history: the history's own failures (they would feed themselves).
_NOT_RECORDED = frozenset({"history.failed"})


def history_camera(cell: str, camera: str | None = None) -> str:
    """The store's name of ``camera`` of ``cell``: ``<cell>/<camera>`` (``<cell>`` alone without a camera)."""
    return cell if not camera else f"{cell}/{camera}"


class ObservedBus(EventBus):
    """An :class:`EventBus` that also hands every event to its observers, on the publisher's thread.

    Observers must be quick and must not publish; an observer that raises is logged and skipped.
    """

    def __init__(self, queue_events: int = DEFAULT_QUEUE_EVENTS) -> None:
        super().__init__(queue_events)
        self._observers: list[Callable[[Event], None]] = []

    def observe(self, observer: Callable[[Event], None]) -> None:
        """Call ``observer(event)`` for every event published from now on."""
        self._observers.append(observer)

    def publish(self, type_: str, data: Mapping[str, Any] | None = None) -> Event:
        """Send the event to every subscriber, then to every observer; the event."""
        event = super().publish(type_, data)
        for observer in list(self._observers):
            try:
                observer(event)
            except Exception as exc:  # an observer's bug never reaches the publisher (a run's thread)
                log.error("event observer failed on %s: %s: %s", type_, type(exc).__name__, exc)
        return event


def abandon_stale_runs(history: HistoryStore, cell: str, cameras: Sequence[str], directory: Path) -> int:
    """Mark failed the runs of ``cell`` the history still has ``running`` (left by a service that crashed).

    Only while no other process holds the cell's lock ``directory/.cellcal.lock`` (its runs are alive);
    runs of other cells in a shared store are never touched (unlike :meth:`HistoryStore.abandon_running`).

    Returns:
        How many runs were marked.
    """
    lock = OutputLock.for_directory(directory)
    try:
        lock.acquire()
    except OutputError:
        return 0  # another process runs on this cell: its runs are not stale
    try:
        marked = 0
        for camera in cameras:
            for record in history.list_runs(camera=history_camera(cell, camera), status="running",
                                            limit=500).items:
                history.finish_run(record.id, "failed", reason=ABANDONED)
                marked += 1
        return marked
    finally:
        lock.release()


def _iso(text: str | None) -> datetime | None:
    try:
        return None if not text else datetime.fromisoformat(text)
    except ValueError:
        return None


def applied_calibrations(cell: str, camera: str, calibration: CameraCalibration) -> list[NewCalibration]:
    """The history records of a calibration put into use: its mount and its base-frame plane.

    The mount (``T_flange_camera``: ``translation_m``, ``quaternion_xyzw``, ``rotvec_rad``) has the 6x6
    covariance of its turn about the flange axes (rad) and its shift (m) when it was estimated; the plane
    (``frame: base``, ``normal``, ``offset_m`` with ``normal . x + offset_m = 0``, ``anchor_m``) has the
    3x3 covariance of its two tilts (rad) and its height at the anchor (m). Both name the file they came from.
    """
    model = calibration.model
    source = {"kind": calibration.kind, "file": str(calibration.path), "created_utc": calibration.created_utc}
    cov = model.covariance
    mount = {**model.mount.to_dict(), "estimated": calibration.estimated_mount, "source": source}
    plane = {"frame": "base", "normal": [float(x) for x in model.plane.normal], "offset_m": float(model.plane.offset_m),
             "anchor_m": model.anchor_m.tolist(), "source": source}
    key = history_camera(cell, camera)
    return [NewCalibration(key, "mount", mount, cov[:6, :6].tolist() if calibration.estimated_mount else None),
            NewCalibration(key, "plane", plane, cov[6:, 6:].tolist())]


def _detail(data: Mapping[str, Any]) -> Any:
    """An event's data as kept in the history: itself, or its size and keys when over the bound."""
    safe = json_safe(dict(data))
    size = len(json.dumps(safe, allow_nan=False, default=str).encode("utf-8"))
    if size <= MAX_EVENT_DETAIL_BYTES:
        return safe
    return {"truncated": True, "bytes": size, "keys": sorted(str(k) for k in data)[:50]}


class Recorder:
    """Writes the service's history and feeds its metrics (either may be None).

    Args:
        bus: The service's bus (its events are recorded when it is an :class:`ObservedBus`).
        history: The store (None: no history kept).
        metrics: The metrics (None: prometheus-client is not installed).
    """

    def __init__(self, bus: EventBus, history: HistoryStore | None, metrics: ServiceMetrics | None) -> None:
        self.bus = bus
        self.history = history
        self.metrics = metrics
        #: Events dropped because the writer fell :data:`MAX_QUEUED_EVENTS` behind.
        self.dropped = 0
        self._queue: queue.Queue[Event | None] = queue.Queue(MAX_QUEUED_EVENTS)
        self._last_failure_event = -FAILURE_EVENT_EVERY_S
        self._writer: threading.Thread | None = None
        if history is not None:
            self._writer = threading.Thread(target=self._write_events, name="cellcal-history", daemon=True)
            self._writer.start()
        if isinstance(bus, ObservedBus):
            bus.observe(self._observe)
        elif history is not None or metrics is not None:
            log.warning("the service's bus is not an ObservedBus: its events are neither recorded nor counted")

    # --- failures -------------------------------------------------------------------------------

    def _failed(self, what: str, exc: BaseException) -> None:
        """A history write failed: logged, counted, published (rate-limited); never raised."""
        line = f"history: cannot record {what}: {exc}".replace("\n", " ")
        log.warning("%s", line)
        if self.metrics is not None:
            self.metrics.history_failures.inc()
        now = time.monotonic()
        if now - self._last_failure_event >= FAILURE_EVENT_EVERY_S:
            self._last_failure_event = now
            self.bus.publish("history.failed", {"message": line})

    def _guarded(self, what: str, write: Callable[[], Any]) -> Any:
        try:
            return write()
        except (CellcalError, OSError) as exc:
            self._failed(what, exc)
        except Exception as exc:  # a driver's own error (psycopg, sqlite3) that the store did not wrap
            self._failed(what, exc)
        return None

    # --- runs -----------------------------------------------------------------------------------

    def run_started(self, run: Run, source: str) -> None:
        """A run began (on its own thread): counted, and written as ``running`` (its ``history_id`` set)."""
        if self.metrics is not None:
            self.metrics.run_started(run.cell)
        history = self.history
        if history is None:
            return
        run.history_id = self._guarded(f"the start of run {run.id}", lambda: history.start_run(
            run.kind, history_camera(run.cell, run.camera), source[:4096], started=run.created_utc))

    def run_ended(self, run: Run, outcome: Outcome, calibration: CameraCalibration | None) -> None:
        """A run ended (before it shows it): counted, and written with its result or reason, and with the
        calibration it put into use (one transaction)."""
        started, ended = _iso(run.started_utc), _iso(outcome.finished_utc)
        if self.metrics is not None:
            duration = (ended - started).total_seconds() if started is not None and ended is not None else None
            self.metrics.run_ended(run.cell, run.camera, run.kind, outcome.state, duration, outcome.result)
        history, history_id = self.history, run.history_id
        if history is None or history_id is None:
            return
        applied = [] if calibration is None else applied_calibrations(run.cell, run.camera, calibration)

        def finish() -> None:
            try:
                history.finish_run(history_id, outcome.state, result=outcome.result, reason=outcome.error,
                                   ended=outcome.finished_utc, applied=applied)
            except OutputError as exc:  # e.g. a result over the store's size bound: kept by reference
                if outcome.result is None:
                    raise
                note = {"result_file": str(outcome.result_file), "not_stored": str(exc)}
                history.finish_run(history_id, outcome.state, result=note, reason=outcome.error,
                                   ended=outcome.finished_utc, applied=applied)

        self._guarded(f"the end of run {run.id}", finish)

    def calibration_seen(self, cell: str, camera: str, calibration: CameraCalibration) -> None:
        """A calibration the service now uses that no run of its own made (a command's, or one found at
        start-up): recorded as applied now, unless it is the one the store has in use already."""
        history = self.history
        if history is None:
            return

        def record() -> None:
            items = applied_calibrations(cell, camera, calibration)
            latest = history.calibration_at(items[0].camera, "mount", datetime.now(UTC))
            if latest is not None and isinstance(latest.value, Mapping) and \
                    latest.value.get("source") == items[0].value["source"]:
                return  # the one in use already (recorded by its run, or before a restart)
            for item in items:
                history.record_applied(item.camera, item.what, item.value, covariance=item.covariance)

        self._guarded(f"the calibration of {cell}/{camera}", record)

    # --- events ---------------------------------------------------------------------------------

    def _observe(self, event: Event) -> None:
        if self.metrics is not None:
            self.metrics.event(event.type, event.data)
        if self.history is None or event.type in _NOT_RECORDED:
            return
        try:
            self._queue.put_nowait(event)
        except queue.Full:
            self.dropped += 1  # the writer is far behind (a slow database): the newest are not kept

    def _write_events(self) -> None:
        history = self.history
        assert history is not None
        while True:
            event = self._queue.get()
            try:
                if event is None:
                    return
                cell, camera = event.data.get("cell"), event.data.get("camera")
                name = history_camera(cell, camera if isinstance(camera, str) else None) \
                    if isinstance(cell, str) and cell else SERVICE_NAME
                self._record_event(history, name, event)
            finally:
                self._queue.task_done()

    def _record_event(self, history: HistoryStore, name: str, event: Event) -> None:
        self._guarded(f"event {event.type}", lambda: history.record_event(
            name, event.type[:200], detail=_detail(event.data), at=datetime.fromtimestamp(event.time_s, UTC)))

    def flush(self, timeout_s: float = 10.0) -> bool:
        """Wait until the events queued so far are written (at most ``timeout_s``); whether they were."""
        deadline = time.monotonic() + timeout_s
        while self._writer is not None and self._queue.unfinished_tasks and time.monotonic() < deadline:
            time.sleep(0.01)
        return self._writer is None or not self._queue.unfinished_tasks

    def close(self, timeout_s: float = 10.0) -> None:
        """Write what is queued (at most ``timeout_s``), stop the writer, close the store. Idempotent."""
        if self._writer is not None:
            try:
                self._queue.put(None, timeout=timeout_s)
            except queue.Full:
                log.warning("history: the writer is stuck; %d events not written", self._queue.qsize())
            self._writer.join(timeout_s)
            self._writer = None
        if self.history is not None:
            self.history.close()
