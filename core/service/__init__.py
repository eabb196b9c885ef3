"""``cellcal serve``: the cell's calibration service (issue #41).

:class:`Service` is the core (runs one at a time per cell, their cancellation, the current
calibration per camera, ``pixel_to_base``, the event bus); each face is a thin adapter over it:
HTTP (:mod:`cellcal.core.service.http`, FastAPI, imported only when served).
"""

from __future__ import annotations

from cellcal.core.service.calibration import CameraCalibration, read_calibration
from cellcal.core.service.cell import CellService, PixelsOnPlane, Service
from cellcal.core.service.errors import BusyError, NotFoundError, RequestError, ServiceError
from cellcal.core.service.events import Event, EventBus, Subscription
from cellcal.core.service.history import HistoryStore, NewCalibration
from cellcal.core.service.history_records import AppliedRecord, EventRecord, RunRecord
from cellcal.core.service.planepoint import MAX_PIXELS, PlaneCalibration, pixel_to_base
from cellcal.core.service.runs import KINDS, STATES, Run, RunCancelled, RunOptions

__all__ = ["KINDS", "MAX_PIXELS", "STATES", "AppliedRecord", "BusyError", "CameraCalibration", "CellService", "Event",
           "EventBus", "EventRecord", "HistoryStore", "NewCalibration", "NotFoundError", "PixelsOnPlane",
           "PlaneCalibration", "RequestError", "Run", "RunCancelled", "RunOptions", "RunRecord", "Service",
           "ServiceError", "Subscription", "pixel_to_base", "read_calibration"]
