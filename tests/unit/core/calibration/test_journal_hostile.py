"""A resume journal someone else wrote: deep nesting, duplicated, negative and out-of-plan pose indices are
refused in one line naming the line (issue #31, ADR 0039)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from cellcal.core.calibration.journal import JournalWriter, read_journal
from cellcal.devices.errors import CalibrationError

FINGERPRINT = "f" * 64


def _journal(tmp_path: Path, extra: str) -> Path:
    """A journal of a 3-pose plan with pose 0 recorded by the writer, then ``extra`` appended as line 3."""
    path = tmp_path / "result.json.journal"
    JournalWriter(path, FINGERPRINT, 3).append(0, {"x": 1.0}, {})
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(extra + "\n")
        fh.write(json.dumps({"kind": "pose", "index": 2, "fingerprint": FINGERPRINT, "pose": {}}) + "\n")
    return path


def _pose(index: object) -> str:
    return json.dumps({"kind": "pose", "index": index, "fingerprint": FINGERPRINT, "pose": {"x": 2.0}})


@pytest.mark.parametrize(("extra", "says"), [
    (_pose(0), "line 3 records pose index 0 a second time"),
    (_pose(-1), "line 3 records pose index -1, not one of the plan's 3 poses (0 to 2)"),
    (_pose(3), "line 3 records pose index 3, not one of the plan's 3 poses (0 to 2)"),
    (_pose(True), "line 3 is not a pose record of this run"),
    ("[" * 100_000 + "]" * 100_000, "line 3 is nested 100000 levels deep, more than the 64 accepted"),
])
def test_a_damaged_line_is_refused_naming_it(tmp_path: Path, extra: str, says: str) -> None:
    path = _journal(tmp_path, extra)
    with pytest.raises(CalibrationError) as err:
        read_journal(path, FINGERPRINT)
    assert str(err.value) == f"{path}: {says}; the journal is damaged"


def test_a_well_formed_journal_still_reads_back(tmp_path: Path) -> None:
    path = _journal(tmp_path, _pose(1))
    assert [e.index for e in read_journal(path, FINGERPRINT)] == [0, 1, 2]
