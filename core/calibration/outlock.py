"""One run per output: an exclusive lock on an output directory or file, held for the whole run.

Two runs writing the same ``--out`` would interleave their resume journals and results
silently; the second one is refused instead (ADR 0008, "One run per output").
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
from pathlib import Path
from types import TracebackType
from typing import Self

from cellcal.devices.errors import OutputError

try:
    import fcntl
except ImportError:  # pragma: no cover - not a POSIX system: runs are not locked
    fcntl = None  # type: ignore[assignment]

__all__ = ["LOCK_NAME", "OutputLock"]

log = logging.getLogger(__name__)

#: Name of the lock file in a locked output directory.
LOCK_NAME = ".cellcal.lock"
#: Attempts to lock a lock file that another run removed right after we opened it.
_ATTEMPTS = 5
#: errno values of a file system without flock (e.g. some network file systems).
_NO_LOCKS = frozenset({errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EINVAL})


class OutputLock:
    """An exclusive ``flock`` on a lock file beside an output, released on any exit.

    The kernel drops the lock when the process ends, however it ends, so a crashed run
    leaves at most a stale lock file that blocks nobody. On release the file is removed
    first and unlocked second; a run that locked the removed file sees that it is no
    longer the one at the path and tries again. Directories the lock had to create are
    removed again on release if nothing else was put in them.

    Args:
        lock_file: The lock file.
        output: What it protects (named in messages).
    """

    def __init__(self, lock_file: str | Path, output: str | Path) -> None:
        self.path = Path(lock_file)
        self.output = Path(output)
        self._fd: int | None = None
        self._created: list[Path] = []

    @classmethod
    def for_directory(cls, directory: str | Path) -> OutputLock:
        """The lock of an output directory: ``DIR/.cellcal.lock``."""
        return cls(Path(directory) / LOCK_NAME, directory)

    @classmethod
    def for_file(cls, file: str | Path) -> OutputLock:
        """The lock of one output file: ``.NAME.cellcal.lock`` beside it."""
        file = Path(file)
        return cls(file.with_name(f".{file.name}{LOCK_NAME}"), file)

    @property
    def held(self) -> bool:
        """Whether this object holds the lock."""
        return self._fd is not None

    def acquire(self) -> Self:
        """Take the lock, creating the directory if needed.

        Raises:
            OutputError: If another run holds it (exit status 1), or the directory or
                lock file cannot be created (a bad path: exit status 2; a full disk: 1).
        """
        if fcntl is None:  # pragma: no cover
            return self
        self._make_directory()
        try:
            for _ in range(_ATTEMPTS):
                if self._try_lock():
                    return self
        except BaseException:
            self._remove_created()
            raise
        raise OutputError(f"cannot lock {self.path}: it keeps being replaced", errno=errno.EBUSY)

    def _try_lock(self) -> bool:
        """One attempt: True when locked (or locks are unsupported), False to try again.

        Raises:
            OutputError: If another run holds the lock, or the lock file cannot be made or locked.
        """
        assert fcntl is not None
        try:  # O_NOFOLLOW: a planted symlink cannot make us write into another file
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            raise OutputError(f"cannot create {self.path}: {exc.strerror or exc}", errno=exc.errno) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read_pid(fd)
            os.close(fd)
            who = f" (pid {holder})" if holder else ""
            raise OutputError(f"{self.output} is in use by another cellcal run{who}; wait for it to end or "
                              f"write elsewhere (lock file {self.path})", errno=errno.EBUSY) from None
        except OSError as exc:
            os.close(fd)
            if exc.errno not in _NO_LOCKS:
                raise OutputError(f"cannot lock {self.path}: {exc.strerror or exc}", errno=exc.errno) from None
            log.warning("%s: the file system cannot lock files (%s); not protected against a second run",
                        self.path, exc.strerror)
            return True
        except BaseException:
            os.close(fd)
            raise
        if not _same_file(fd, self.path):  # the previous holder removed it between our open and our lock
            os.close(fd)
            return False
        self._fd = fd
        with contextlib.suppress(OSError):  # who holds it, for the message of a second run
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode("ascii"))
        return True

    def release(self) -> None:
        """Remove the lock file, then unlock; idempotent, never raises."""
        fd, self._fd = self._fd, None
        if fd is not None:
            with contextlib.suppress(OSError):
                self.path.unlink()
            with contextlib.suppress(OSError):
                os.close(fd)
        self._remove_created()

    def _make_directory(self) -> None:
        """Create the lock file's directory (and parents), remembering which ones were new."""
        missing = []
        directory = self.path.parent
        while not directory.exists() and directory != directory.parent:
            missing.append(directory)
            directory = directory.parent
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"cannot create {self.path.parent}: {exc.strerror or exc}", errno=exc.errno) from None
        self._created = missing  # deepest first

    def _remove_created(self) -> None:
        for directory in self._created:
            try:
                directory.rmdir()
            except OSError:
                break  # not empty (the run wrote into it), or gone
        self._created = []

    def __enter__(self) -> Self:
        return self.acquire()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.release()


def _same_file(fd: int, path: Path) -> bool:
    """Whether the open ``fd`` is still the file at ``path``."""
    try:
        here, there = os.fstat(fd), os.stat(path, follow_symlinks=False)
    except OSError:
        return False
    return (here.st_dev, here.st_ino) == (there.st_dev, there.st_ino)


def _read_pid(fd: int) -> int | None:
    """The process id a lock holder wrote into the lock file, if readable."""
    with contextlib.suppress(OSError, ValueError):
        return int(os.pread(fd, 32, 0).decode("ascii").strip())
    return None
