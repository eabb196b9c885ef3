"""The report page: parsed, every embedded picture decodes, and its numbers are the result's."""

from __future__ import annotations

import base64
import json
import re
from html.parser import HTMLParser
from pathlib import Path
from typing import Any

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")
pytest.importorskip("matplotlib")

from cellcal.core.report.html import render_html  # noqa: E402
from cellcal.core.report.render import pictures, render_to_file  # noqa: E402
from cellcal.devices.errors import ConfigError  # noqa: E402


class Page(HTMLParser):
    """The images, the number cells (by row) and the text of a page."""

    def __init__(self) -> None:
        super().__init__()
        self.images: list[dict[str, str | None]] = []
        self.rows: list[tuple[dict[str, str | None], list[str]]] = []
        self.text: list[str] = []
        self.external: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if tag == "img":
            self.images.append(a)
        if tag == "tr":
            self.rows.append((a, []))
        if tag == "td" and "data-value" in a and self.rows:
            self.rows[-1][1].append(str(a["data-value"]))
        for key in ("src", "href"):
            value = a.get(key) or ""
            if value and not value.startswith("data:"):
                self.external.append(value)

    def handle_data(self, data: str) -> None:
        self.text.append(data)


def parse(page: str) -> Page:
    parser = Page()
    parser.feed(page)
    parser.close()
    return parser


def test_page_embeds_every_picture_and_shows_the_results_numbers(passing: dict[str, Any]) -> None:
    pics = pictures(passing)
    page = parse(render_html(passing, pics))
    assert page.external == []  # nothing to fetch: one self-contained file
    assert len(page.images) == len(pics) == 3 * 2 + 2
    for img in page.images:
        src = str(img["src"])
        assert src.startswith("data:image/png;base64,")
        image = cv2.imdecode(np.frombuffer(base64.b64decode(src.split(",", 1)[1]), np.uint8), cv2.IMREAD_COLOR)
        assert image is not None and image.shape[0] > 200 and image.shape[1] > 400
    result = passing["calibrate"]["result"]
    pose_rows = [cells for attrs, cells in page.rows if attrs.get("class") == "pose"]
    assert len(pose_rows) == len(result["poses"])
    for cells, pose in zip(pose_rows, result["poses"], strict=True):
        ff, exp = pose["full_frame"], pose["expected"]
        expected = [ff["tilt_x_deg"], ff["tilt_y_deg"], ff["height_m"], exp["tilt_x_deg"], exp["height_m"],
                    ff["residual_rms_m"]]
        assert [float(c) for c in cells] == expected
    method_rows = {str(attrs["data-method"]): cells for attrs, cells in page.rows if attrs.get("class") == "method"}
    for name, groups in result["summary"]["methods"].items():
        g = groups["all"]
        assert [float(c) for c in method_rows[name]] == [g["mean_angle_deg"], g["mean_error_pct"], g["max_error_pct"]]
    text = "".join(page.text)
    assert f"{result['poses'][0]['full_frame']['tilt_x_deg']:.4f}" in text
    assert result["summary"]["plane_consistency"]["verdict"] in text


def test_a_failed_run_says_why_on_the_page(refused: dict[str, Any]) -> None:
    page = parse(render_html(refused, pictures(refused)))
    text = "".join(page.text)
    assert "The run failed:" in text and "quality gate 'expected_plane' failed" in text
    assert "failed: expected_plane" in text
    assert len(page.images) == 3  # the refused pose's two pictures and the tilt/height one


@pytest.mark.parametrize(("document", "message"), [
    ({"schema": "cellcal.report/9"}, "schema 'cellcal.report/9'; expected 'cellcal.report/1'"),
    ({"schema": "cellcal.report/1", "kind": "calibrate", "calibrate": {"poses": [{"index": "a"}]}},
     "malformed report data: ValueError"),
    ({"schema": "cellcal.report/1", "kind": "handeye", "handeye": {"result": {"mount": {"translation_m": 1}}}},
     "malformed report data: "),
])
def test_report_data_that_cannot_be_drawn_is_refused_in_one_line(tmp_path: Path, document: dict[str, Any],
                                                                  message: str) -> None:
    (tmp_path / "report-data.json").write_text(json.dumps(document))
    with pytest.raises(ConfigError, match=re.escape(message)) as info:
        render_to_file(tmp_path, tmp_path / "page.html")
    assert "\n" not in str(info.value) and "report-data.json" in str(info.value)
    assert not (tmp_path / "page.html").exists()
