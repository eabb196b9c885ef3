"""A hostile shell and hostile files: every one is ONE short, escaped stderr line and exit status 2.

Files that are no configuration (a FIFO, ``/dev/zero``, 1 MiB of comment, arrays nested
50,000 deep), hostile arguments (empty paths, escape sequences, bytes that are not
UTF-8, 300 kB values) and hostile values inside a configuration (1e308, 5e-324, 10**300,
huge strings and keys, control characters, too many items). No traceback, no hang, no
terminal control sequence reaches the user, no line is longer than 400 characters.
"""

from __future__ import annotations

import os
import tomllib
from pathlib import Path
from typing import Any

import pytest
from fuzz_targets import CONFIG_DIR, dump_toml

from cellcal.core.cli import main

DEFAULT_BASE = "sim.toml"


def _read(name: str) -> dict[str, Any]:
    return tomllib.loads((CONFIG_DIR / name).read_text(encoding="utf-8"))


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def _assert_one_line(code: int, err: str, *parts: str) -> str:
    lines = err.splitlines()
    assert code == 2, err
    assert len(lines) == 1 and "Traceback" not in err, err
    for part in parts:
        assert part in lines[0], f"{part!r} not in {lines[0]!r}"
    return lines[0]


def test_config_path_problems(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "nope.toml"
    _assert_one_line(*_run(["calibrate", "--check", "--config", str(missing)], capsys)[::2],
                     str(missing), "not found")
    _assert_one_line(*_run(["calibrate", "--config", str(tmp_path)], capsys)[::2], str(tmp_path), "directory")
    binary = tmp_path / "binary.toml"
    binary.write_bytes(b"[cell]\nname = \"\xff\xfe\"\n")
    _assert_one_line(*_run(["calibrate", "--config", str(binary)], capsys)[::2], str(binary),
                     "not UTF-8 text: byte 0xff at offset 15")
    bad = tmp_path / "bad.toml"
    bad.write_text("[cell]\nname = 'x'\nseed = = 3\n")
    _assert_one_line(*_run(["calibrate", "--config", str(bad)], capsys)[::2], str(bad), "invalid TOML",
                     "line 3")
    dup = tmp_path / "dup.toml"
    dup.write_text("[cell]\nseed = 1\n[camera]\nbackend = 'sim'\n[cell]\nseed = 2\n")
    _assert_one_line(*_run(["calibrate", "--config", str(dup)], capsys)[::2], str(dup), "invalid TOML", "line 5")
    empty = tmp_path / "empty.toml"
    empty.write_text("")
    _assert_one_line(*_run(["calibrate", "--config", str(empty)], capsys)[::2], str(empty), "key 'camera'",
                     "missing table")


def _hostile_line(argv: list[str], capsys: pytest.CaptureFixture[str], *parts: str) -> str:
    """Run ``argv`` (a usage error may exit through SystemExit): one line, status 2, short and escaped."""
    try:
        code, out, err = _run(argv, capsys)
    except SystemExit as exc:
        code, (out, err) = int(exc.code or 0), capsys.readouterr()
    line = _assert_one_line(code, err, *parts)
    assert out == "" and len(line) <= 400 + len("cellcal calibrate: error: ") + 1, len(line)
    assert not any(ord(ch) < 0x20 or 0x7F <= ord(ch) < 0xA0 for ch in line), line
    return line


def test_files_that_are_not_configurations(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)  # reading it would block until a writer comes: refused before any read
    _hostile_line(["calibrate", "--check", "--config", str(fifo)], capsys, str(fifo), "not a regular file")
    _hostile_line(["calibrate", "--check", "--config", "/dev/zero"], capsys, "/dev/zero", "not a regular file")
    huge = tmp_path / "huge.toml"
    huge.write_bytes(b"# " + b"x" * (1 << 20) + b"\n")
    _hostile_line(["calibrate", "--check", "--config", str(huge)], capsys, str(huge), "larger than 1048576 bytes")
    deep = tmp_path / "deep.toml"  # 50,000 nested arrays: tomllib recurses once per level
    deep.write_text("[cell]\nname = " + "[" * 50_000 + "]" * 50_000 + "\n")
    _hostile_line(["calibrate", "--check", "--config", str(deep)], capsys, str(deep), "nested too deeply")
    table = tmp_path / "paper.csv"
    os.mkfifo(table)
    _hostile_line(["paper", str(table)], capsys, str(table), "not a regular file")
    _hostile_line(["paper", "/dev/zero"], capsys, "/dev/zero", "not a regular file")
    _hostile_line(["monitor", "--baseline", str(fifo), "--frames", "1"], capsys, str(fifo), "not a regular file")
    _hostile_line(["calibrate", "--replay", str(fifo)], capsys, str(fifo), "not a file")
    if os.geteuid() != 0:  # root reads anything
        locked = tmp_path / "locked.toml"
        locked.write_text("[cell]\n")
        locked.chmod(0)
        _hostile_line(["calibrate", "--check", "--config", str(locked)], capsys, str(locked), "Permission denied")


@pytest.mark.parametrize(("argv", "parts"), [
    (["calibrate", "--check", "--config", ""], ("--config", "empty")),
    (["calibrate", "--out", ""], ("--out", "empty")),
    (["record", "--out", ""], ("--out", "empty")),
    (["study", "--out", ""], ("--out", "empty")),
    (["monitor", "--config", ""], ("--config", "empty")),
    (["calibrate", "--check", "--config", "a\x1b[2J\x1b]0;pwned\x07\n\u202e.toml"],
     ("a\\x1b[2J\\x1b]0;pwned\\x07\\x0a\\u202e.toml", "file not found")),
    (["calibrate", "--check", "--config", "x\udcff\udcfe.toml"], ("x\\xff\\xfe.toml", "file not found")),
    (["calibrate", "--check", "--config", "y" * 300_000], ("cannot read", "File name too long", " ... ")),
    (["calibrate", "--bogus", "z" * 300_000], ("unrecognized arguments", " ... ")),
    (["paper", "t.csv", "--fov", "\x1b[31m", "45"], ("--fov", "\\x1b[31m")),
], ids=["empty-config", "empty-out", "empty-record-out", "empty-study-out", "empty-monitor-config",
        "escape-codes", "undecodable-bytes", "300-kB-path", "300-kB-argument", "escape-in-a-number"])
def test_hostile_arguments_are_one_short_escaped_line(argv: list[str], parts: tuple[str, ...],
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    _hostile_line(argv, capsys, *parts)


def test_hostile_values_in_a_config_are_shown_short(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Huge numbers, strings and keys in a file come back elided, escaped, on one line."""
    base = _read(DEFAULT_BASE)
    for change, parts in (
            ({"cell": {"seed": 10**300}}, ("key 'cell.seed'", "64-bit range", "...")),
            ({"plan": {**base["plan"], "heights_m": [1e308, 0.5]}}, ("key 'plan.heights_m'", "<= 10.0", "1e+308")),
            ({"plan": {**base["plan"], "speed_m_s": 5e-324}}, ("key 'plan.speed_m_s'", ">= 0.001", "5e-324")),
            ({"plan": {**base["plan"], "target_m": [1e308, 0.0, 0.0]}}, ("key 'plan.target_m'", "<= 10.0")),
            ({"cell": {"name": "n" * 100_000}}, ("key 'cell.name'", "at most 100 characters")),
            ({"cell": {"name": "\x1b[2J"}}, ("key 'cell.name'", "control characters", "\\x1b[2J")),
            ({"cell": {"\x1b[31m" + "k" * 1000: 1}}, ("unknown key", "\\x1b[31m", "...")),
            ({"plan": {**base["plan"], "heights_m": [0.5] * 101}}, ("key 'plan.heights_m'", "at most 100 items")),
            ({"plan": {**base["plan"], "heights_m": [0.5] * 40, "azimuths_deg": [0.0] * 30}},
             ("key 'plan'", "1200 poses", "at most 1000"))):
        path = tmp_path / "hostile.toml"
        path.write_text(dump_toml({**base, **change}), encoding="utf-8")
        line = _hostile_line(["calibrate", "--check", "--config", str(path)], capsys, str(path), *parts)
        assert len(line) < 300, line
