"""write_bytes_atomic (core.report) and the resume journal's first write, which uses it."""

from __future__ import annotations

import errno
import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from cellcal.core.calibration.journal import JOURNAL_SCHEMA, JournalWriter, read_journal
from cellcal.core.calibration.report import write_bytes_atomic
from cellcal.devices.errors import OutputError


@pytest.fixture
def fsynced(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Kinds ("dir"/"file") of the descriptors os.fsync is called on (the real fsync still runs)."""
    kinds: list[str] = []
    real = os.fsync

    def spy(fd: int) -> None:
        kinds.append("dir" if stat.S_ISDIR(os.fstat(fd).st_mode) else "file")
        real(fd)

    monkeypatch.setattr(os, "fsync", spy)
    return kinds


@pytest.mark.parametrize(("fsync_dir", "expected"), [(False, ["file"]), (True, ["file", "dir"])])
def test_fsync_dir_also_syncs_the_directory_after_the_rename(tmp_path: Path, fsynced: list[str], fsync_dir: bool,
                                                             expected: list[str]) -> None:
    out = write_bytes_atomic(tmp_path / "sub" / "x.bin", b"\x00abc\n", fsync_dir=fsync_dir)
    assert out.read_bytes() == b"\x00abc\n"
    assert stat.S_IMODE(out.stat().st_mode) == 0o644
    assert fsynced == expected
    assert [p.name for p in out.parent.iterdir()] == ["x.bin"]


def test_failure_leaves_the_earlier_file_and_no_temp_file(tmp_path: Path) -> None:
    target = tmp_path / "r.json"
    target.write_bytes(b"old")
    (tmp_path / "blocker").write_text("a file, not a directory")
    with pytest.raises(OutputError, match=r"cannot write .*blocker") as info:
        write_bytes_atomic(tmp_path / "blocker" / "r.json", b"new", fsync_dir=True)
    assert info.value.bad_path  # a path that cannot be used: bad input (exit status 2)
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blocker", "r.json"]


def test_first_journal_write_is_header_and_pose_made_durable(tmp_path: Path, fsynced: list[str]) -> None:
    path = tmp_path / "out" / "result.json.journal.jsonl"
    writer = JournalWriter(path, "f" * 64, 3)
    writer.append(0, {"index": 0, "angle_deg": 30.5}, {"camera": {"state": [1, 2]}})
    header = {"kind": "header", "schema": JOURNAL_SCHEMA, "fingerprint": "f" * 64, "poses": 3}
    pose = {"kind": "pose", "index": 0, "fingerprint": "f" * 64, "pose": {"index": 0, "angle_deg": 30.5},
            "device_state": {"camera": {"state": [1, 2]}}}
    assert path.read_text(encoding="utf-8") == "".join(
        json.dumps(o, separators=(",", ":")) + "\n" for o in (header, pose))
    assert fsynced == ["file", "dir"]
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    assert [p.name for p in path.parent.iterdir()] == [path.name]

    writer.append(1, {"index": 1, "angle_deg": 31.0}, {})  # later poses are appended and fsync'd in place
    assert fsynced == ["file", "dir", "file"]
    assert [e.index for e in read_journal(path, "f" * 64)] == [0, 1]
    assert writer.appended == 2


def test_journal_that_cannot_be_created_says_so(tmp_path: Path) -> None:
    (tmp_path / "blocker").write_text("")
    writer = JournalWriter(tmp_path / "blocker" / "r.json.journal.jsonl", "f" * 64, 1)
    with pytest.raises(OutputError, match=r"^resume journal: cannot write .*r\.json\.journal\.jsonl"):
        writer.append(0, {}, {})
    assert writer.appended == 0 and writer.saved == 0


@pytest.mark.parametrize(("code", "bad_path"), [(errno.ENOSPC, False), (errno.EIO, False), (errno.EDQUOT, False),
                                                (errno.EFBIG, False), (errno.EACCES, True), (errno.EROFS, True)])
def test_a_full_disk_is_an_environment_failure_and_a_bad_path_bad_input(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, code: int, bad_path: bool) -> None:
    target = tmp_path / "r.json"
    target.write_bytes(b"old")

    def failing_fsync(fd: int) -> None:  # where a full disk shows itself on many file systems
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(os, "fsync", failing_fsync)
    with pytest.raises(OutputError, match=os.strerror(code)) as info:
        write_bytes_atomic(target, b"new")
    assert info.value.errno == code and info.value.bad_path is bad_path
    assert target.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["r.json"]


_PARTIAL_WRITE = """
import resource, signal, sys
from cellcal.core.calibration.report import write_bytes_atomic
from cellcal.devices.errors import OutputError
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # past the limit write() fails with EFBIG instead of killing us
resource.setrlimit(resource.RLIMIT_FSIZE, (65536, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
try:
    write_bytes_atomic(sys.argv[1], bytes(1 << 20), fsync_dir=True)
except OutputError as exc:
    print(exc.errno, exc.bad_path, exc)
"""


def test_a_write_that_fails_part_way_leaves_the_old_file_and_the_folder_as_they_were(tmp_path: Path) -> None:
    """A real short write (the file-size limit stops it at 64 KiB of 1 MiB), in a child process."""
    target = tmp_path / "result.json"
    target.write_bytes(b'{"old": true}')
    done = subprocess.run([sys.executable, "-c", _PARTIAL_WRITE, str(target)], capture_output=True, text=True,
                          timeout=60, check=True)
    code, bad_path, message = done.stdout.strip().split(" ", 2)
    assert int(code) == errno.EFBIG and bad_path == "False"  # an environment failure: exit status 1
    assert message == f"cannot write {target}: {os.strerror(errno.EFBIG)}"
    assert target.read_bytes() == b'{"old": true}'
    assert [p.name for p in tmp_path.iterdir()] == ["result.json"]  # no temp file left


def test_an_interrupt_while_syncing_leaves_the_old_file_and_is_not_swallowed(tmp_path: Path,
                                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    target = tmp_path / "result.json"
    target.write_bytes(b"old")
    seen: list[bytes] = []
    real_fsync = os.fsync

    def interrupted_fsync(fd: int) -> None:
        real_fsync(fd)
        seen.append(Path(f"/proc/self/fd/{fd}").read_bytes())  # the temp file was complete ...
        raise KeyboardInterrupt  # ... when Ctrl-C came

    monkeypatch.setattr(os, "fsync", interrupted_fsync)
    with pytest.raises(KeyboardInterrupt):
        write_bytes_atomic(target, b"new content")
    assert seen == [b"new content"]
    assert target.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["result.json"]
