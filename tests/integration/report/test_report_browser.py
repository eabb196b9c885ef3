"""The report in a real headless browser: Debian's chromium driven by playwright (system executable, no download).

Every picture loads (``naturalWidth > 0``), nothing is fetched from the network, and the console
has no errors. Skipped, saying which, only when ``/usr/bin/chromium`` or playwright is absent
(``.ci/run`` installs both).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from cellcal.core.cli import main
from tests.support.browser import chromium_page, require_browser


def test_every_picture_loads_and_the_console_is_clean(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    require_browser()  # before the run: skipped, saying which, without chromium or playwright
    out = tmp_path / "run"
    assert main(["calibrate", "--quiet", "--out", str(out)]) == 0
    page_path = (out / "report.html").resolve()
    messages: list[str] = []
    requests: list[str] = []
    with chromium_page(messages, requests) as page:
        page.goto(page_path.as_uri(), wait_until="load", timeout=60_000)
        widths = page.eval_on_selector_all("img", "imgs => imgs.map(i => [i.complete, i.naturalWidth])")
        title = page.title()
    assert len(widths) == 8
    assert all(complete and width > 0 for complete, width in widths), widths
    assert not [m for m in messages if m.startswith(("error", "pageerror"))], messages
    assert all(url.startswith(("file:", "data:")) for url in requests), requests
    assert title == "cellcal calibrate report - camera sim (cell 'paper-sim')"
