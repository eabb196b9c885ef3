"""docs/extending.md, part 1, runs exactly as written: from an empty folder to a passing kit and a calibration.

Every fenced block whose info string holds ``file=PATH`` is written to an empty folder;
every ```` ```console run ```` block is run there, command by command (lines starting
with ``$ ``), in a fresh virtual environment, and the output the doc shows under each
command must appear in what it prints: a line ``...`` skips any lines, `` ... `` inside
a line matches anything, whitespace runs compare equal.

The fresh environment stands for the doc's step 0 ("a virtual environment with cellcal
installed"): it sees this checkout's environment through a ``.pth`` file and has ``cellcal``
and ``pip`` commands; ``pip`` installs offline (no index, no build isolation), into it only.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import sysconfig
from dataclasses import dataclass
from pathlib import Path

import pytest
from repo_paths import REPO_ROOT

DOC = REPO_ROOT / "docs" / "extending.md"
FENCE = re.compile(r"^```(\w*)([^\n]*)\n(.*?)^```[ \t]*$", re.M | re.S)
WILDCARD = re.compile(r"(?:^|\s)\.\.\.(?:\s|$)")


@dataclass(frozen=True)
class Step:
    """A file to write (``path``) or a console block to run (``path`` None)."""

    path: str | None
    body: str


def doc_steps(text: str) -> list[Step]:
    """The marked blocks of the doc, in order."""
    steps = []
    for lang, info, body in FENCE.findall(text):
        words = info.split()
        files = [w.removeprefix("file=") for w in words if w.startswith("file=")]
        if files:
            steps.append(Step(files[0], body))
        elif lang == "console" and "run" in words:
            steps.append(Step(None, body))
    return steps


def commands(block: str) -> list[tuple[str, list[str]]]:
    """``(command, expected output lines)`` per ``$ `` line of a console block."""
    out: list[tuple[str, list[str]]] = []
    for line in block.splitlines():
        if line.startswith("$ "):
            out.append((line[2:], []))
        elif out:
            out[-1][1].append(line)
    return out


def _normal(line: str) -> str:
    return " ".join(line.split())


def _pattern(expected: str) -> re.Pattern[str]:
    return re.compile(".*".join(re.escape(_normal(part)) for part in WILDCARD.split(expected)))


def shows(expected: list[str], actual: str) -> str | None:
    """None if ``actual`` shows ``expected`` (see the module docstring), else the first line not found."""
    lines = [_normal(x) for x in actual.splitlines()]
    i, skipping = 0, False
    for want in expected:
        if want.strip() == "...":
            skipping = True
            continue
        pattern = _pattern(want)
        while i < len(lines) and not pattern.fullmatch(lines[i]):
            if not skipping:
                return want
            i += 1
        if i == len(lines):
            return want
        i, skipping = i + 1, False
    return None if skipping or i == len(lines) else f"(unexpected extra output: {lines[i]!r})"


def fresh_venv(root: Path) -> dict[str, str]:
    """A new virtual environment that sees this one's packages and has a ``cellcal`` command; its environ."""
    venv = root / "venv"
    # without its own pip and setuptools: it uses this environment's (a current setuptools builds wheels)
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=300)
    py = venv / "bin" / "python"
    purelib = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             check=True, capture_output=True, text=True, timeout=60).stdout.strip()
    here = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    Path(purelib, "cellcal-checkout.pth").write_text(
        "".join(f"import site; site.addsitedir({d!r})\n" for d in sorted(here)))
    for name, module, function in (("cellcal", "cellcal.core.cli", "main"), ("pip", "pip._internal.cli.main", "main")):
        launcher = venv / "bin" / name
        launcher.write_text(f"#!{py}\nimport sys\nfrom {module} import {function}\nsys.exit({function}())\n")
        launcher.chmod(0o755)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env.update(PATH=f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}", VIRTUAL_ENV=str(venv),
               PIP_NO_INDEX="1", PIP_NO_BUILD_ISOLATION="0", PIP_DISABLE_PIP_VERSION_CHECK="1")
    return env


def test_the_markers_find_part_one() -> None:
    steps = doc_steps(DOC.read_text())
    files = [s.path for s in steps if s.path]
    assert files == ["pyproject.toml", "src/zcam_cellcal/__init__.py", "src/zcam_cellcal/camera.py",
                     "tests/test_conformance.py", "cell.toml"]
    run = [c for s in steps if s.path is None for c, _ in commands(s.body)]
    assert run[0] == 'pip install -q ".[test]"'
    assert any(c.startswith("cellcal calibrate --config cell.toml") for c in run)


def test_the_output_matcher() -> None:
    out = "cameras:\n  sim   cellcal.sims.camera:SimCamera  [cellcal 0.1]\n  zcam  zcam:ZCam  [x 1]\narms:\n"
    assert shows(["cameras:", "...", "  zcam ... zcam:ZCam [x 1]", "arms:"], out) is None
    assert shows(["cameras:", "  zcam ... zcam:ZCam [x 1]"], out) == "  zcam ... zcam:ZCam [x 1]"
    assert shows(["14 passed in ..."], "14 passed in 2.01s") is None
    assert shows(["14 passed in ..."], "13 passed, 1 failed in 2.01s") == "14 passed in ..."
    assert shows([".... [100%]"], "..... [100%]") == ".... [100%]"


@pytest.mark.slow
def test_part_one_runs_as_written(tmp_path: Path) -> None:
    env = fresh_venv(tmp_path)
    folder = tmp_path / "cellcal-zcam"
    folder.mkdir()
    for step in doc_steps(DOC.read_text()):
        if step.path is not None:
            target = folder / step.path
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_text(step.body)
            continue
        for command, expected in commands(step.body):
            done = subprocess.run(command, shell=True, cwd=folder, env=env, capture_output=True, text=True,
                                  timeout=300)
            assert done.returncode == 0, f"$ {command}\nexit {done.returncode}\n{done.stdout}\n{done.stderr}"
            missing = shows(expected, done.stdout)
            assert missing is None, f"$ {command}: the doc shows {missing!r}; it printed:\n{done.stdout}"
    # the run really is the doc's: eight poses from four sides, consistent
    assert (folder / "out" / "result.json").stat().st_size > 10_000
