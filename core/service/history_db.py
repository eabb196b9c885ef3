"""The history store's connection: a ``sqlite:`` or ``postgresql:`` URL, one lock, explicit transactions.

Both databases get the same SQL, written with ``?`` placeholders; :meth:`Database.sql` turns them
into psycopg's ``%s`` (the one place the parameter styles meet). Every error of either driver
leaves as a one-line :class:`~cellcal.devices.errors.ConfigError` (the URL names something that
cannot be a history database) or :class:`~cellcal.devices.errors.OutputError` (reading or writing
it failed), never as a driver traceback.
"""

from __future__ import annotations

import os
import sqlite3
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
from typing import Any
from urllib.parse import urlsplit, urlunsplit

from cellcal.devices.errors import ConfigError, MissingDependencyError, OutputError

__all__ = ["DEFAULT_FILENAME", "Database", "redact_url", "sqlite_url"]

DEFAULT_FILENAME = "cellcal-history.sqlite"
"""The SQLite file's name beside the service (``DIR/cellcal-history.sqlite``)."""

_PG_SCHEMES = ("postgresql", "postgres")
_MIGRATION_LOCK_KEY = 0x63656C6C63616C  # "cellcal" as an integer: the advisory lock of a migration


def sqlite_url(path: str | os.PathLike[str]) -> str:
    """The ``sqlite:`` URL of a file path (absolute paths give ``sqlite:////abs/path``)."""
    return "sqlite:///" + os.fspath(path)


def redact_url(url: str) -> str:
    """``url`` with any password replaced by ``***``, for messages and logs."""
    parts = urlsplit(url)
    if parts.password is None:
        return url
    host = parts.hostname or ""
    netloc = f"{parts.username or ''}:***@{host}" + (f":{parts.port}" if parts.port else "")
    return urlunsplit((parts.scheme, netloc, parts.path, parts.query, parts.fragment))


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


class Database:
    """One connection to a history database, shared by every thread under one lock.

    Statements run in autocommit mode; :meth:`transaction` wraps several in ``BEGIN`` ...
    ``COMMIT`` (``BEGIN IMMEDIATE`` on SQLite, which takes the write lock at once), and rolls
    back on any error, so a failed write leaves the rows before it as they were.

    Args:
        url: ``sqlite:///relative/path``, ``sqlite:////absolute/path``, ``sqlite:///:memory:``,
            or ``postgresql://user@host:port/db`` (any libpq URL; the password belongs in
            ``~/.pgpass`` or ``PGPASSWORD``, not in the URL).
        busy_timeout_s: How long a SQLite writer waits for another process's lock, seconds;
            PostgreSQL's connect timeout, seconds.

    Raises:
        ConfigError: The URL is of another kind, or names no usable database.
        MissingDependencyError: A PostgreSQL URL without psycopg installed.
    """

    def __init__(self, url: str, *, busy_timeout_s: float = 10.0):
        self.url = redact_url(url)
        self._raw_url = url
        self._busy_timeout_s = float(busy_timeout_s)
        self._lock = threading.RLock()
        scheme = url.split(":", 1)[0].lower() if ":" in url else ""
        if scheme == "sqlite":
            self.dialect = "sqlite"
        elif scheme in _PG_SCHEMES:
            self.dialect = "postgresql"
        else:
            raise ConfigError(f"history URL '{self.url}' is neither sqlite:///PATH nor postgresql://user@host:port/db")
        self._conn: Any = self._connect()

    # --- connecting -----------------------------------------------------------------------------

    def _connect(self) -> Any:
        return self._connect_sqlite() if self.dialect == "sqlite" else self._connect_postgres()

    def _connect_sqlite(self) -> sqlite3.Connection:
        if not self._raw_url.startswith("sqlite:///"):
            raise ConfigError(f"history URL '{self.url}' must start with sqlite:/// (then the file's path)")
        path = self._raw_url[len("sqlite:///"):]
        if not path:
            raise ConfigError(f"history URL '{self.url}' names no file")
        try:
            conn = sqlite3.connect(path, timeout=self._busy_timeout_s, isolation_level=None,
                                   check_same_thread=False)
        except sqlite3.Error as exc:
            raise ConfigError(f"history database {path}: cannot open ({_first_line(exc)})") from exc
        try:
            # WAL: readers (another process, a backup) never block the writer nor see half a transaction
            conn.execute("PRAGMA journal_mode=WAL").fetchone()
            conn.execute("PRAGMA foreign_keys=ON")
            conn.execute(f"PRAGMA busy_timeout={int(self._busy_timeout_s * 1000)}")  # milliseconds
        except sqlite3.Error as exc:
            conn.close()
            raise ConfigError(f"history database {path}: not a usable SQLite database ({_first_line(exc)})") from exc
        return conn

    def _connect_postgres(self) -> Any:
        try:
            import psycopg
        except ImportError as exc:
            raise MissingDependencyError("psycopg (the PostgreSQL client of the history store)", "postgres") from exc
        try:
            return psycopg.connect(self._raw_url, autocommit=True,
                                   connect_timeout=max(1, round(self._busy_timeout_s)),
                                   application_name="cellcal-history")
        except psycopg.Error as exc:
            raise ConfigError(f"history database {self.url}: cannot connect ({_first_line(exc)})") from exc

    def _live(self) -> Any:
        """The connection, reconnected if PostgreSQL dropped it since the last call."""
        if self._conn is None:
            raise OutputError(f"history database {self.url}: the store is closed")
        if self.dialect == "postgresql" and (self._conn.closed or self._conn.broken):
            self._conn = self._connect_postgres()
        return self._conn

    def close(self) -> None:
        """Close the connection; later calls raise :class:`OutputError`."""
        with self._lock:
            if self._conn is not None:
                self._conn.close()
                self._conn = None

    # --- statements -----------------------------------------------------------------------------

    def sql(self, text: str) -> str:
        """``text`` (``?`` placeholders) in this database's parameter style."""
        if self.dialect == "sqlite":
            return text
        return text.replace("%", "%%").replace("?", "%s")

    def ddl(self, text: str) -> str:
        """A schema statement with ``{pk}`` replaced by this database's auto-numbered key column."""
        pk = ("INTEGER PRIMARY KEY AUTOINCREMENT" if self.dialect == "sqlite"
              else "BIGINT GENERATED BY DEFAULT AS IDENTITY PRIMARY KEY")
        return text.replace("{pk}", pk)

    def run(self, conn: Any, text: str, params: Sequence[Any]) -> Any:
        """Execute ``text`` on ``conn``; without parameters the text goes as written (no placeholders)."""
        if not params:
            return conn.execute(text)
        return conn.execute(self.sql(text), tuple(params))

    def _errors(self) -> tuple[type[BaseException], ...]:
        if self.dialect == "sqlite":
            return (sqlite3.Error,)
        import psycopg

        return (psycopg.Error,)

    def query(self, text: str, params: Sequence[Any] = ()) -> list[tuple[Any, ...]]:
        """Rows of one read-only statement.

        Raises:
            OutputError: The database could not be read.
        """
        with self._lock:
            try:
                cur = self.run(self._live(), text, params)
                return list(cur.fetchall())
            except self._errors() as exc:
                raise OutputError(f"history database {self.url}: reading failed ({_first_line(exc)})") from exc

    @contextmanager
    def transaction(self, *, migration: bool = False) -> Iterator[Cursor]:
        """A write transaction: every statement through the yielded cursor commits together or not at all.

        Args:
            migration: Also take PostgreSQL's advisory lock, so that two services opening one
                old database migrate it once (SQLite's ``BEGIN IMMEDIATE`` already excludes).

        Raises:
            OutputError: A statement or the commit failed (everything rolled back).
        """
        with self._lock:
            conn = self._live()
            errors = self._errors()
            try:
                conn.execute("BEGIN IMMEDIATE" if self.dialect == "sqlite" else "BEGIN")
                if migration and self.dialect == "postgresql":
                    conn.execute("SELECT pg_advisory_xact_lock(%s)", (_MIGRATION_LOCK_KEY,))
            except errors as exc:
                raise OutputError(f"history database {self.url}: writing failed ({_first_line(exc)})") from exc
            try:
                yield Cursor(self, conn)
                conn.execute("COMMIT")
            except BaseException as exc:
                with suppress(*errors):  # if the connection is gone, the server discards the transaction itself
                    conn.execute("ROLLBACK")
                if isinstance(exc, errors):
                    raise OutputError(f"history database {self.url}: writing failed ({_first_line(exc)})") from exc
                raise

    def table_names(self) -> set[str]:
        """Names of the tables in the database (its current schema on PostgreSQL)."""
        if self.dialect == "sqlite":
            rows = self.query("SELECT name FROM sqlite_master WHERE type = 'table'")
        else:
            rows = self.query("SELECT table_name FROM information_schema.tables WHERE table_schema = current_schema()")
        return {str(r[0]) for r in rows}


class Cursor:
    """The statements of one :meth:`Database.transaction`."""

    def __init__(self, db: Database, conn: Any):
        self._db = db
        self._conn = conn

    def execute(self, text: str, params: Sequence[Any] = ()) -> list[tuple[Any, ...]]:
        """Run one statement; its rows (empty for most writes; ``RETURNING`` gives the new id)."""
        cur = self._db.run(self._conn, text, params)
        return list(cur.fetchall()) if cur.description is not None else []

    def ddl(self, text: str) -> None:
        """Run one schema statement (see :meth:`Database.ddl`)."""
        self._conn.execute(self._db.ddl(text))
