"""``cellcal devices``: the registry as a user sees it."""

from __future__ import annotations

import importlib.util

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
    assert main(["devices", "--scan", "--hosts", "127.0.0.1", "--timeout", "0.5"]) == 0
    out = capsys.readouterr().out
    scan = out.split("scan:")[1]
    lines = [line.strip() for line in scan.strip().splitlines()]
    # every registered backend is reported once, with what discovery found or why it could not look
    names = [line.split(":")[0] for line in lines]
    assert len(names) == len(set(names)) and {"camera sim", "camera oak", "camera o3r", "arm sim", "arm xarm"} <= set(
        names)
    assert "camera sim: no discovery (this backend cannot look for devices; configure its address)" in lines
    oak = [line for line in lines if line.startswith("camera oak:")]
    if importlib.util.find_spec("depthai") is None:
        # without its SDK the OAK backend cannot look, and says why
        assert len(oak) == 1 and oak[0].startswith("camera oak: unavailable:") and "depthai" in oak[0]
    else:
        # with depthai installed discovery runs and ends: no device attached here, or the devices it found
        assert oak and not any("unavailable" in line for line in oak)
