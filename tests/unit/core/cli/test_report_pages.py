"""``cellcal report DIR``: which page it opens — DIR's report.html, its one fixed camera's page, or a page named."""

from __future__ import annotations

from pathlib import Path

import pytest

from cellcal.core.cli.report import _page_of
from cellcal.devices.errors import ConfigError


def test_the_run_page_first_then_the_one_camera_page_then_none(tmp_path: Path) -> None:
    assert _page_of(tmp_path, "report.html") is None
    (tmp_path / "handeye-above.html").write_text("<html></html>")
    assert _page_of(tmp_path, "report.html") == tmp_path / "handeye-above.html"
    (tmp_path / "report.html").write_text("<html></html>")
    assert _page_of(tmp_path, "report.html") == tmp_path / "report.html"


def test_several_camera_pages_are_named_in_one_line(tmp_path: Path) -> None:
    for name in ("above", "side45"):
        (tmp_path / f"handeye-{name}.html").write_text("<html></html>")
    with pytest.raises(ConfigError) as err:
        _page_of(tmp_path, "report.html")
    text = str(err.value)
    assert "2 camera reports" in text and "handeye-above.html" in text and "handeye-side45.html" in text
    assert "\n" not in text
    assert _page_of(tmp_path / "handeye-side45.html", "report.html") == tmp_path / "handeye-side45.html"
