"""What the history store gives back (runs, applied calibrations, events, pages) and its time format.

Times go in as timezone-aware :class:`~datetime.datetime` values or ISO 8601 strings with an offset
(``Z`` or ``+02:00``), and come out as ISO 8601 UTC strings with microseconds,
``2024-05-01T10:00:00.000000Z``: one fixed width, so they also sort as text. A time without a
zone is refused: the store cannot guess the cell's.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from datetime import UTC, datetime, timedelta
from typing import Any, Generic, TypeVar

from cellcal.devices.errors import ConfigError

__all__ = ["AppliedRecord", "EventRecord", "Page", "RunRecord", "iso_from_us", "us_from_time"]

_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
_ONE_US = timedelta(microseconds=1)

T = TypeVar("T")


def us_from_time(value: datetime | str, what: str = "time") -> int:
    """Microseconds since 1970-01-01 UTC of a timezone-aware datetime or ISO 8601 string.

    Raises:
        ConfigError: The value is not a time, or has no timezone.
    """
    if isinstance(value, str):
        try:
            value = datetime.fromisoformat(value)
        except ValueError as exc:
            raise ConfigError(f"'{value}' is not an ISO 8601 time", key=what) from exc
    if not isinstance(value, datetime):
        raise ConfigError(f"expected a datetime or an ISO 8601 string, got {type(value).__name__}", key=what)
    if value.tzinfo is None or value.utcoffset() is None:
        raise ConfigError(f"time {value.isoformat()} has no timezone (give UTC, e.g. a trailing Z)", key=what)
    return (value - _EPOCH) // _ONE_US  # exact integer arithmetic on timedelta


def iso_from_us(us: int | None) -> str | None:
    """ISO 8601 UTC text (``...T10:00:00.000000Z``) of microseconds since the epoch (None stays None)."""
    if us is None:
        return None
    return (_EPOCH + int(us) * _ONE_US).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def _load(text: str | None) -> Any:
    return None if text is None else json.loads(text)


@dataclass(frozen=True)
class RunRecord:
    """One run: a calibrate, handeye, depthcal or fixed-handeye, from its start.

    Attributes:
        id: The run's number in this store.
        kind: ``calibrate``, ``handeye``, ``depthcal`` or ``fixed-handeye``.
        camera: The camera's name ("" for a run over the whole cell).
        source: The cell/config the run used (a path or a name), "" if not told.
        started: Start, ISO 8601 UTC.
        ended: End, ISO 8601 UTC; None while running.
        status: ``running``, ``ok``, ``failed`` or ``cancelled``.
        result: The result document (JSON data), if any.
        reason: Why it failed or was cancelled (one line), if it did.
    """

    id: int
    kind: str
    camera: str
    source: str
    started: str
    ended: str | None
    status: str
    result: Any
    reason: str | None

    @classmethod
    def from_row(cls, row: tuple[Any, ...]) -> RunRecord:
        """From ``id, kind, camera, source, started_us, ended_us, status, result_json, reason``."""
        rid, kind, camera, source, started, ended, status, result, reason = row
        return cls(int(rid), kind, camera, source, str(iso_from_us(started)), iso_from_us(ended), status,
                   _load(result), reason)

    def as_dict(self) -> dict[str, Any]:
        """JSON data of the record."""
        return asdict(self)


@dataclass(frozen=True)
class AppliedRecord:
    """One calibration put into use.

    Attributes:
        id: Its number in this store.
        camera: The camera it belongs to.
        what: ``mount`` (camera in the flange/tool frame), ``plane`` (the work plane; the service stores it in the
            base frame, its document saying ``"frame": "base"``) or ``camera_base`` (camera in the base frame).
        value: The pose or plane as JSON data (metres, radians, as the caller wrote it).
        covariance: Its covariance as JSON data (SI units squared), if given.
        run_id: The run that produced it, if any.
        applied: When it was put into use, ISO 8601 UTC.
    """

    id: int
    camera: str
    what: str
    value: Any
    covariance: Any
    run_id: int | None
    applied: str

    @classmethod
    def from_row(cls, row: tuple[Any, ...]) -> AppliedRecord:
        """From ``id, camera, what, value_json, covariance_json, run_id, applied_us``."""
        aid, camera, what, value, cov, run_id, applied = row
        return cls(int(aid), camera, what, _load(value), _load(cov), None if run_id is None else int(run_id),
                   str(iso_from_us(applied)))

    def as_dict(self) -> dict[str, Any]:
        """JSON data of the record."""
        return asdict(self)


@dataclass(frozen=True)
class EventRecord:
    """One drift or track event of a camera.

    Attributes:
        id: Its number in this store.
        camera: The camera's name.
        kind: What happened (e.g. ``knock``, ``drift``, ``track-started``).
        at: When, ISO 8601 UTC.
        detail: Its details as JSON data, if any.
    """

    id: int
    camera: str
    kind: str
    at: str
    detail: Any

    @classmethod
    def from_row(cls, row: tuple[Any, ...]) -> EventRecord:
        """From ``id, camera, kind, at_us, detail_json``."""
        eid, camera, kind, at, detail = row
        return cls(int(eid), camera, kind, str(iso_from_us(at)), _load(detail))

    def as_dict(self) -> dict[str, Any]:
        """JSON data of the record."""
        return asdict(self)


@dataclass(frozen=True)
class Page(Generic[T]):
    """One page of a listing.

    Attributes:
        items: The records, in the listing's order.
        next_cursor: Pass it back to get the next page; None on the last page.
    """

    items: tuple[T, ...]
    next_cursor: str | None
