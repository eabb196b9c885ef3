"""The report in a real headless browser: Debian's chromium driven by playwright (system executable, no download).

Every picture loads (``naturalWidth > 0``), nothing is fetched from the network, and the console
has no errors. Skipped, saying which, only when ``/usr/bin/chromium`` or playwright is absent
(``.ci/run`` installs both).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from cellcal.core.cli import main

CHROMIUM = Path("/usr/bin/chromium")


def test_every_picture_loads_and_the_console_is_clean(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} is not installed (apt-get install chromium)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (pip install playwright)")
    out = tmp_path / "run"
    assert main(["calibrate", "--quiet", "--out", str(out)]) == 0
    page_path = (out / "report.html").resolve()
    messages: list[str] = []
    requests: list[str] = []
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), headless=True, timeout=60_000)
        try:
            page = browser.new_page()
            page.on("console", lambda msg: messages.append(f"{msg.type}: {msg.text}"))
            page.on("pageerror", lambda exc: messages.append(f"pageerror: {exc}"))
            page.on("request", lambda req: requests.append(req.url))
            page.goto(page_path.as_uri(), wait_until="load", timeout=60_000)
            widths = page.eval_on_selector_all("img", "imgs => imgs.map(i => [i.complete, i.naturalWidth])")
            title = page.title()
        finally:
            browser.close()
    assert len(widths) == 8
    assert all(complete and width > 0 for complete, width in widths), widths
    assert not [m for m in messages if m.startswith(("error", "pageerror"))], messages
    assert all(url.startswith(("file:", "data:")) for url in requests), requests
    assert title == "cellcal calibrate report - camera sim (cell 'paper-sim')"
