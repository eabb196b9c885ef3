"""Debian's chromium driven by playwright for the tests that open a page in a real browser (reports, the status page).

``.ci/run`` installs ``/usr/bin/chromium``; playwright downloads no browser. Where either is missing the test
skips, saying which.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

CHROMIUM = Path("/usr/bin/chromium")
#: Milliseconds the browser's start and a page's load may take on a loaded machine.
BROWSER_TIMEOUT_MS = 60_000


def require_browser() -> Any:
    """playwright's sync API; skips the test when chromium or playwright is not installed."""
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} is not installed (apt-get install chromium)")
    return pytest.importorskip("playwright.sync_api", reason="playwright is not installed (pip install playwright)")


@contextlib.contextmanager
def chromium_page(messages: list[str], requests: list[str] | None = None) -> Iterator[Any]:
    """A new page of headless chromium, closed with the block.

    Args:
        messages: Receives every console line (``type: text``) and page error (``pageerror: ...``).
        requests: Receives the URL of every request the page makes (None: not followed).
    """
    sync_api = require_browser()
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), headless=True, timeout=BROWSER_TIMEOUT_MS)
        try:
            page = browser.new_page()
            page.on("console", lambda msg: messages.append(f"{msg.type}: {msg.text}"))
            page.on("pageerror", lambda exc: messages.append(f"pageerror: {exc}"))
            if requests is not None:
                page.on("request", lambda req: requests.append(req.url))
            yield page
        finally:
            browser.close()
