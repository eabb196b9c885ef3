"""The history store's schema: its versions as an ordered list of SQL steps, and the migration on open.

A database records, in its ``schema_version`` table, every version it was migrated to. Opening one
runs the steps after its newest version inside one transaction (all of them or none), so a
database written by an older cellcal is brought to :data:`SCHEMA_VERSION` with its rows intact; one
written by a newer cellcal is refused, as is a database that holds other tables but no
``schema_version`` (someone else's). ``{pk}`` in a step is the auto-numbered key column of the
database at hand (:meth:`~cellcal.core.service.history_db.Database.ddl`); everything else is the
same SQL on SQLite and PostgreSQL.

Times are ``BIGINT`` microseconds since 1970-01-01 UTC (``*_us`` columns): integers order the same
on both databases whatever their collation, to the microsecond; ties go to the smaller ``id``
(the earlier write). JSON documents are ``TEXT`` exactly as written, so floats read back bit for bit.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from cellcal.devices.errors import ConfigError, OutputError

from .history_db import Database

__all__ = ["MIGRATIONS", "SCHEMA_VERSION", "Migration", "migrate"]


@dataclass(frozen=True)
class Migration:
    """The SQL steps that take a database from ``version - 1`` to ``version``."""

    version: int
    description: str
    steps: tuple[str, ...]


MIGRATIONS: tuple[Migration, ...] = (
    Migration(1, "runs and applied calibrations", (
        "CREATE TABLE schema_version (version INTEGER NOT NULL PRIMARY KEY, applied_us BIGINT NOT NULL, "
        "description TEXT NOT NULL)",
        "CREATE TABLE runs (id {pk}, kind TEXT NOT NULL, camera TEXT NOT NULL, started_us BIGINT NOT NULL, "
        "ended_us BIGINT, status TEXT NOT NULL, result_json TEXT, reason TEXT)",
        "CREATE INDEX ix_runs_started ON runs (started_us, id)",
        "CREATE TABLE applied (id {pk}, camera TEXT NOT NULL, what TEXT NOT NULL, value_json TEXT NOT NULL, "
        "covariance_json TEXT, run_id BIGINT REFERENCES runs (id), applied_us BIGINT NOT NULL)",
        "CREATE INDEX ix_applied_at ON applied (camera, what, applied_us, id)",
    )),
    Migration(2, "the cell/config source of a run; drift and track events", (
        "ALTER TABLE runs ADD COLUMN source TEXT NOT NULL DEFAULT ''",
        "CREATE INDEX ix_runs_camera ON runs (camera, started_us, id)",
        "CREATE TABLE events (id {pk}, camera TEXT NOT NULL, kind TEXT NOT NULL, at_us BIGINT NOT NULL, "
        "detail_json TEXT)",
        "CREATE INDEX ix_events_at ON events (at_us, id)",
    )),
)
"""Every version's steps, oldest first; a new version is appended here, never edited in place."""

SCHEMA_VERSION = MIGRATIONS[-1].version
"""The version this code writes and reads."""


def _current_version(db: Database) -> int:
    """The database's newest version: 0 for an empty database.

    Raises:
        ConfigError: The database holds tables but no ``schema_version``, or cannot be read.
    """
    try:
        return _read_version(db)
    except OutputError as exc:  # a file SQLite opened but cannot read: its pages are damaged
        raise ConfigError(f"history database {db.url}: not a usable database ({exc.__cause__ or exc})") from exc


def _read_version(db: Database) -> int:
    tables = db.table_names()
    if "schema_version" not in tables:
        if tables:
            shown = ", ".join(sorted(tables)[:3])
            raise ConfigError(f"history database {db.url} is not a cellcal history (tables {shown}, "
                              "no schema_version)")
        return 0
    rows = db.query("SELECT MAX(version) FROM schema_version")
    return int(rows[0][0] or 0)


def migrate(db: Database) -> int:
    """Bring ``db`` to :data:`SCHEMA_VERSION`, in one transaction; return the version it had.

    Raises:
        ConfigError: The database is newer than this code, or someone else's.
        OutputError: A step failed (nothing of the migration stays).
    """
    found = _current_version(db)
    if found > SCHEMA_VERSION:
        raise ConfigError(f"history database {db.url} has schema version {found}, newer than this cellcal's "
                          f"{SCHEMA_VERSION}; upgrade cellcal or use another database")
    if found == SCHEMA_VERSION:
        return found
    with db.transaction(migration=True) as cur:
        # read again under the write lock: another service may have migrated since
        if "schema_version" in db.table_names():
            rows = cur.execute("SELECT MAX(version) FROM schema_version")
            found = int(rows[0][0] or 0)
        now_us = time.time_ns() // 1000  # microseconds since the epoch, UTC
        for migration in MIGRATIONS:
            if migration.version <= found:
                continue
            for step in migration.steps:
                cur.ddl(step)
            cur.execute("INSERT INTO schema_version (version, applied_us, description) VALUES (?, ?, ?)",
                        (migration.version, now_us, migration.description))
    return found
