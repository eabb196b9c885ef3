"""``cellcal devices``: the registry as a user sees it."""

from __future__ import annotations

import pytest

from cellcal.core.cli import main


def test_lists_backends_with_their_origin(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["devices"]) == 0
    out = capsys.readouterr().out
    cams = out.split("arms:")[0]
    arms = out.split("arms:")[1]
    for name in ("sim", "o3r", "oak"):
        assert f"  {name} " in cams
    for name in ("sim", "xarm", "ur"):
        assert f"  {name} " in arms
    assert "cellcal.sims.camera:SimCamera  [cellcal 0.1.0]" in cams


def test_scan_reports_every_backend_without_failing(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["devices", "--scan", "--timeout", "0.5"]) == 0
    out = capsys.readouterr().out
    scan = out.split("scan:")[1]
    # the OAK backend can discover; with no device attached it says so (or why it cannot look)
    assert "camera oak: no devices found" in scan or "camera oak: unavailable:" in scan
