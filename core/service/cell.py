"""The service core over one or several cells: runs one at a time per cell, their cancellation, the current
calibration per camera and ``pixel_to_base``, its history and metrics (:mod:`.recorder`). Every face (HTTP,
XML-RPC) is a thin adapter over :class:`Service`.

Each camera's runs write into ``OUT/<cell>/<camera>/`` (``result.json``, ``handeye.json``,
``depthcal.json``, their reports). A run holds the cell's lock ``OUT/<cell>/.cellcal.lock``
(:class:`OutputLock`, as the commands' own) from its start to its end, so a second run on the
cell, from this service or another, is refused; the run itself takes the camera directory's
lock as the command does.
"""

from __future__ import annotations

import contextlib
import logging
import re
import threading
import time
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cellcal.core.calibration.config import CellConfig, load_every_camera
from cellcal.core.calibration.outlock import OutputLock
from cellcal.core.service.calibration import CameraCalibration, read_calibration
from cellcal.core.service.errors import BusyError, NotFoundError, RequestError
from cellcal.core.service.events import EventBus
from cellcal.core.service.history import HistoryStore
from cellcal.core.service.planepoint import MAX_PIXELS, pixel_to_base, quaternion_matrix
from cellcal.core.service.recorder import ObservedBus, Recorder, abandon_stale_runs
from cellcal.core.service.runs import KINDS, Builder, Outcome, Run, RunOptions, execute
from cellcal.core.service.watch import Watches
from cellcal.devices.errors import CellcalError, ConfigError, OutputError
from cellcal.devices.version import cellcal_version

__all__ = ["MAX_RUNS_KEPT", "CellService", "PixelsOnPlane", "Service"]

#: Finished runs the service remembers (the oldest are forgotten first).
MAX_RUNS_KEPT = 200
#: Seconds :meth:`Service.close` waits for a cancelled run to stop the arm and end.
CLOSE_WAIT_S = 60.0
#: Seconds a camera's result files are not looked at again (another process's run is seen within this).
RECHECK_S = 1.0
#: A cell or camera name usable as a directory name and in a URL.
NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}")

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PixelsOnPlane:
    """What ``pixel_to_base`` answers: points (N, 3) in the base frame and their 1-sigma per base axis (N, 3), m."""

    points_m: np.ndarray
    sigma_m: np.ndarray
    calibration: CameraCalibration


def _default_build(config: CellConfig) -> tuple[Any, Any]:
    from cellcal.core.calibration.calibrator import build_devices

    camera, arm = build_devices(config)
    return camera, arm


def parse_flange_pose(data: Any) -> tuple[np.ndarray, np.ndarray]:
    """``T_base_flange`` of a request (``translation_m``: 3 numbers, m; ``quaternion_xyzw``: a unit quaternion)
    as its rotation matrix and translation (m).

    Raises:
        RequestError: Naming what is wrong.
    """
    if not isinstance(data, Mapping):
        raise RequestError("flange_pose must be an object with translation_m and quaternion_xyzw")
    try:
        t = np.asarray(data["translation_m"], dtype=np.float64)
        q = np.asarray(data["quaternion_xyzw"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise RequestError("flange_pose needs translation_m (3 numbers, m) and quaternion_xyzw (4 numbers)") from None
    if t.shape != (3,) or q.shape != (4,) or not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))):
        raise RequestError("flange_pose needs translation_m (3 finite numbers, m) and quaternion_xyzw (4 finite "
                           "numbers)")
    if abs(float(np.linalg.norm(q)) - 1.0) > 1e-6:
        raise RequestError(f"flange_pose.quaternion_xyzw is not a unit quaternion (norm {np.linalg.norm(q):.9g})")
    return quaternion_matrix(q), t


class CellService:
    """One cell: its cameras (one configuration each), its one run at a time, its calibrations.

    Args:
        configs: The cell's configuration once per camera (:func:`load_every_camera`).
        out_dir: The service's output directory (the cell writes into ``out_dir/<cell>``).
        bus: Where its events go.
        build: ``config -> (camera, SafeArm)`` (default: the configuration's backends).
        recorder: Told of each run's start and end and of each calibration put into use (None: nobody).
    """

    def __init__(self, configs: Sequence[CellConfig], out_dir: Path, bus: EventBus, build: Builder | None = None,
                 recorder: Recorder | None = None):
        self.name = configs[0].cell.name
        if not NAME.fullmatch(self.name):
            raise ConfigError(f"cell name {self.name!r} cannot name a directory and a URL (letters, digits, '_', "
                              "'.', '-')", source=configs[0].source, key="cell.name")
        self.configs = {c.camera_name: c for c in configs}
        for name in self.configs:
            if not NAME.fullmatch(name):
                raise ConfigError(f"camera name {name!r} cannot name a directory and a URL", source=configs[0].source)
        self.directory = out_dir / self.name
        self.bus = bus
        self._build = build or _default_build
        self.recorder = recorder
        self._lock = threading.Lock()
        self._active: Run | None = None
        #: The tracking or monitoring session that has the cell (:mod:`.watch`), if any: no run meanwhile.
        self.watch: Any = None
        self._calibrations: dict[str, tuple[Any, CameraCalibration | None, float]] = {}

    @property
    def active(self) -> Run | None:
        """The run in progress, if any."""
        return self._active

    @property
    def builder(self) -> Builder:
        """``config -> (camera, SafeArm)``: how the cell's devices are built (runs, tracking, monitoring)."""
        return self._build

    def occupy(self, holder: Any, what: str) -> OutputLock:
        """Take the cell for a tracking or monitoring session ``holder`` (doing ``what``) as a run takes it: its
        lock held until :meth:`vacate`, no run meanwhile.

        Raises:
            BusyError: A run or another session has the cell, or another process holds its lock.
        """
        with self._lock:
            if self._active is not None:
                raise BusyError(f"cell {self.name!r} is running {self._active.kind} run {self._active.id}: {what} "
                                "waits for its end")
            if self.watch is not None:
                raise BusyError(f"cell {self.name!r} is {self.watch.kind}ing already (stop it first)")
            lock = OutputLock.for_directory(self.directory)
            try:
                lock.acquire()
            except OutputError as exc:
                raise BusyError(str(exc)) from None
            self.watch = holder
        return lock

    def vacate(self, holder: Any, lock: OutputLock) -> None:
        """The cell freed by the session ``holder`` (its lock released; idempotent)."""
        if lock.held:
            lock.release()
        with self._lock:
            if self.watch is holder:
                self.watch = None

    def camera_config(self, camera: str) -> CellConfig:
        """The configuration of ``camera`` (NotFoundError naming the cell's cameras)."""
        try:
            return self.configs[camera]
        except KeyError:
            raise NotFoundError(f"cell {self.name!r} has no camera {camera!r} (has: "
                                f"{', '.join(sorted(self.configs))})") from None

    def flange_config(self, camera: str) -> CellConfig:
        """The configuration of ``camera`` if it is on the flange (RequestError for a fixed one)."""
        config = self.camera_config(camera)
        if config.camera_entry.on != "flange":
            raise RequestError(f"camera {camera!r} is fixed (on the base): the service runs and maps cameras on "
                               "the flange")
        return config

    def describe(self) -> dict[str, Any]:
        """JSON form: the cell, its cameras and its run in progress."""
        active = self._active
        return {"name": self.name, "config": next(iter(self.configs.values())).source,
                "cameras": [{"name": n, "on": c.camera_entry.on, "backend": c.camera_section.get("backend")}
                            for n, c in self.configs.items()],
                "active_run": None if active is None else active.id}

    def start_run(self, kind: str, camera: str, options: RunOptions) -> Run:
        """Start a run of ``kind`` on ``camera`` in a worker thread; the run (``queued`` or already ``running``).

        Raises:
            RequestError: Unknown kind, or a fixed camera.
            NotFoundError: Unknown camera.
            BusyError: The cell runs something already (here, or another process holds its lock).
        """
        if kind not in KINDS:
            raise RequestError(f"unknown run kind {kind!r} (known: {', '.join(KINDS)})")
        config = self.flange_config(camera)
        with self._lock:
            if self._active is not None:
                raise BusyError(f"cell {self.name!r} is running {self._active.kind} run {self._active.id}: one run "
                                "at a time per cell")
            if self.watch is not None:
                raise BusyError(f"cell {self.name!r} is {self.watch.kind}ing: stop it first (one run, tracking or "
                                "monitoring at a time per cell)")
            lock = OutputLock.for_directory(self.directory)
            try:
                lock.acquire()
            except OutputError as exc:
                raise BusyError(str(exc)) from None
            run = Run(self.name, camera, kind, options, self.directory / camera)
            self._active = run
        thread = threading.Thread(target=self._work, args=(run, config, lock), name=f"cellcal-run-{run.id}",
                                  daemon=True)
        try:
            thread.start()
        except BaseException:
            self._active = None
            lock.release()
            raise
        return run

    def _work(self, run: Run, config: CellConfig, lock: OutputLock) -> None:
        last = [""]

        def changed(r: Run) -> None:
            data = r.to_dict()
            self.bus.publish("run.state" if data["state"] != last[0] else "run.progress", data)
            last[0] = data["state"]

        def settle(r: Run, outcome: Outcome) -> None:  # before the run shows its end
            calibration = None
            if outcome.state == "ok":
                self._calibrations.pop(r.camera, None)
                try:
                    calibration = self._read(r.camera, seen=False)
                except CellcalError as exc:
                    log.warning("run %s: its calibration cannot be read: %s", r.id, exc)
            if self.recorder is not None:
                self.recorder.run_ended(r, outcome, calibration)
            self._free(lock)

        try:
            if self.recorder is not None:
                self.recorder.run_started(run, config.source)
            execute(run, config, self._build, changed, settle)
        finally:
            self._free(lock)
            if run.state == "ok":
                self.bus.publish("calibration.changed", {"cell": self.name, "camera": run.camera,
                                                         "kind": run.kind, "run": run.id})

    def _free(self, lock: OutputLock) -> None:
        """The cell's lock released and its run slot freed (idempotent)."""
        if lock.held:
            lock.release()
        with self._lock:
            self._active = None

    def cancel(self, run: Run) -> None:
        """Ask ``run`` to stop at its next safe point (the arm told to stop there).

        Raises:
            BusyError: The run has ended already.
        """
        with run.lock:
            if run.final:
                raise BusyError(f"run {run.id} has ended ({run.state}): nothing to cancel")
            run.cancel_requested = True
        self.bus.publish("run.cancel_requested", {"id": run.id, "cell": self.name, "camera": run.camera})

    def calibration(self, camera: str) -> CameraCalibration | None:
        """The camera's current calibration (read again when its files change); None before its first result.

        Raises:
            NotFoundError: Unknown camera. ConfigError: A result file that cannot be read.
        """
        return self._read(camera, seen=True)

    def _read(self, camera: str, seen: bool) -> CameraCalibration | None:
        """:meth:`calibration`; ``seen``: a newly read one is told to the recorder as put into use."""
        config = self.camera_config(camera)
        directory = self.directory / camera
        cached = self._calibrations.get(camera)
        now = time.monotonic()
        if cached is not None and now - cached[2] < RECHECK_S:
            return cached[1]  # looked at its files a moment ago (a run of this service drops the entry)
        stamp = tuple(_stamp(directory / name) for name in ("result.json", "handeye.json"))
        if cached is not None and cached[0] == stamp:
            self._calibrations[camera] = (stamp, cached[1], now)
            return cached[1]
        calibration = read_calibration(directory, lambda: _configured_intrinsics(config))
        self._calibrations[camera] = (stamp, calibration, now)
        if seen and calibration is not None and self.recorder is not None:
            self.recorder.calibration_seen(self.name, camera, calibration)
        return calibration

    def pixel_to_base(self, camera: str, pixels: Any, flange_pose: Any) -> PixelsOnPlane:
        """Pixels of ``camera`` seen from ``flange_pose`` -> points on its calibrated plane (base frame), 1-sigma.

        Raises:
            RequestError: Pixels not (N, 2) finite numbers, N outside 1..:data:`MAX_PIXELS`, a bad flange pose.
            NotFoundError: Unknown camera, or no calibration yet.
        """
        self.flange_config(camera)
        flange = parse_flange_pose(flange_pose)
        try:
            uv = np.asarray(pixels, dtype=np.float64)
        except (TypeError, ValueError):
            raise RequestError("pixels must be [u, v] or a list of [u, v] (numbers, px)") from None
        uv = uv.reshape(1, -1) if uv.ndim == 1 else uv
        if uv.ndim != 2 or uv.shape[1] != 2 or not 1 <= uv.shape[0] <= MAX_PIXELS:
            raise RequestError(f"pixels must be [u, v] or a list of 1 to {MAX_PIXELS} [u, v] pairs")
        if not np.all(np.isfinite(uv)):
            raise RequestError("pixels must be finite numbers")
        calibration = self.calibration(camera)
        if calibration is None:
            raise NotFoundError(f"camera {camera!r} of cell {self.name!r} has no calibration yet (run calibrate or "
                                "handeye)")
        points, sigma = pixel_to_base(calibration.model, flange, uv)
        return PixelsOnPlane(points, sigma, calibration)


def _stamp(path: Path) -> tuple[int, int] | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_mtime_ns, st.st_size


def _configured_intrinsics(config: CellConfig) -> Any:
    from cellcal.core.calibration.calibrator import build_devices

    camera, _arm = build_devices(config)  # not connected: only what the configuration fixes
    return camera.configured_intrinsics()


class Service:
    """The calibration service over the cells of ``configs``; faces call it, it never calls them.

    Args:
        configs: Configuration files, one cell each (None: the packaged ``sim.toml``).
        out_dir: Where the cells write (``out_dir/<cell>/<camera>/``).
        build: ``config -> (camera, SafeArm)`` for every run (default: the configuration's backends).
        bus: The event bus (default: a new :class:`ObservedBus`, whose events are recorded and counted).
        history: The history store, or its URL (``sqlite:///PATH``, ``postgresql://...``), closed by
            :meth:`close`; None: no history kept.

    Attributes:
        metrics: The service's Prometheus metrics (None without prometheus-client).
        history: The history store (None: none kept).

    Raises:
        ConfigError: A configuration that does not validate, two with the same cell name, or an unusable history.
    """

    def __init__(self, configs: Sequence[str | Path | None], out_dir: str | Path, *, build: Builder | None = None,
                 bus: EventBus | None = None, history: HistoryStore | str | None = None) -> None:
        self.out_dir = Path(out_dir)
        self.bus = bus or ObservedBus()
        self.cells: dict[str, CellService] = {}
        for path in configs or [None]:
            cell = CellService(load_every_camera(path), self.out_dir, self.bus, build)
            if cell.name in self.cells:
                raise ConfigError(f"two configurations name cell {cell.name!r}: give each cell once",
                                  source=str(path) if path is not None else None)
            self.cells[cell.name] = cell
        self.history = HistoryStore(history) if isinstance(history, str) else history
        self.metrics = _metrics(self.cells)
        self.recorder = Recorder(self.bus, self.history, self.metrics)
        for cell in self.cells.values():
            cell.recorder = self.recorder
            if self.history is not None:
                marked = abandon_stale_runs(self.history, cell.name, list(cell.configs), cell.directory)
                if marked:
                    log.warning("history: %d run(s) of cell %s were left running; marked failed", marked, cell.name)
        self._runs: OrderedDict[str, Run] = OrderedDict()
        self._lock = threading.Lock()
        self.closed = False
        #: The cells' tracking and monitoring sessions (:mod:`.watch`).
        self.watches = Watches(self)
        #: The runs :meth:`close` found in progress and cancelled.
        self.stopped: list[Run] = []

    def cell(self, name: str) -> CellService:
        """The cell called ``name`` (NotFoundError naming the cells)."""
        try:
            return self.cells[name]
        except KeyError:
            raise NotFoundError(f"no cell {name!r} (cells: {', '.join(sorted(self.cells))})") from None

    def start_run(self, cell: str, kind: str, camera: str, options: Mapping[str, Any] | None = None) -> Run:
        """Start a run (:meth:`CellService.start_run`) and remember it; the run."""
        if self.closed:
            raise BusyError("the service is shutting down")
        try:
            parsed = RunOptions.from_dict(options)
        except ConfigError as exc:
            raise RequestError(str(exc)) from None
        run = self.cell(cell).start_run(kind, camera, parsed)
        with self._lock:
            self._runs[run.id] = run
            while len(self._runs) > MAX_RUNS_KEPT:
                oldest = next(iter(self._runs.values()))
                if not oldest.final:
                    break
                self._runs.popitem(last=False)
        return run

    def run(self, run_id: str) -> Run:
        """The run ``run_id`` (NotFoundError if unknown or forgotten)."""
        with self._lock:
            run = self._runs.get(run_id)
        if run is None:
            raise NotFoundError(f"no run {run_id!r}")
        return run

    def runs(self) -> list[Run]:
        """The runs remembered, oldest first."""
        with self._lock:
            return list(self._runs.values())

    def cancel_run(self, run_id: str) -> Run:
        """Cancel run ``run_id`` (:meth:`CellService.cancel`); the run."""
        run = self.run(run_id)
        self.cells[run.cell].cancel(run)
        return run

    def health(self) -> dict[str, Any]:
        """JSON form of the service's state: ok, its cells and their runs in progress."""
        return {"status": "stopping" if self.closed else "ok",
                "cells": {name: (None if c.active is None else c.active.id) for name, c in self.cells.items()},
                "subscribers": self.bus.subscribers}

    def close(self, wait_s: float = CLOSE_WAIT_S) -> list[Run]:
        """Stop: cancel every run in progress (its arm told to stop), wait for them to end, close the bus.

        Returns:
            The runs that were in progress. Idempotent.
        """
        self.closed = True
        active = [c.active for c in self.cells.values() if c.active is not None]
        self.stopped.extend(active)
        for run in active:
            with contextlib.suppress(CellcalError):  # it ended meanwhile
                self.cells[run.cell].cancel(run)
        for run in active:
            run.done.wait(wait_s)
        self.watches.close()  # tracking and monitoring stopped, their files written
        self.bus.close()
        self.recorder.close()
        return active


def _metrics(cells: Mapping[str, CellService]) -> Any:
    """The service's metrics, or None when prometheus-client (the ``serve`` extra) is not installed."""
    try:
        from cellcal.core.service.metrics import ServiceMetrics
    except ImportError:
        return None
    return ServiceMetrics(cells, cellcal_version())
