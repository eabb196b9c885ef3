"""The one strict-JSON cleaner (cellcal.devices.jsonsafe) and the writers that use it."""

from __future__ import annotations

import datetime as dt
import json
import math
from pathlib import Path

import numpy as np
import pytest

from cellcal.core.calibration.journal import JournalWriter, plan_fingerprint, read_journal
from cellcal.core.calibration.report import write_json_atomic
from cellcal.devices.jsonsafe import json_safe
from cellcal.devices.pose import Pose


def test_non_finite_numbers_become_null_at_any_depth() -> None:
    doc = {"a": math.nan, "b": [1.5, math.inf, -math.inf], "c": {"d": (np.float32("nan"), np.float64(2.25))}}
    assert json_safe(doc) == {"a": None, "b": [1.5, None, None], "c": {"d": [None, 2.25]}}


def test_numpy_values_become_python_values_of_the_same_number() -> None:
    out = json_safe({"i": np.int64(-7), "u": np.uint8(255), "f": np.float32(0.5), "b": np.bool_(True),
                     "arr": np.array([[1.0, np.nan], [np.inf, 3.0]]), "ints": np.arange(3, dtype=np.int16)})
    assert out == {"i": -7, "u": 255, "f": 0.5, "b": True, "arr": [[1.0, None], [None, 3.0]], "ints": [0, 1, 2]}
    assert [type(out[k]) for k in ("i", "u", "f", "b")] == [int, int, float, bool]
    assert all(type(v) is int for v in out["ints"])
    json.dumps(out, allow_nan=False)  # strict JSON without a default= hook


def test_nested_tuples_sets_and_keys() -> None:
    out = json_safe({1: ((1, 2), (3, (4, 5))), "s": frozenset({7}), (0, 1): None})
    assert out == {"1": [[1, 2], [3, [4, 5]]], "s": [7], "(0, 1)": None}


def test_toml_dates_and_times_become_iso_strings() -> None:
    t = dt.datetime(2024, 5, 17, 8, 30, 0, tzinfo=dt.UTC)
    assert json_safe([t, t.date(), dt.time(7, 45)]) == ["2024-05-17T08:30:00+00:00", "2024-05-17", "07:45:00"]


def test_an_unknown_object_is_a_type_error_naming_type_and_place() -> None:
    with pytest.raises(TypeError, match=r"cellcal\.devices\.pose\.Pose at \$\.poses\[1\]\.camera_pose is not JSON"):
        json_safe({"poses": [{}, {"camera_pose": Pose.identity()}]})
    with pytest.raises(TypeError, match=r"builtins\.bytes at \$\[0\]"):
        json_safe([b"raw"])


def test_result_writer_uses_it_and_refuses_unknown_objects(tmp_path: Path) -> None:
    out = write_json_atomic(tmp_path / "r.json", {"x": (np.float64(1.0), math.nan), "n": np.int32(4)})
    assert json.loads(out.read_text()) == {"x": [1.0, None], "n": 4}
    with pytest.raises(TypeError, match="Pose at"):
        write_json_atomic(tmp_path / "bad.json", {"pose": Pose.identity()})
    assert not (tmp_path / "bad.json").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.json"]


def test_journal_lines_are_cleaned_the_same_way(tmp_path: Path) -> None:
    fp = plan_fingerprint({"cell": {"seed": np.int64(3)}}, [Pose.identity()])
    assert fp == plan_fingerprint({"cell": {"seed": 3}}, [Pose.identity()])
    writer = JournalWriter(tmp_path / "j.jsonl", fp, 1)
    writer.append(0, {"angle": np.float32(1.5), "rms": math.inf, "t": (1, 2)}, {})
    (entry,) = read_journal(tmp_path / "j.jsonl", fp)
    assert entry.pose == {"angle": 1.5, "rms": None, "t": [1, 2]}


def test_device_info_extra_must_be_json_data() -> None:
    from cellcal.devices.types import DeviceInfo

    ok = DeviceInfo("acme", "ACME", "Z1", extra={"fw": (1, 2), "temp_c": np.float32(41.5), "port": None})
    assert json_safe(ok.extra) == {"fw": [1, 2], "temp_c": 41.5, "port": None}
    with pytest.raises(TypeError, match=r"^DeviceInfo.extra of backend 'acme': .*Pose at \$\.mount is not JSON"):
        DeviceInfo("acme", "ACME", "Z1", extra={"mount": Pose.identity()})
