"""OutputLock: one run per output directory or file, released on any exit, never blocked by a dead run."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
from pathlib import Path

import pytest

from cellcal.core.calibration.outlock import LOCK_NAME, OutputLock
from cellcal.devices.errors import OutputError


def test_a_second_lock_on_the_same_directory_is_refused_naming_the_holder(tmp_path: Path) -> None:
    with OutputLock.for_directory(tmp_path / "out") as held:
        assert held.held and (tmp_path / "out" / LOCK_NAME).read_text() == f"{os.getpid()}\n"
        with pytest.raises(OutputError) as info:
            OutputLock.for_directory(tmp_path / "out").acquire()  # a second open file: flock refuses it
        assert str(info.value) == (f"{tmp_path / 'out'} is in use by another cellcal run (pid {os.getpid()}); "
                                   f"wait for it to end or write elsewhere (lock file {held.path})")
        assert info.value.errno == errno.EBUSY and not info.value.bad_path
        other = OutputLock.for_directory(tmp_path / "other").acquire()  # another directory is free
        other.release()
    assert list(tmp_path.iterdir()) == []  # released: the lock file is gone, and the directories it made
    OutputLock.for_directory(tmp_path / "out").acquire().release()  # and the directory can be locked again


def test_released_on_an_exception_and_directories_it_made_are_removed_if_empty(tmp_path: Path) -> None:
    target = tmp_path / "a" / "b" / "out"
    with pytest.raises(RuntimeError), OutputLock.for_directory(target):
        assert (target / LOCK_NAME).exists()
        raise RuntimeError("the run failed")
    assert list(tmp_path.iterdir()) == []  # a/b/out made for the lock, and nothing else was put there
    with OutputLock.for_directory(target):
        (target / "result.json").write_text("{}")
    assert [p.name for p in target.iterdir()] == ["result.json"]  # a directory with a result stays


def test_file_locks_are_per_file(tmp_path: Path) -> None:
    with OutputLock.for_file(tmp_path / "s.mcap") as held:
        assert held.path == tmp_path / f".s.mcap{LOCK_NAME}"
        with pytest.raises(OutputError, match=r"s\.mcap is in use by another cellcal run"):
            OutputLock.for_file(tmp_path / "s.mcap").acquire()
        OutputLock.for_file(tmp_path / "t.mcap").acquire().release()
    assert list(tmp_path.iterdir()) == []


def test_a_killed_holder_leaves_a_file_that_blocks_nobody(tmp_path: Path) -> None:
    code = ("import os, signal, sys; from cellcal.core.calibration.outlock import OutputLock; "
            "OutputLock.for_directory(sys.argv[1]).acquire(); os.kill(os.getpid(), signal.SIGKILL)")
    proc = subprocess.Popen([sys.executable, "-c", code, str(tmp_path)])
    assert proc.wait(60) == -9
    assert (tmp_path / LOCK_NAME).read_text() == f"{proc.pid}\n"  # left behind by the dead run
    with OutputLock.for_directory(tmp_path) as lock:
        assert lock.held and (tmp_path / LOCK_NAME).read_text() == f"{os.getpid()}\n"
    assert list(tmp_path.iterdir()) == []


def test_a_planted_symlink_is_not_followed(tmp_path: Path) -> None:
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    out = tmp_path / "out"
    out.mkdir()
    (out / LOCK_NAME).symlink_to(victim)
    with pytest.raises(OutputError, match=r"cannot create .*\.cellcal\.lock") as info:
        OutputLock.for_directory(out).acquire()
    assert info.value.errno == errno.ELOOP and info.value.bad_path
    assert victim.read_text() == "precious\n"


@pytest.mark.parametrize(("make", "code"), [("file", errno.EEXIST), ("parent-file", errno.ENOTDIR)])
def test_paths_that_cannot_be_an_output_directory_are_bad_paths(tmp_path: Path, make: str, code: int) -> None:
    (tmp_path / "f").write_text("")
    target = tmp_path / "f" if make == "file" else tmp_path / "f" / "out"
    with pytest.raises(OutputError, match=f"cannot create {target}") as info:
        OutputLock.for_directory(target).acquire()
    assert info.value.errno == code and info.value.bad_path
