"""What import-linter cannot check: what a fresh interpreter actually loads.

The dependency rules themselves are import-linter contracts in pyproject.toml
(``lint-imports`` in .ci/run). This test imports ``cellcal.core`` and then every module
of core and devices in a fresh interpreter and asserts that no vendor SDK, driver or sim
was loaded on the way (an SDK may arrive through a third-party package, which the
contracts do not see).
"""

from __future__ import annotations

import json
import subprocess
import sys

from repo_paths import REPO_ROOT

#: Top-level names of the vendor SDKs (and other heavy optional packages) core must not load.
VENDOR_SDKS = ("ifm3dpy", "depthai", "rtde_control", "rtde_receive", "xarm", "serial", "usb", "open3d")

_PROBE = """
import importlib, json, pkgutil, sys
import cellcal.core
after_core = sorted(sys.modules)
for pkg in ("cellcal.core", "cellcal.devices"):
    root = importlib.import_module(pkg)
    for info in pkgutil.walk_packages(root.__path__, prefix=pkg + "."):
        if not info.name.endswith("__main__"):
            importlib.import_module(info.name)
print(json.dumps({"core": after_core, "all": sorted(sys.modules)}))
"""


def _under(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def _unwanted(modules: list[str]) -> list[str]:
    return [m for m in modules
            if m.split(".")[0] in VENDOR_SDKS or _under(m, "cellcal.drivers") or _under(m, "cellcal.sims")]


def test_importing_core_loads_no_vendor_sdk_driver_or_sim() -> None:
    proc = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=120,
                          cwd=REPO_ROOT, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    loaded = json.loads(proc.stdout.strip().splitlines()[-1])
    assert "cellcal.core" in loaded["core"]
    assert _unwanted(loaded["core"]) == [], "import cellcal.core loaded these"
    assert "cellcal.core.calibration.calibrator" in loaded["all"] and "cellcal.devices.registry" in loaded["all"]
    assert _unwanted(loaded["all"]) == [], "importing every module of core and devices loaded these"
