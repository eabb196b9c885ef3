"""A throwaway PostgreSQL server for the tests: Debian's binaries, a fresh cluster in a temporary folder.

:func:`start_postgres` runs ``initdb`` into a temporary folder and starts ``postgres`` on a free
loopback port with its socket in that folder (as ``nobody`` when the tests run as root: initdb
refuses root); :meth:`PostgresServer.new_database` gives each test its own empty database as a
``postgresql://user@127.0.0.1:port/db`` URL. The session fixture :func:`postgres_server` skips,
saying why, where no server can be started (no binaries, no psycopg, initdb or the server failed);
:func:`database_url` gives a test the URL of an empty database once on SQLite and once on PostgreSQL.
``.ci/run`` installs Debian's ``postgresql`` package; the server is stopped and its folder removed
at the end of the session.
"""

from __future__ import annotations

import glob
import itertools
import os
import pwd
import shutil
import signal
import subprocess
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from ports import free_port

__all__ = ["PostgresServer", "PostgresUnavailableError", "database_url", "find_bindir", "postgres_server",
           "start_postgres"]

USER = "cellcal"  # the cluster's superuser (trust authentication on loopback only)
_READY_WAIT_S = 60.0  # generous: a loaded machine may take seconds to start a cluster


class PostgresUnavailableError(RuntimeError):
    """No PostgreSQL server could be started here; the message says why."""


def find_bindir() -> Path | None:
    """The newest ``/usr/lib/postgresql/<major>/bin`` holding initdb and postgres (or PATH's), if any."""
    candidates = sorted(glob.glob("/usr/lib/postgresql/*/bin"), key=lambda p: int(Path(p).parent.name)
                        if Path(p).parent.name.isdigit() else 0, reverse=True)
    for c in candidates:
        if os.access(os.path.join(c, "initdb"), os.X_OK) and os.access(os.path.join(c, "postgres"), os.X_OK):
            return Path(c)
    initdb = shutil.which("initdb")
    return Path(initdb).parent if initdb and shutil.which("postgres") else None


class PostgresServer:
    """A running throwaway cluster (see :func:`start_postgres`)."""

    def __init__(self, root: Path, port: int, proc: subprocess.Popen[bytes]):
        self.root = root
        self.port = port
        self.proc = proc
        self._names = itertools.count(1)

    def url(self, db: str = "postgres") -> str:
        """The URL of database ``db`` on this server."""
        return f"postgresql://{USER}@127.0.0.1:{self.port}/{db}"

    def new_database(self) -> str:
        """Create an empty database; its URL."""
        import psycopg

        name = f"t{next(self._names)}"
        with psycopg.connect(self.url(), autocommit=True) as conn:
            conn.execute(f"CREATE DATABASE {name}")
        return self.url(name)

    def stop(self) -> None:
        """Fast shutdown (SIGINT ends the sessions and stops), then remove the folder."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        shutil.rmtree(self.root, ignore_errors=True)


def _as_user() -> dict[str, object]:
    """``subprocess`` arguments that drop root to ``nobody``; none when not root."""
    if os.geteuid() != 0:
        return {}
    try:
        nobody = pwd.getpwnam("nobody")
    except KeyError:
        raise PostgresUnavailableError("running as root and there is no 'nobody' user to run initdb as") from None
    return {"user": nobody.pw_uid, "group": nobody.pw_gid, "extra_groups": []}


def _tail(path: Path, lines: int = 5) -> str:
    try:
        return " | ".join(path.read_text(errors="replace").strip().splitlines()[-lines:])
    except OSError:
        return "(no log)"


def start_postgres() -> PostgresServer:
    """initdb into a temporary folder and start a server on a free port of 127.0.0.1.

    Raises:
        PostgresUnavailableError: Saying why no server could be started.
    """
    try:
        import psycopg
    except ImportError:
        raise PostgresUnavailableError("psycopg is not installed (pip install 'psycopg[binary]')") from None
    bindir = find_bindir()
    if bindir is None:
        raise PostgresUnavailableError("no initdb/postgres under /usr/lib/postgresql/*/bin nor on PATH "
                                  "(apt-get install postgresql; .ci/run does)")
    as_user = _as_user()
    root = Path(tempfile.mkdtemp(prefix="cellcal-pg-"))
    if as_user:
        os.chown(root, int(as_user["user"]), int(as_user["group"]))  # type: ignore[call-overload]
    data, log = root / "data", root / "server.log"
    init = subprocess.run([str(bindir / "initdb"), "-D", str(data), "-U", USER, "--auth=trust", "-E", "UTF8",
                           "--no-locale", "-N"], capture_output=True, text=True, cwd=root, **as_user)  # type: ignore[call-overload]
    if init.returncode != 0:
        shutil.rmtree(root, ignore_errors=True)
        last = (init.stderr or init.stdout).strip().splitlines()[-1:] or ["no output"]
        raise PostgresUnavailableError(f"initdb failed (status {init.returncode}): {last[0]}")
    port = free_port()
    with open(log, "wb") as out:
        if as_user:
            os.chown(log, int(as_user["user"]), int(as_user["group"]))  # type: ignore[call-overload]
        # fsync off: a test cluster need not survive a power cut, and the tests run faster
        proc = subprocess.Popen([str(bindir / "postgres"), "-D", str(data), "-k", str(root), "-p", str(port),
                                 "-c", "listen_addresses=127.0.0.1", "-c", "fsync=off"],
                                stdout=out, stderr=subprocess.STDOUT, cwd=root, **as_user)  # type: ignore[call-overload]
    server = PostgresServer(root, port, proc)
    deadline = time.monotonic() + _READY_WAIT_S
    while True:  # poll until it accepts connections (not a timing assertion: a start-up wait)
        try:
            psycopg.connect(server.url(), connect_timeout=2).close()
            return server
        except psycopg.OperationalError:
            if proc.poll() is not None or time.monotonic() > deadline:
                reason = f"postgres did not start (status {proc.poll()}): {_tail(log)}"
                server.stop()
                raise PostgresUnavailableError(reason) from None
            time.sleep(0.1)


@pytest.fixture(scope="session")
def postgres_server() -> Iterator[PostgresServer]:
    """A PostgreSQL server for the session; the test skips, saying why, where none can be started."""
    try:
        server = start_postgres()
    except PostgresUnavailableError as exc:
        pytest.skip(f"no PostgreSQL server for this test: {exc}")
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture(params=["sqlite", "postgresql"])
def database_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """The URL of an empty database, once a SQLite file and once a PostgreSQL database (or skipped)."""
    if request.param == "sqlite":
        return "sqlite:///" + str(tmp_path / "history.sqlite")
    server: PostgresServer = request.getfixturevalue("postgres_server")
    return server.new_database()
