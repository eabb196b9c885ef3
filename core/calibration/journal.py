"""The resume journal: one JSON line per measured pose, next to the result file.

``<result>.journal.jsonl`` (schema ``cellcal.journal/1``) lets ``cellcal calibrate
--resume`` continue an interrupted run; each line is fsync'd before the next move.
Format, fingerprint and failure rules: ADR 0008.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cellcal.core.calibration.report import write_bytes_atomic
from cellcal.devices import boundedjson
from cellcal.devices.errors import CalibrationError, ConfigError, OutputError
from cellcal.devices.jsonsafe import json_safe
from cellcal.devices.pose import Pose

JOURNAL_SCHEMA = "cellcal.journal/1"
JOURNAL_SUFFIX = ".journal.jsonl"


def journal_path(result_path: str | Path) -> Path:
    """Where the journal of a result file lives: ``<result>.journal.jsonl`` beside it."""
    p = Path(result_path)
    return p.with_name(p.name + JOURNAL_SUFFIX)


def plan_fingerprint(document: Mapping[str, Any], poses: Sequence[Pose]) -> str:
    """SHA-256 (hex) of the configuration document and the planned flange poses.

    Poses (translation and rotation matrix) are rounded to 1 nm / 1e-12 so the fingerprint
    does not depend on the last bit of a float computed on another machine.
    """
    plan = [[round(float(v), 9) for v in p.translation] + [round(float(v), 12) for v in p.rotation_matrix.ravel()]
            for p in poses]
    text = json.dumps({"config": json_safe(document), "plan": plan}, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


@dataclass(frozen=True)
class JournalEntry:
    """One recorded pose.

    Attributes:
        index: 0-based plan index.
        pose: The pose's entry of the result document, as it was written.
        device_state: What the devices saved for a resume (``{"camera": ..., "arm": ...}``).
    """

    index: int
    pose: dict[str, Any]
    device_state: dict[str, Any]


class JournalWriter:
    """Appends pose records to a journal, durably.

    Args:
        path: The journal file.
        fingerprint: :func:`plan_fingerprint` of the run.
        n_poses: Number of poses in the plan.
        append: Continue an existing journal (resume) instead of starting a new one.
        resumed: Poses the continued journal already holds (with ``append``).

    A new journal is created only when the first pose is appended, so a run that
    fails before measuring anything leaves no journal (and keeps an older one).
    """

    def __init__(self, path: str | Path, fingerprint: str, n_poses: int, *, append: bool = False,
                 resumed: int = 0):
        self.path = Path(path)
        self.fingerprint = fingerprint
        self.n_poses = n_poses
        self._started = append and self.path.exists()
        self.resumed = resumed if self._started else 0
        self.appended = 0

    @property
    def saved(self) -> int:
        """Poses of this run in the journal: those it resumed from plus those it appended.

        An older journal left by another run (this one has not appended yet) does not count.
        """
        return self.resumed + self.appended

    @staticmethod
    def _line(obj: Mapping[str, Any]) -> str:
        return json.dumps(json_safe(obj), allow_nan=False, separators=(",", ":")) + "\n"

    def append(self, index: int, pose: Mapping[str, Any], device_state: Mapping[str, Any]) -> None:
        """Record one measured pose (flushed and fsync'd before returning).

        Raises:
            OutputError: If the journal cannot be written (disk full, no permission ...).
        """
        line = {"kind": "pose", "index": int(index), "fingerprint": self.fingerprint, "pose": pose,
                "device_state": device_state}
        if not self._started:  # a new journal appears whole or not at all, its directory entry durable
            header = {"kind": "header", "schema": JOURNAL_SCHEMA, "fingerprint": self.fingerprint,
                      "poses": self.n_poses}
            try:
                write_bytes_atomic(self.path, (self._line(header) + self._line(line)).encode("utf-8"), fsync_dir=True)
            except OutputError as exc:
                raise OutputError(f"resume journal: {exc}", errno=exc.errno) from None
            self._started = True
        else:
            try:
                with open(self.path, "a", encoding="utf-8") as fh:
                    fh.write(self._line(line))
                    fh.flush()
                    os.fsync(fh.fileno())
            except OSError as exc:
                raise OutputError(f"cannot write the resume journal {self.path}: {exc.strerror or exc}",
                                  errno=exc.errno) from None
        self.appended += 1


def read_journal(path: str | Path, fingerprint: str) -> list[JournalEntry]:
    """The poses recorded in a journal, checked against the current run's fingerprint.

    Raises:
        CalibrationError: If there is no journal, or it is not a cellcal journal.
        ConfigError: If it was written for another configuration or plan.
    """
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise CalibrationError(f"{path}: no journal to resume (run without --resume to start afresh)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"{path}: cannot read the journal: {exc}") from None
    objs: list[dict[str, Any]] = []
    for n, text in enumerate(lines, 1):
        try:
            obj = boundedjson.loads(text)
        except boundedjson.JSONTooDeepError as exc:
            raise CalibrationError(f"{path}: line {n} is {exc}; the journal is damaged") from None
        except json.JSONDecodeError:
            if n == len(lines):
                break  # torn last line: the process died while writing it
            raise CalibrationError(f"{path}: line {n} is not JSON; the journal is damaged") from None
        if not isinstance(obj, dict):
            raise CalibrationError(f"{path}: line {n} is not a JSON object; the journal is damaged")
        objs.append(obj)
    if not objs or objs[0].get("kind") != "header" or objs[0].get("schema") != JOURNAL_SCHEMA:
        raise CalibrationError(f"{path}: not a {JOURNAL_SCHEMA} journal")
    if objs[0].get("fingerprint") != fingerprint:
        raise ConfigError("the configuration or plan changed since the interrupted run "
                          f"(journal fingerprint {str(objs[0].get('fingerprint'))[:12]}, now {fingerprint[:12]}); "
                          "run without --resume to start afresh", source=str(path))
    entries: dict[int, JournalEntry] = {}
    n_poses = objs[0].get("poses")
    for n, obj in enumerate(objs[1:], 2):
        index = obj.get("index")
        if (obj.get("kind") != "pose" or obj.get("fingerprint") != fingerprint or not isinstance(index, int)
                or isinstance(index, bool) or not isinstance(obj.get("pose"), dict)):
            raise CalibrationError(f"{path}: line {n} is not a pose record of this run; the journal is damaged")
        # each plan pose once, and only poses the plan has
        if index < 0 or (isinstance(n_poses, int) and index >= n_poses):
            raise CalibrationError(f"{path}: line {n} records pose index {index}, not one of the plan's "
                                   f"{n_poses} poses (0 to {n_poses - 1 if isinstance(n_poses, int) else '?'}); "
                                   "the journal is damaged")
        if index in entries:
            raise CalibrationError(f"{path}: line {n} records pose index {index} a second time; the journal is damaged")
        entries[index] = JournalEntry(index, obj["pose"], dict(obj.get("device_state") or {}))
    return [entries[i] for i in sorted(entries)]


def remove_journal(path: str | Path) -> None:
    """Delete a journal (after the result was written); no error if it is gone."""
    Path(path).unlink(missing_ok=True)


__all__ = ["JOURNAL_SCHEMA", "JOURNAL_SUFFIX", "JournalEntry", "JournalWriter", "journal_path",
           "plan_fingerprint", "read_journal", "remove_journal"]
