"""The resume journal: what its fingerprint must tell apart, and how it is written and read back.

The fingerprint decides whether ``--resume`` may reuse measured poses. It must change with
anything that changes what a pose measures: any configuration value, a planned flange
position moved by a micrometre (far below an arm's 0.02-0.1 mm repeatability, so no real
re-plan goes unnoticed), an orientation turned by a microradian, the order or number of
poses. It must not change with float noise of a recomputed plan (1e-15 m) or the key order
of the configuration document.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cellcal.core.calibration.journal import (
    JOURNAL_SCHEMA,
    JournalWriter,
    journal_path,
    plan_fingerprint,
    read_journal,
    remove_journal,
)
from cellcal.devices.errors import CalibrationError, ConfigError, OutputError
from cellcal.devices.pose import Pose

DOC = {"cell": {"name": "test"}, "plan": {"heights_m": [0.46, 0.59, 0.61], "inclination_deg": 80.0},
       "camera": {"backend": "sim"}}
POSES = [Pose.from_xyz_rpy([0.30, 0.01, 0.46], [math.pi, 0.2, 0.1]),
         Pose.from_xyz_rpy([0.31, -0.02, 0.59], [math.pi, 0.2, -0.1]),
         Pose.from_xyz_rpy([0.29, 0.00, 0.61], [math.pi - 0.1, 0.0, 0.0])]


def shifted(pose: Pose, dx_m: float = 0.0, angle_rad: float = 0.0) -> Pose:
    return Pose(Rotation.from_rotvec([0.0, 0.0, angle_rad]) * pose.rotation,
                pose.translation + np.array([dx_m, 0.0, 0.0]))


def test_fingerprint_is_stable_under_float_noise_and_key_order() -> None:
    ref = plan_fingerprint(DOC, POSES)
    assert len(ref) == 64 and int(ref, 16) >= 0  # SHA-256, hex
    reordered = {"camera": {"backend": "sim"}, "plan": {"inclination_deg": 80.0, "heights_m": [0.46, 0.59, 0.61]},
                 "cell": {"name": "test"}}
    assert plan_fingerprint(reordered, POSES) == ref
    assert plan_fingerprint(DOC, [shifted(p, 1e-15) for p in POSES]) == ref
    recomputed = [Pose.from_matrix(p.as_matrix()) for p in POSES]  # another route to the same poses
    assert plan_fingerprint(DOC, recomputed) == ref


@pytest.mark.parametrize("change", [
    "config value", "config key", "nested list", "1 um along x", "0.1 mm along x", "1 cm along x",
    "1 urad about z", "pose order", "one pose less", "one pose more",
])
def test_fingerprint_tells_apart_everything_that_changes_a_measurement(change: str) -> None:
    doc: dict[str, object] = json.loads(json.dumps(DOC))
    poses = list(POSES)
    if change == "config value":
        doc["camera"] = {"backend": "o3r-emulated"}
    elif change == "config key":
        doc["cell"] = {"name": "test", "seed": 7}
    elif change == "nested list":
        doc["plan"] = {"heights_m": [0.46, 0.59, 0.62], "inclination_deg": 80.0}
    elif change.endswith("along x"):
        metres = {"1 um": 1e-6, "0.1 mm": 1e-4, "1 cm": 1e-2}[change.removesuffix(" along x")]
        poses[1] = shifted(poses[1], dx_m=metres)
    elif change == "1 urad about z":
        poses[2] = shifted(poses[2], angle_rad=1e-6)
    elif change == "pose order":
        poses[0], poses[1] = poses[1], poses[0]
    elif change == "one pose less":
        poses = poses[:2]
    else:
        poses = [*poses, POSES[0]]
    assert plan_fingerprint(doc, poses) != plan_fingerprint(DOC, POSES)


def test_journal_lives_beside_its_result(tmp_path: Path) -> None:
    assert journal_path(tmp_path / "out" / "result.json") == tmp_path / "out" / "result.json.journal.jsonl"
    assert journal_path("result.json") == Path("result.json.journal.jsonl")


def test_written_poses_read_back_in_plan_order(tmp_path: Path) -> None:
    path = tmp_path / "r.json.journal.jsonl"
    fp = plan_fingerprint(DOC, POSES)
    writer = JournalWriter(path, fp, 3)
    assert not path.exists() and writer.saved == 0  # nothing until the first pose
    writer.append(2, {"angle_deg": 80.01}, {"camera": {"seq": 5}})
    writer.append(0, {"angle_deg": 79.99}, {})
    assert writer.saved == 2
    lines = [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]
    assert lines[0] == {"kind": "header", "schema": JOURNAL_SCHEMA, "fingerprint": fp, "poses": 3}
    assert lines[1] == {"kind": "pose", "index": 2, "fingerprint": fp, "pose": {"angle_deg": 80.01},
                        "device_state": {"camera": {"seq": 5}}}
    entries = read_journal(path, fp)
    assert [(e.index, e.pose, e.device_state) for e in entries] == [
        (0, {"angle_deg": 79.99}, {}), (2, {"angle_deg": 80.01}, {"camera": {"seq": 5}})]
    # a resumed run appends to the same journal, with no second header
    again = JournalWriter(path, fp, 3, append=True, resumed=2)
    assert again.saved == 2
    again.append(1, {"angle_deg": 80.0}, {})
    assert again.saved == 3 and [e.index for e in read_journal(path, fp)] == [0, 1, 2]
    assert sum(1 for line in path.read_text().splitlines() if '"header"' in line) == 1
    remove_journal(path)
    remove_journal(path)  # gone already: no error
    assert not path.exists()


def test_an_append_without_a_journal_starts_a_new_one(tmp_path: Path) -> None:
    path = tmp_path / "j.jsonl"
    writer = JournalWriter(path, "f" * 64, 2, append=True, resumed=5)
    assert writer.saved == 0  # nothing to resume from
    writer.append(0, {}, {})
    assert json.loads(path.read_text().splitlines()[0])["kind"] == "header" and writer.saved == 1


def test_a_torn_last_line_is_dropped_and_damage_elsewhere_is_named(tmp_path: Path) -> None:
    path = tmp_path / "j.jsonl"
    fp = "a" * 64
    writer = JournalWriter(path, fp, 3)
    writer.append(0, {"n": 0}, {})
    writer.append(1, {"n": 1}, {})
    good = path.read_text()
    path.write_text(good + '{"kind": "pose", "ind')  # the process died mid-line
    assert [e.index for e in read_journal(path, fp)] == [0, 1]
    cases = {
        good.replace('"n":0', '"n":', 1): f"{path}: line 2 is not JSON; the journal is damaged",
        good.splitlines()[0] + "\n[1]\n" + good.splitlines()[2] + "\n":
            f"{path}: line 2 is not a JSON object; the journal is damaged",
        good.replace('"kind":"pose","index":1', '"kind":"pose","index":"1"'):
            f"{path}: line 3 is not a pose record of this run; the journal is damaged",
        good.replace('"kind":"pose","index":0', '"kind":"note","index":0'):
            f"{path}: line 2 is not a pose record of this run; the journal is damaged",
        good.replace('"pose":{"n":1}', '"pose":[1]'):
            f"{path}: line 3 is not a pose record of this run; the journal is damaged",
        "".join(line + "\n" for line in good.splitlines()[1:]): f"{path}: not a {JOURNAL_SCHEMA} journal",
        good.replace(JOURNAL_SCHEMA, "cellcal.journal/0"): f"{path}: not a {JOURNAL_SCHEMA} journal",
        "": f"{path}: not a {JOURNAL_SCHEMA} journal",
    }
    for text, message in cases.items():
        path.write_text(text)
        with pytest.raises(CalibrationError) as info:
            read_journal(path, fp)
        assert str(info.value) == message and not isinstance(info.value, ConfigError)
    # a pose line of another run inside this run's journal
    lines = good.splitlines()
    path.write_text("\n".join([lines[0], lines[1].replace(fp, "b" * 64), lines[2]]) + "\n")
    with pytest.raises(CalibrationError, match=r"line 2 is not a pose record of this run"):
        read_journal(path, fp)


def test_another_plan_and_a_missing_or_unreadable_journal_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "j.jsonl"
    JournalWriter(path, "a" * 64, 1).append(0, {}, {})
    with pytest.raises(ConfigError) as info:
        read_journal(path, "b" * 64)
    assert "the configuration or plan changed since the interrupted run (journal fingerprint aaaaaaaaaaaa, now " \
           "bbbbbbbbbbbb); run without --resume to start afresh" in str(info.value)
    assert str(path) in str(info.value)
    with pytest.raises(CalibrationError) as missing:
        read_journal(tmp_path / "none.jsonl", "a" * 64)
    assert str(missing.value) == f"{tmp_path / 'none.jsonl'}: no journal to resume (run without --resume to start " \
                                 "afresh)"
    with pytest.raises(CalibrationError, match=r": cannot read the journal: "):
        read_journal(tmp_path, "a" * 64)  # a directory
    path.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(CalibrationError, match=r": cannot read the journal: "):
        read_journal(path, "a" * 64)


def test_a_journal_that_cannot_be_written_is_an_output_error(tmp_path: Path) -> None:
    (tmp_path / "a-file").write_text("")
    with pytest.raises(OutputError, match=r"^resume journal: ") as first:
        JournalWriter(tmp_path / "a-file" / "j.jsonl", "a" * 64, 2).append(0, {}, {})  # its folder is a file
    assert first.value.errno is not None
    folder = tmp_path / "out"
    folder.mkdir()
    writer = JournalWriter(folder / "j.jsonl", "a" * 64, 2)
    writer.append(0, {}, {})
    shutil.rmtree(folder)  # the output folder vanished between two poses
    with pytest.raises(OutputError) as later:
        writer.append(1, {}, {})
    assert str(later.value) == f"cannot write the resume journal {folder / 'j.jsonl'}: {os.strerror(2)}"
    assert later.value.errno == 2 and writer.saved == 1


def test_fingerprint_is_the_sha256_of_the_canonical_plan_record() -> None:
    """The on-disk contract: a journal written by an earlier cellcal of the same format stays resumable.

    SHA-256 of the compact, key-sorted JSON ``{"config": document, "plan": [[x, y, z] rounded to 1 nm
    + the rotation matrix row by row rounded to 1e-12], ...]}`` (ADR 0008).
    """
    plan = [[round(float(v), 9) for v in p.translation] + [round(float(v), 12) for v in p.as_matrix()[:3, :3].ravel()]
            for p in POSES]
    canonical = json.dumps({"config": DOC, "plan": plan}, sort_keys=True, separators=(",", ":"))
    assert plan_fingerprint(DOC, POSES) == hashlib.sha256(canonical.encode("utf-8")).hexdigest()
    # within the rounding: 0.2 nm and 2e-14 of a matrix entry leave it unchanged (values far from a rounding edge)
    poses = [Pose.from_xyz_rpy([0.3000000001234, 0.01, 0.46], [math.pi, 0.2, 0.1])]
    moved = [Pose(poses[0].rotation, poses[0].translation + np.array([2e-10, 0.0, 0.0]))]
    assert plan_fingerprint(DOC, moved) == plan_fingerprint(DOC, poses)


def test_another_run_s_journal_is_replaced_not_continued(tmp_path: Path) -> None:
    path = tmp_path / "j.jsonl"
    JournalWriter(path, "a" * 64, 3).append(0, {"run": "old"}, {})
    fresh = JournalWriter(path, "b" * 64, 3)  # a new run, not --resume
    assert fresh.saved == 0
    fresh.append(0, {"run": "new"}, {})
    assert [e.pose for e in read_journal(path, "b" * 64)] == [{"run": "new"}]
    resumed = JournalWriter(path, "b" * 64, 3, append=True)  # resume without saying how many it holds
    assert resumed.saved == 0
    resumed.append(1, {"run": "new"}, {})
    assert resumed.saved == 1 and [e.index for e in read_journal(path, "b" * 64)] == [0, 1]


def test_a_header_only_journal_of_another_plan_is_refused_naming_both_fingerprints(tmp_path: Path) -> None:
    path = tmp_path / "j.jsonl"
    path.write_text(json.dumps({"kind": "header", "schema": JOURNAL_SCHEMA, "fingerprint": "c" * 64,
                                "poses": 3}) + "\n")
    assert read_journal(path, "c" * 64) == []
    with pytest.raises(ConfigError, match=r"journal fingerprint cccccccccccc, now dddddddddddd"):
        read_journal(path, "d" * 64)


def test_the_journal_is_plain_ascii_so_any_locale_reads_it(tmp_path: Path) -> None:
    path = tmp_path / "j.jsonl"
    writer = JournalWriter(path, "e" * 64, 2)
    writer.append(0, {"cell": "Zelle Süd", "unit": "µm"}, {})
    writer.append(1, {"cell": "Zelle Süd"}, {})
    raw = path.read_bytes()
    assert raw.isascii() and b"Zelle S\\u00fcd" in raw  # non-ASCII is escaped by the JSON encoder
    assert [e.pose["cell"] for e in read_journal(path, "e" * 64)] == ["Zelle Süd", "Zelle Süd"]
