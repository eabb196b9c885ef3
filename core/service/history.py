"""The calibration history of a cell: every run, every applied calibration, every drift/track event.

A :class:`HistoryStore` opens a ``sqlite:///PATH`` file (by default ``cellcal-history.sqlite``
beside the service) or a ``postgresql://user@host:port/db`` database (psycopg 3, the
``postgres`` extra), migrates it to the current schema (:mod:`.history_schema`), and answers
"the mount of camera C as it was at time T": the latest calibration applied at or before T.
Writes from the service's worker threads are serialised by one lock, each in its own
transaction. Documents are strict JSON (:func:`~cellcal.devices.jsonsafe.json_safe`: NaN becomes
null) of at most ``max_document_bytes``; floats read back bit for bit.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, TypeVar

from cellcal.devices.errors import ConfigError, OutputError
from cellcal.devices.jsonsafe import json_safe

from .history_db import DEFAULT_FILENAME, Cursor, Database, sqlite_url
from .history_records import AppliedRecord, EventRecord, Page, RunRecord, us_from_time
from .history_schema import SCHEMA_VERSION, migrate

__all__ = [
    "APPLIED_KINDS",
    "DEFAULT_FILENAME",
    "MAX_DOCUMENT_BYTES",
    "MAX_PAGE",
    "RUN_KINDS",
    "RUN_STATUSES",
    "HistoryStore",
    "NewCalibration",
    "sqlite_url",
]

RUN_KINDS = ("calibrate", "handeye", "depthcal", "fixed-handeye")
RUN_STATUSES = ("running", "ok", "failed", "cancelled")
APPLIED_KINDS = ("mount", "plane", "camera_base")
MAX_DOCUMENT_BYTES = 1 << 20
"""Largest JSON document (a result, a pose, a covariance, an event's detail) stored: 1 MiB of UTF-8."""
MAX_PAGE = 500
"""Most records one listing call returns."""
_MAX_NAME = 200  # characters of a camera name or an event kind
_MAX_SOURCE = 4096  # characters of a run's source (a path)
_MAX_REASON = 2000  # characters of a failure's reason kept (longer ones are cut)

_RUN_COLS = "id, kind, camera, source, started_us, ended_us, status, result_json, reason"
_APPLIED_COLS = "id, camera, what, value_json, covariance_json, run_id, applied_us"
R = TypeVar("R")


@dataclass(frozen=True)
class NewCalibration:
    """A calibration to record as applied (see :meth:`HistoryStore.record_applied`)."""

    camera: str
    what: str
    value: Any
    covariance: Any = None


def _name(value: str, key: str, *, limit: int = _MAX_NAME, empty: bool = False) -> str:
    if not isinstance(value, str) or (not value and not empty) or len(value) > limit:
        raise ConfigError(f"expected a{'' if empty else ' non-empty'} name of at most {limit} characters, "
                          f"got {value!r:.60}", key=key)
    return value


def _one_of(value: str, allowed: Sequence[str], key: str) -> str:
    if value not in allowed:
        raise ConfigError(f"'{value}' is not one of {', '.join(allowed)}", key=key)
    return value


def _cursor(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    try:
        us, _, rid = text.partition(":")
        return int(us), int(rid)
    except ValueError:
        raise ConfigError(f"'{text:.40}' is not a cursor this store gave", key="cursor") from None


class HistoryStore:
    """The history database of one service (thread-safe).

    Args:
        url: ``sqlite:///PATH`` or ``postgresql://user@host:port/db`` (see
            :class:`~cellcal.core.service.history_db.Database`).
        max_document_bytes: Largest JSON document accepted, bytes of UTF-8.
        busy_timeout_s: How long a write waits for another process's lock, seconds.
        clock: The current UTC time when a call gives none (tests pass their own).

    Attributes:
        migrated_from: The schema version the database had when opened (0: it was empty; equal
            to :data:`~cellcal.core.service.history_schema.SCHEMA_VERSION`: nothing to migrate).

    Raises:
        ConfigError: Not a usable database, someone else's, or one newer than this code.
        MissingDependencyError: A PostgreSQL URL without psycopg.
        OutputError: The migration could not be written.
    """

    def __init__(self, url: str, *, max_document_bytes: int = MAX_DOCUMENT_BYTES, busy_timeout_s: float = 10.0,
                 clock: Callable[[], datetime] | None = None):
        self._db = Database(url, busy_timeout_s=busy_timeout_s)
        self.max_document_bytes = int(max_document_bytes)
        self._clock = clock or (lambda: datetime.now(UTC))
        try:
            self.migrated_from = migrate(self._db)
        except BaseException:
            self._db.close()
            raise

    @classmethod
    def beside(cls, directory: str | os.PathLike[str], **kwargs: Any) -> HistoryStore:
        """The default store of a service: ``DIRECTORY/cellcal-history.sqlite``."""
        return cls(sqlite_url(os.path.abspath(os.path.join(directory, DEFAULT_FILENAME))), **kwargs)

    @property
    def url(self) -> str:
        """The database's URL, its password (if any) shown as ``***``."""
        return self._db.url

    @property
    def dialect(self) -> str:
        """``"sqlite"`` or ``"postgresql"``."""
        return self._db.dialect

    @property
    def schema_version(self) -> int:
        """The database's schema version (after opening: :data:`~.history_schema.SCHEMA_VERSION`)."""
        return int(self._db.query("SELECT MAX(version) FROM schema_version")[0][0])

    def close(self) -> None:
        """Close the database."""
        self._db.close()

    def __enter__(self) -> HistoryStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- writing --------------------------------------------------------------------------------

    def _us(self, value: datetime | str | None, key: str) -> int:
        return us_from_time(self._clock() if value is None else value, key)

    def _json(self, value: Any, key: str) -> str | None:
        """Strict JSON text of ``value`` (None stays None), refused over the size limit."""
        if value is None:
            return None
        text = json.dumps(json_safe(value), allow_nan=False, separators=(",", ":"))
        size = len(text.encode("utf-8"))
        if size > self.max_document_bytes:
            raise OutputError(f"history: {key} is {size} bytes of JSON, over the limit of "
                              f"{self.max_document_bytes}; not stored")
        return text

    def start_run(self, kind: str, camera: str, source: str = "", *, started: datetime | str | None = None) -> int:
        """Record a run that starts now (or at ``started``); its id, for :meth:`finish_run`."""
        row = (_one_of(kind, RUN_KINDS, "kind"), _name(camera, "camera", empty=True),
               _name(source, "source", limit=_MAX_SOURCE, empty=True), self._us(started, "started"))
        with self._db.transaction() as cur:
            got = cur.execute("INSERT INTO runs (kind, camera, source, started_us, status) "
                              "VALUES (?, ?, ?, ?, 'running') RETURNING id", row)
        return int(got[0][0])

    def finish_run(self, run_id: int, status: str, *, result: Any = None, reason: str | None = None,
                   ended: datetime | str | None = None, applied: Sequence[NewCalibration] = ()) -> RunRecord:
        """End a running run, and record the calibrations it applied, all in one transaction.

        Args:
            run_id: From :meth:`start_run`.
            status: ``ok``, ``failed`` or ``cancelled``.
            result: The result document (JSON data), if any.
            reason: Why it failed or was cancelled (cut to 2000 characters).
            ended: When it ended (default now).
            applied: Calibrations put into use from this run, applied at ``ended``.

        Raises:
            ConfigError: No such run, or it has ended already.
        """
        _one_of(status, RUN_STATUSES[1:], "status")
        result_json = self._json(result, f"the result of run {run_id}")
        ended_us = self._us(ended, "ended")
        prepared = [self._prepared(item) for item in applied]
        with self._db.transaction() as cur:
            rows = cur.execute("SELECT status FROM runs WHERE id = ?", (int(run_id),))
            if not rows:
                raise ConfigError(f"run {run_id} is not in the history", key="run_id")
            if rows[0][0] != "running":
                raise ConfigError(f"run {run_id} has ended already ({rows[0][0]})", key="run_id")
            cur.execute("UPDATE runs SET status = ?, ended_us = ?, result_json = ?, reason = ? WHERE id = ?",
                        (status, ended_us, result_json, None if reason is None else str(reason)[:_MAX_REASON],
                         int(run_id)))
            for item in prepared:
                self._insert_applied(cur, item, int(run_id), ended_us)
        found = self.run(run_id)
        assert found is not None  # written just above, never deleted
        return found

    def abandon_running(self, reason: str, *, ended: datetime | str | None = None) -> int:
        """Mark every run still ``running`` as ``failed`` with ``reason`` (a service starting after a crash).

        Returns:
            How many runs were marked.
        """
        with self._db.transaction() as cur:
            rows = cur.execute("UPDATE runs SET status = 'failed', ended_us = ?, reason = ? "
                               "WHERE status = 'running' RETURNING id",
                               (self._us(ended, "ended"), str(reason)[:_MAX_REASON]))
        return len(rows)

    def _prepared(self, item: NewCalibration) -> tuple[str, str, str, str | None]:
        camera = _name(item.camera, "camera")
        what = _one_of(item.what, APPLIED_KINDS, "what")
        value = self._json(item.value, f"the {what} of {camera}")
        if value is None:
            raise ConfigError(f"the {what} of {camera} has no value", key="value")
        return camera, what, value, self._json(item.covariance, f"the covariance of {camera}'s {what}")

    def _insert_applied(self, cur: Cursor, item: tuple[str, str, str, str | None], run_id: int | None,
                        at_us: int) -> int:
        got = cur.execute("INSERT INTO applied (camera, what, value_json, covariance_json, run_id, applied_us) "
                          "VALUES (?, ?, ?, ?, ?, ?) RETURNING id", (*item, run_id, at_us))
        return int(got[0][0])

    def record_applied(self, camera: str, what: str, value: Any, *, covariance: Any = None,
                       run_id: int | None = None, applied_at: datetime | str | None = None) -> int:
        """Record a calibration put into use; its id.

        Args:
            camera: The camera's name.
            what: ``mount``, ``plane`` or ``camera_base``.
            value: The pose or plane as JSON data (numpy arrays become lists), metres and radians.
            covariance: Its covariance (e.g. a 6x6 array, SI units squared), if known.
            run_id: The run that produced it, if any (it must be in the history).
            applied_at: When it was put into use (default now).

        Raises:
            ConfigError: A bad argument, or ``run_id`` not in the history.
        """
        item = self._prepared(NewCalibration(camera, what, value, covariance))
        at_us = self._us(applied_at, "applied_at")
        with self._db.transaction() as cur:
            if run_id is not None and not cur.execute("SELECT id FROM runs WHERE id = ?", (int(run_id),)):
                raise ConfigError(f"run {run_id} is not in the history", key="run_id")
            return self._insert_applied(cur, item, None if run_id is None else int(run_id), at_us)

    def record_event(self, camera: str, kind: str, *, detail: Any = None, at: datetime | str | None = None) -> int:
        """Record a drift or track event of ``camera`` (``kind`` e.g. ``knock``); its id."""
        row = (_name(camera, "camera"), _name(kind, "kind"), self._us(at, "at"),
               self._json(detail, f"the detail of a {kind} event"))
        with self._db.transaction() as cur:
            got = cur.execute("INSERT INTO events (camera, kind, at_us, detail_json) VALUES (?, ?, ?, ?) "
                              "RETURNING id", row)
        return int(got[0][0])

    # --- reading --------------------------------------------------------------------------------

    def run(self, run_id: int) -> RunRecord | None:
        """One run by id; None if there is none."""
        rows = self._db.query(f"SELECT {_RUN_COLS} FROM runs WHERE id = ?", (int(run_id),))
        return RunRecord.from_row(rows[0]) if rows else None

    def _page(self, sql: str, where: list[str], params: list[Any], time_col: str, limit: int,
              cursor: str | None, newest_first: bool, build: Callable[[tuple[Any, ...]], R]) -> Page[R]:
        """One page ordered by ``(time_col, id)``, resumed after ``cursor``."""
        if not isinstance(limit, int) or not 1 <= limit <= MAX_PAGE:
            raise ConfigError(f"page size {limit!r} is not between 1 and {MAX_PAGE}", key="limit")
        after = _cursor(cursor)
        op, order = ("<", "DESC") if newest_first else (">", "ASC")
        if after is not None:  # keyset: strictly past the last row of the previous page
            where.append(f"({time_col} {op} ? OR ({time_col} = ? AND id {op} ?))")
            params += [after[0], after[0], after[1]]
        clause = f" WHERE {' AND '.join(where)}" if where else ""
        rows = self._db.query(f"{sql}{clause} ORDER BY {time_col} {order}, id {order} LIMIT ?", [*params, limit + 1])
        page = rows[:limit]
        last = page[-1] if page else None
        next_cursor = None
        if len(rows) > limit and last is not None:
            next_cursor = f"{last[_time_index(sql, time_col)]}:{last[0]}"
        return Page(tuple(build(r) for r in page), next_cursor)

    def list_runs(self, *, camera: str | None = None, kind: str | None = None, status: str | None = None,
                  limit: int = 50, cursor: str | None = None) -> Page[RunRecord]:
        """Runs, newest start first, at most ``limit`` (<= :data:`MAX_PAGE`) per page."""
        where, params = _filters(camera=camera, kind=kind, status=status)
        return self._page(f"SELECT {_RUN_COLS} FROM runs", where, params, "started_us", limit, cursor, True,
                          RunRecord.from_row)

    def list_applied(self, *, camera: str | None = None, what: str | None = None, limit: int = 50,
                     cursor: str | None = None) -> Page[AppliedRecord]:
        """Applied calibrations, newest first, at most ``limit`` per page."""
        where, params = _filters(camera=camera, what=what)
        return self._page(f"SELECT {_APPLIED_COLS} FROM applied", where, params, "applied_us", limit, cursor,
                          True, AppliedRecord.from_row)

    def calibration_at(self, camera: str, what: str, at: datetime | str) -> AppliedRecord | None:
        """The ``what`` of ``camera`` as it was at time ``at``: the latest applied at or before it.

        Two applied in the same microsecond: the later write wins. None before the first.
        """
        rows = self._db.query(f"SELECT {_APPLIED_COLS} FROM applied WHERE camera = ? AND what = ? "
                              "AND applied_us <= ? ORDER BY applied_us DESC, id DESC LIMIT 1",
                              (camera, _one_of(what, APPLIED_KINDS, "what"), us_from_time(at, "at")))
        return AppliedRecord.from_row(rows[0]) if rows else None

    def state_at(self, camera: str, at: datetime | str) -> dict[str, AppliedRecord]:
        """Every kind of calibration of ``camera`` in use at ``at`` (kinds never applied left out)."""
        found = {what: self.calibration_at(camera, what, at) for what in APPLIED_KINDS}
        return {what: rec for what, rec in found.items() if rec is not None}

    def events(self, since: datetime | str | None = None, until: datetime | str | None = None, *,
               camera: str | None = None, kind: str | None = None, limit: int = MAX_PAGE,
               cursor: str | None = None) -> Page[EventRecord]:
        """Events with ``since <= at < until`` (either bound may be None), oldest first, a page at a time."""
        where, params = _filters(camera=camera, kind=kind)
        if since is not None:
            where.append("at_us >= ?")
            params.append(us_from_time(since, "since"))
        if until is not None:
            where.append("at_us < ?")
            params.append(us_from_time(until, "until"))
        return self._page("SELECT id, camera, kind, at_us, detail_json FROM events", where, params, "at_us",
                          limit, cursor, False, EventRecord.from_row)

    def __repr__(self) -> str:
        return f"HistoryStore({self.url!r}, schema {SCHEMA_VERSION})"


def _filters(**equal: str | None) -> tuple[list[str], list[Any]]:
    """``col = ?`` clauses (and their values) of the filters given."""
    given = {col: value for col, value in equal.items() if value is not None}
    return [f"{col} = ?" for col in given], list(given.values())


def _time_index(sql: str, time_col: str) -> int:
    """Position of ``time_col`` among the selected columns of ``sql``."""
    cols = [c.strip() for c in sql.split("FROM")[0].removeprefix("SELECT").split(",")]
    return cols.index(time_col)

