"""The reports' error budget tables (ADR 0059): calibrate's from a real sim run, the hand-eye one from its result."""

from __future__ import annotations

import copy
import math
from html.parser import HTMLParser
from typing import Any

from cellcal.core.calibration.budget import ALLOWANCE_TERMS
from cellcal.core.report.html import render_html


class Rows(HTMLParser):
    """Every table row: its attributes, its cells' text and ``data-value`` and which cells are highlighted."""

    def __init__(self) -> None:
        super().__init__()
        self.rows: list[dict[str, Any]] = []
        self.text: list[str] = []
        self._cell: dict[str, Any] | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if tag == "tr":
            self.rows.append({"attrs": a, "cells": []})
        if tag == "td" and self.rows:
            self._cell = {"value": a.get("data-value"), "text": "", "class": a.get("class") or ""}
            self.rows[-1]["cells"].append(self._cell)

    def handle_endtag(self, tag: str) -> None:
        if tag == "td":
            self._cell = None

    def handle_data(self, data: str) -> None:
        self.text.append(data)
        if self._cell is not None:
            self._cell["text"] += data


def parse(page: str) -> Rows:
    parser = Rows()
    parser.feed(page)
    parser.close()
    return parser


def _class(row: dict[str, Any]) -> str:
    return str(row["attrs"].get("class") or "")


def test_the_calibrate_report_has_the_budget_of_the_run(passing: dict[str, Any]) -> None:
    budget = passing["calibrate"]["result"]["summary"]["error_budget"]
    cons = budget["consensus"]
    assert cons["judged"] == "allowance"            # the ToF sim states its allowance
    page = parse(render_html(passing, []))
    text = "".join(page.text)
    assert "Error budget" in text
    assert f"{ALLOWANCE_TERMS[cons['dominant']['height']]} dominates" in text and cons["next"] in text
    terms = {str(r["attrs"]["data-term"]): r for r in page.rows if _class(r).startswith("budget") and
             "data-term" in r["attrs"]}
    assert list(terms) == list(ALLOWANCE_TERMS)
    for key, row in terms.items():
        at = cons["at_allowance"][key]
        values = [c["value"] for c in row["cells"] if c["value"] is not None]
        assert float(values[0]) == abs(at["tilt_rad"]) and float(values[1]) == abs(at["height_m"])
        assert row["cells"][3]["text"] == f"{abs(at['height_m']) * 1000:.3f}"              # mm
        assert row["cells"][2]["text"] == f"{math.degrees(abs(at['tilt_rad'])):.4f}"       # deg
        unit = {"depth_scale": "depth_scale_1pct", "depth_offset": "depth_offset_1mm"}.get(key)
        if unit:
            assert float(values[3]) == abs(cons[unit]["height_m"])
        assert ("dominant" in _class(row)) == (key == cons["dominant"]["height"])
    # the case on the ToF sim: 1 % of scale moves the height more than 1 mm of offset, yet at
    # the camera's 0.2 % and 5 mm the offset dominates
    assert abs(cons["depth_scale_1pct"]["height_m"]) > abs(cons["depth_offset_1mm"]["height_m"])
    assert cons["dominant"]["height"] == "depth_offset" and terms["depth_scale"]["cells"][1]["text"] == "0.2 %"
    pose_rows = [r for r in page.rows if _class(r) == "budget-pose"]
    assert len(pose_rows) == len(budget["poses"]) == 3
    for row, pose in zip(pose_rows, budget["poses"], strict=True):
        cells = row["cells"][1:]
        n = len(ALLOWANCE_TERMS)                       # the ToF sim states every term, its wiggle too
        heights = [float(c["value"]) for c in cells[:n]]
        assert heights == [abs(pose["at_allowance"][k]["height_m"]) for k in ALLOWANCE_TERMS]
        marked = [k for k, c in zip(ALLOWANCE_TERMS, cells[:n], strict=True) if "dominant" in c["class"]]
        assert marked == [pose["dominant"]["height"]]


def test_a_report_without_a_budget_has_no_budget_table(passing: dict[str, Any]) -> None:
    data = copy.deepcopy(passing)
    data["calibrate"]["result"]["summary"]["error_budget"] = None
    assert "Error budget" not in render_html(data, [])


def _handeye(budget: dict[str, Any] | None) -> dict[str, Any]:
    mount = {"translation_m": [0.01, -0.02, 0.05], "translation_ci_m": [[0.009, 0.011], [-0.021, -0.019],
                                                                          [0.049, 0.051]],
             "rpy_deg": [0.1, -0.2, 90.0], "rpy_ci_deg": [[0.0, 0.2], [-0.3, -0.1], [89.9, 90.1]], "confidence": 0.95}
    result: dict[str, Any] = {"method": "plane", "mount": mount, "fit": {"chi2_per_dof": 1.0},
                              "observability": {"rank": 6, "n_parameters": 6}}
    if budget is not None:
        result["error_budget"] = budget
    return {"schema": "cellcal.report/1", "kind": "handeye", "camera": "sim", "status": "ok",
            "handeye": {"result": result}}


HANDEYE_BUDGET = {
    "terms": {"depth_scale_1pct": {"tx_m": 0.0012, "ty_m": -0.0008, "tz_m": 0.0061, "roll_rad": 0.0004,
                                   "pitch_rad": -0.0002, "yaw_rad": 0.0, "plane_offset_m": 0.0049},
              "depth_offset_1mm": {"tx_m": 0.0, "ty_m": 0.0001, "tz_m": 0.001, "roll_rad": 0.0,
                                   "pitch_rad": 0.0, "yaw_rad": 0.0, "plane_offset_m": 0.001},
              "arm_accuracy": {"tx_m": 0.0005, "ty_m": 0.0005, "tz_m": 0.0004, "roll_rad": 0.002,
                               "pitch_rad": 0.002, "yaw_rad": 0.001, "plane_offset_m": 0.0006}},
    "dominant": "depth_scale_1pct", "next": "run cellcal depthcal"}


def test_the_handeye_report_has_the_budget_when_its_result_has_one() -> None:
    assert "Error budget" not in render_html(_handeye(None), [])
    page = parse(render_html(_handeye(HANDEYE_BUDGET), []))
    text = "".join(page.text)
    assert "Error budget" in text and "depth scale (1 %) dominates" in text and "run cellcal depthcal" in text
    rows = {str(r["attrs"]["data-term"]): r for r in page.rows if _class(r).startswith("handeye-budget")}
    assert list(rows) == list(HANDEYE_BUDGET["terms"])
    assert [k for k, r in rows.items() if "dominant" in _class(r)] == ["depth_scale_1pct"]
    scale = rows["depth_scale_1pct"]["cells"]
    assert [c["text"] for c in scale[1:]] == ["1.200", "0.800", "6.100", "0.0229", "0.0115", "0.0000", "4.900"]
    assert float(scale[3]["value"]) == 0.0061


def test_a_report_of_an_earlier_budget_is_still_drawn(passing: dict[str, Any]) -> None:
    """A run directory from before the budget was judged at the allowance (no at_allowance, per-unit names)."""
    from cellcal.core.calibration.budget import budget_line

    data = copy.deepcopy(passing)
    old = data["calibrate"]["result"]["summary"]["error_budget"]
    for block in [old["consensus"], *old["poses"]]:
        block.pop("at_allowance"), block.pop("judged")
        block["dominant"] = {"tilt": "arm_accuracy", "height": "depth_scale_1pct"}
    page = parse(render_html(data, []))
    text = "".join(page.text)
    assert "depth scale (1 %) dominates" in text
    marked = [r["attrs"]["data-term"] for r in page.rows if "dominant" in _class(r)]
    assert marked == ["depth_scale"]
    assert not [r for r in page.rows if _class(r) == "budget-pose"]
    assert budget_line(old).startswith("error budget, height: depth scale (1 %) dominates per unit")


def test_the_handeye_report_judged_at_the_allowance() -> None:
    from cellcal.core.calibration.budget import handeye_budget_line

    budget = copy.deepcopy(HANDEYE_BUDGET)
    budget["at_allowance"] = {
        "depth_scale": {k: v * 0.2 for k, v in HANDEYE_BUDGET["terms"]["depth_scale_1pct"].items()},
        "depth_offset": {k: v * 5.0 for k, v in HANDEYE_BUDGET["terms"]["depth_offset_1mm"].items()},
        "arm_accuracy": HANDEYE_BUDGET["terms"]["arm_accuracy"]}
    budget.update(judged="allowance", dominant="depth_offset")
    arm = copy.deepcopy(budget)
    arm["dominant"] = "arm_accuracy"                # a key of both tables: highlighted in the judged one only
    rows = parse(render_html(_handeye(arm), [])).rows
    assert [_class(r) for r in rows if "dominant" in _class(r)] == ["handeye-budget-allowance dominant"]
    page = parse(render_html(_handeye(budget), []))
    judged = {str(r["attrs"]["data-term"]): r for r in page.rows if _class(r).startswith("handeye-budget-allowance")}
    assert list(judged) == ["depth_scale", "depth_offset", "arm_accuracy"]
    assert [k for k, r in judged.items() if "dominant" in _class(r)] == ["depth_offset"]
    assert judged["depth_offset"]["cells"][3]["text"] == "5.000"                       # tz: 5 x 1 mm of offset
    per_unit = [r for r in page.rows if _class(r).split() and _class(r).split()[0] == "handeye-budget"]
    assert len(per_unit) == 3 and not any("dominant" in _class(r) for r in per_unit)
    assert "depth offset dominates" in "".join(page.text)
    assert handeye_budget_line({"error_budget": budget}) == (
        "error budget of the mount: depth offset dominates (depth offset 5 mm, 0 deg; depth scale 1.2 mm, 0.0046 deg; "
        "arm accuracy 0.5 mm, 0.11 deg; per 1 % scale 6.1 mm, per 1 mm offset 1 mm): run cellcal depthcal")
