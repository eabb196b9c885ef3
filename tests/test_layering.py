"""The dependency direction of the source tree: ``core -> devices <- drivers``, ``sims -> devices``.

Every ``.py`` under core/, devices/, drivers/, sims/ and testing/ is parsed with
:mod:`ast`; each absolute ``cellcal.*`` import and each relative import (resolved
against the file's own package) counts, wherever it sits — module top level, inside a
function, under ``if TYPE_CHECKING``. The rules:

* devices imports nothing from core, drivers, sims or testing;
* core imports nothing from drivers, sims or testing (it gets devices from the registry);
* drivers and sims import nothing from each other or from testing, and from core only
  its pure geometry (:data:`PURE_GEOMETRY`);
* testing (the vendor conformance kit) imports nothing from drivers or sims.

A separate check imports ``cellcal.core`` (and every module of core and devices) in a
fresh interpreter and asserts no vendor SDK, driver or sim was loaded on the way.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
#: Source folder -> the package it is installed as (pyproject.toml package-dir).
LAYERS = {"core": "cellcal.core", "devices": "cellcal.devices", "drivers": "cellcal.drivers",
          "sims": "cellcal.sims", "testing": "cellcal.testing"}

#: The modules of core that drivers and sims may use: pure geometry with no I/O, no
#: orchestration, themselves importing only cellcal.devices (checked below).
#: cellcal.core.camera: pixel rays / projection of the OpenCV camera model (the sim camera
#: and the O3R emulator render with it; the OAK driver back-projects with it).
#: cellcal.core.transforms: vendor pose conventions (xArm mm + rpy, UR rotation vector)
#: <-> Pose (the xArm/UR drivers and the xArm emulator convert with them).
PURE_GEOMETRY = ("cellcal.core.camera", "cellcal.core.transforms")

#: Layer -> cellcal packages it must not import (prefixes, matched on whole dotted parts).
FORBIDDEN = {
    "devices": ("cellcal.core", "cellcal.drivers", "cellcal.sims", "cellcal.testing"),
    "core": ("cellcal.drivers", "cellcal.sims", "cellcal.testing"),
    "drivers": ("cellcal.sims", "cellcal.testing"),
    "sims": ("cellcal.drivers", "cellcal.testing"),
    "testing": ("cellcal.drivers", "cellcal.sims"),
}
#: Layers that may import from core only the modules in PURE_GEOMETRY.
CORE_GEOMETRY_ONLY = ("drivers", "sims")

#: Top-level names of the vendor SDKs (and other heavy optional packages) core must not load.
VENDOR_SDKS = ("ifm3dpy", "depthai", "rtde_control", "rtde_receive", "xarm", "serial", "usb", "open3d")


@dataclass(frozen=True)
class Import:
    """One ``cellcal`` import found in a source file."""

    file: Path
    line: int
    target: str
    """Dotted name imported, as finely as the statement says (``from a import b`` -> ``a.b``)."""

    def __str__(self) -> str:
        return f"{self.file.relative_to(ROOT)}:{self.line}: imports {self.target}"


def _package_of(path: Path) -> str:
    """Dotted package a source file belongs to (its own name for an ``__init__.py``)."""
    rel = path.relative_to(ROOT).with_suffix("")
    layer, *rest = rel.parts
    parts = [LAYERS[layer], *rest[:-1]]
    return ".".join(parts)


def _resolve(package: str, level: int, module: str | None) -> str:
    base = package.split(".")
    if level > 1:
        base = base[: len(base) - (level - 1)]
    return ".".join(base + ([module] if module else []))


def cellcal_imports(path: Path, source: str | None = None) -> list[Import]:
    """Every import of a ``cellcal`` module in ``path`` (relative ones resolved), by line.

    Args:
        path: The file (it decides the package relative imports resolve against).
        source: Its text; None reads the file.
    """
    text = path.read_text(encoding="utf-8") if source is None else source
    tree = ast.parse(text, filename=str(path))
    package = _package_of(path)
    found: list[Import] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.extend(Import(path, node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            module = _resolve(package, node.level, node.module) if node.level else (node.module or "")
            for alias in node.names:
                found.append(Import(path, node.lineno, module if alias.name == "*" else f"{module}.{alias.name}"))
    found.sort(key=lambda imp: imp.line)
    return [imp for imp in found if imp.target == "cellcal" or imp.target.startswith("cellcal.")]


def _under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def _sources(layer: str) -> list[Path]:
    return sorted((ROOT / layer).rglob("*.py"))


def violations(layer: str) -> list[Import]:
    """Imports in ``layer`` that break its rules."""
    bad = []
    for path in _sources(layer):
        for imp in cellcal_imports(path):
            forbidden = any(_under(imp.target, p) for p in FORBIDDEN[layer])
            impure_core = layer in CORE_GEOMETRY_ONLY and _under(imp.target, "cellcal.core") \
                and not any(_under(imp.target, m) for m in PURE_GEOMETRY)
            if forbidden or impure_core:
                bad.append(imp)
    return bad


def _report(bad: list[Import], rule: str) -> str:
    return f"{len(bad)} import(s) break '{rule}':\n" + "\n".join(f"  {imp}" for imp in bad)


def test_every_layer_folder_has_sources() -> None:
    for layer in LAYERS:
        assert _sources(layer), f"no .py files under {layer}/ (moved? update LAYERS)"


def test_the_scanner_sees_relative_nested_and_from_imports() -> None:
    # A scanner that missed an import form would let violations through.
    found = [imp.target for imp in cellcal_imports(ROOT / "sims" / "o3r" / "backend.py")]
    assert any(_under(t, "cellcal.sims.o3r.emulator") for t in found)  # from .emulator import ...
    assert any(_under(t, "cellcal.sims.camera") for t in found)  # from ..camera import ...
    source = ("import os\n"
              "import cellcal.drivers.xarm.arm\n"
              "def f():\n"
              "    from cellcal.core import calibrator\n"
              "    if True:\n"
              "        from ...drivers import ur\n"
              "    from . import wire\n")
    probe = ROOT / "sims" / "xarm" / "probe.py"  # only names the package; nothing is read or written there
    bad = [str(imp) for imp in cellcal_imports(probe, source)]
    assert bad == ["sims/xarm/probe.py:2: imports cellcal.drivers.xarm.arm",
                   "sims/xarm/probe.py:4: imports cellcal.core.calibrator",
                   "sims/xarm/probe.py:6: imports cellcal.drivers.ur",
                   "sims/xarm/probe.py:7: imports cellcal.sims.xarm.wire"]


@pytest.mark.parametrize("layer", sorted(FORBIDDEN))
def test_layer_imports_follow_the_dependency_direction(layer: str) -> None:
    bad = violations(layer)
    rule = {
        "devices": "devices imports nothing from core, drivers, sims or testing",
        "core": "core never imports drivers, sims or testing (devices come from the registry)",
        "drivers": f"drivers import no sims/testing, and from core only {', '.join(PURE_GEOMETRY)}",
        "sims": f"sims import no drivers/testing, and from core only {', '.join(PURE_GEOMETRY)}",
        "testing": "testing imports no drivers or sims",
    }[layer]
    assert not bad, _report(bad, rule)


def test_pure_geometry_modules_depend_on_devices_only() -> None:
    bad = []
    for name in PURE_GEOMETRY:
        path = ROOT / "core" / (name.rsplit(".", 1)[1] + ".py")
        bad.extend(imp for imp in cellcal_imports(path)
                   if not (_under(imp.target, "cellcal.devices") or any(_under(imp.target, m) for m in PURE_GEOMETRY)))
    assert not bad, _report(bad, "core's pure geometry imports only cellcal.devices (and itself)")


_PROBE = """
import importlib, json, pkgutil, sys
import cellcal.core
after_core = sorted(sys.modules)
for pkg in ("cellcal.core", "cellcal.devices"):
    for info in pkgutil.iter_modules(importlib.import_module(pkg).__path__):
        importlib.import_module(f"{pkg}.{info.name}")
print(json.dumps({"core": after_core, "all": sorted(sys.modules)}))
"""


def _unwanted(modules: list[str]) -> list[str]:
    return [m for m in modules
            if m.split(".")[0] in VENDOR_SDKS or _under(m, "cellcal.drivers") or _under(m, "cellcal.sims")]


def test_importing_core_loads_no_vendor_sdk_driver_or_sim() -> None:
    proc = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=120,
                          cwd=ROOT, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    loaded = json.loads(proc.stdout.strip().splitlines()[-1])
    assert "cellcal.core" in loaded["core"]
    assert _unwanted(loaded["core"]) == [], "import cellcal.core loaded these"
    assert "cellcal.core.calibrator" in loaded["all"] and "cellcal.devices.registry" in loaded["all"]
    assert _unwanted(loaded["all"]) == [], "importing every module of core and devices loaded these"
