"""The o3r-ifm3d backend without ifm3dpy: registered, and a one-line install hint instead of a traceback."""

from __future__ import annotations

import sys

import pytest

from cellcal.devices.errors import MissingDependencyError
from cellcal.devices.registry import default_registry


def test_backend_is_registered_and_names_the_missing_sdk(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in [m for m in sys.modules if m == "ifm3dpy" or m.startswith("ifm3dpy.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "ifm3dpy", None)  # "import ifm3dpy" now fails as if it were not installed
    cam = default_registry().create_camera({"backend": "o3r-ifm3d", "host": "127.0.0.1"})
    assert cam.backend_name == "o3r-ifm3d" and not cam.connected
    with pytest.raises(MissingDependencyError) as err:
        cam.connect(timeout=1.0)
    text = str(err.value)
    assert "\n" not in text
    assert text == "ifm3dpy is not installed; install it with: pip install 'cellcal[o3r-ifm3d]'"
    assert not cam.connected
