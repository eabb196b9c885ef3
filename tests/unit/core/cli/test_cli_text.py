"""What the CLI prints from outside (paths, keys, values): escaped, one line, at most 400 characters."""

from __future__ import annotations

import errno

import pytest

from cellcal.core.cli.app import exit_status
from cellcal.core.cli.text import MAX_LINE, escape, one_line
from cellcal.devices.errors import (
    CalibrationError,
    CalibrationQualityError,
    ConfigError,
    DeviceTimeoutError,
    OutputError,
    RecordingFileError,
    RecordingWriteError,
)


@pytest.mark.parametrize(("text", "shown"), [
    ("plain path/é漢.toml", "plain path/é漢.toml"),
    ("a\x1b[2Jb", "a\\x1b[2Jb"),                 # clear screen
    ("t\x1b]0;title\x07", "t\\x1b]0;title\\x07"),  # set the terminal's title
    ("two\nlines\r", "two\\x0alines\\x0d"),
    ("c1\x9b31m", "c1\\x9b31m"),                 # the 8-bit CSI
    ("evil\u202etxt.exe", "evil\\u202etxt.exe"),  # right-to-left override
    ("bytes\udcff\udcfe", "bytes\\xff\\xfe"),     # argv bytes that were not UTF-8
    ("lone\ud800", "lone\\ud800"),
])
def test_escape_makes_every_character_visible_and_printable(text: str, shown: str) -> None:
    assert escape(text) == shown
    shown.encode("utf-8")  # always encodable


def test_one_line_cuts_in_the_middle_and_keeps_both_ends() -> None:
    assert one_line("short") == "short"
    text = "head-" + "x" * 100_000 + "-tail\n"
    line = one_line(text)
    assert len(line) == MAX_LINE and line.startswith("head-") and line.endswith("-tail\\x0a") and " ... " in line
    escaped = one_line("\x1b" * 300)  # short text that escaping makes long
    assert len(escaped) == MAX_LINE and "\x1b" not in escaped


@pytest.mark.parametrize(("exc", "status"), [
    (ConfigError("bad"), 2),
    (CalibrationError("bad input"), 2),
    (RecordingFileError("corrupt", source="s.mcap"), 2),
    (CalibrationQualityError("coverage", 0.1, 0.5), 1),
    (DeviceTimeoutError("slow"), 1),
    (OutputError("disk full", errno=errno.ENOSPC), 1),
    (OutputError("I/O error", errno=errno.EIO), 1),
    (OutputError("in use", errno=errno.EBUSY), 1),
    (OutputError("no permission", errno=errno.EACCES), 2),
    (OutputError("read-only", errno=errno.EROFS), 2),
    (OutputError("not a directory", errno=errno.ENOTDIR), 2),
    (RecordingWriteError("disk full", errno=errno.ENOSPC), 1),
    (RecordingWriteError("no such directory", errno=errno.ENOENT), 2),
])
def test_exit_status_of_each_kind_of_failure(exc: Exception, status: int) -> None:
    assert exit_status(exc) == status  # type: ignore[arg-type]
