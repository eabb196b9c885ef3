"""Mutation testing of the critical modules with mutmut, in bounded time (ADR 0023).

Usage::

    .venv/bin/python tests/mutation/run.py                 # every module of modules.toml
    .venv/bin/python tests/mutation/run.py safety journal  # some of them
    .venv/bin/python tests/mutation/run.py --list
    .venv/bin/python tests/mutation/run.py handeye-estimator --survivors   # re-check the last run's survivors

Each module is mutated in a staged copy of the repository (never in the work tree): the
top-level folders are copied under ``cellcal/`` so that a file's path is its import name,
which is how mutmut matches a mutant to the tests that reach it. mutmut runs one module at
a time with a wall-clock bound; the kill rate per module and every surviving mutant (as a
diff) are printed and written to ``<workdir>/<module>/survivors.txt``.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import tomllib
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
MODULES = Path(__file__).with_name("modules.toml")
PACKAGES = ("configs", "core", "devices", "drivers", "sims", "testing")
#: Folders the tests read beside the package, by their path in the repository (``REPO_ROOT / "configs"``,
#: ``docs/extending.md``, ``examples/``): staged at the root as well, and copied by mutmut into ``mutants/``.
BESIDE = ("configs", "docs", "examples")
#: The project's shared data, which tests read as ``REPO_ROOT.parent / "shared"``.
SHARED = REPO.parent / "shared"
#: mutmut statuses that mean the tests noticed the mutant.
DETECTED = ("killed", "timeout", "segfault", "caught by type check")
IGNORE = shutil.ignore_patterns("__pycache__", "*.pyc", "mutants", ".hypothesis")


def stage(name: str, module: dict[str, object], workdir: Path) -> Path:
    """Copy the repository into ``workdir/name`` with the package folders under ``cellcal/``.

    What the tests read beside the package is staged too, where they look for it: mutmut runs
    them in ``root/mutants/`` (so ``REPO_ROOT`` is ``root/mutants``), with ``tests/`` (and its
    ``tests/data``) and the :data:`BESIDE` folders copied there by mutmut (``also_copy``), and
    ``root/shared`` a symlink to the shared data (``REPO_ROOT.parent / "shared"``).
    """
    root = workdir / name
    shutil.rmtree(root, ignore_errors=True)
    for package in PACKAGES:
        shutil.copytree(REPO / package, root / "cellcal" / package, ignore=IGNORE)
    shutil.copytree(REPO / "tests", root / "tests", ignore=IGNORE)
    beside = [folder for folder in BESIDE if (REPO / folder).is_dir()]
    for folder in beside:
        shutil.copytree(REPO / folder, root / folder, ignore=IGNORE)
    if SHARED.is_dir():
        (root / "shared").symlink_to(SHARED, target_is_directory=True)
    tests = [str(t) for t in module["tests"] if (REPO / str(t)).is_file()]  # type: ignore[attr-defined]
    missing = sorted(set(map(str, module["tests"])) - set(tests))  # type: ignore[call-overload]
    if missing:
        print(f"  [{name}] not in this checkout, skipped: {', '.join(missing)}")
    text = (REPO / "pyproject.toml").read_text(encoding="utf-8")
    shared = tomllib.loads(text).get("tool", {}).get("mutmut")
    if shared is None or "\n[tool.mutmut]\n" not in text:
        raise SystemExit("pyproject.toml has no [tool.mutmut] table")
    also_copy = list(dict.fromkeys([*shared.get("also_copy", []), "tests", *beside]))
    per_module = {"only_mutate": ["cellcal/" + str(module["file"])], "pytest_add_cli_args_test_selection": tests,
                  "also_copy": also_copy}
    # the staged table: pyproject's settings with this module's (TOML's strings and lists are JSON's)
    table = "".join(f"{key} = {json.dumps(value)}\n" for key, value in {**shared, **per_module}.items())
    head, _, rest = text.partition("\n[tool.mutmut]\n")
    tail = rest[rest.find("\n[") + 1:] if "\n[" in rest else ""  # the tables after [tool.mutmut]
    (root / "pyproject.toml").write_text(f"{head}\n[tool.mutmut]\n{table}\n{tail}", encoding="utf-8")
    return root


def mutmut(root: Path, args: list[str], timeout_s: float, log: Path | None = None) -> tuple[int | None, str]:
    """Run ``mutmut ARGS`` in ``root``; None as the code when it ran out of time (its group is killed)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # the staged copy must be what imports
    out = open(log, "w", encoding="utf-8") if log else subprocess.PIPE  # noqa: SIM115 (closed below)
    proc = subprocess.Popen([sys.executable, "-m", "mutmut", *args], cwd=root, env=env, stdout=out,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        text, _ = proc.communicate(timeout=timeout_s)
        return proc.returncode, text or ""
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # mutmut forks one worker per mutant: end the whole group
        proc.wait()
        return None, ""
    finally:
        if log:
            out.close()  # type: ignore[union-attr]


# Prints name, status and diff of each named mutant in one process (mutmut's `show`, without a process per mutant).
_SHOW = """
import sys
import mutmut.__main__ as mm
for name in sys.argv[1:]:
    m = mm.find_mutant(name)
    status = mm.status_by_exit_code[m.exit_code_by_key[name]]
    diff = mm.get_diff_for_mutant(name, path=m.path).splitlines()
    body = [line for line in diff if line[:1] in '+-' and line[:3] not in ('+++', '---')]
    print(name + '\\x01' + status + '\\x01' + '\\n'.join(body) + '\\x00')
"""


def statuses(root: Path, scope: list[str]) -> dict[str, str]:
    """mutmut's status of every mutant in ``scope`` (fnmatch patterns of mutant names; empty: all)."""
    _, text = mutmut(root, ["results", "--all", "true"], 120)
    rows = (line.strip().rsplit(": ", 1) for line in text.splitlines() if ": " in line)
    return {n: st for n, st in rows if not scope or any(fnmatch.fnmatchcase(n, p) for p in scope)}


def diffs(root: Path, names: list[str]) -> dict[str, str]:
    """The diff (changed lines only) of each named mutant."""
    if not names:
        return {}
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    out = subprocess.run([sys.executable, "-c", _SHOW, *names], cwd=root, env=env, capture_output=True, text=True,
                         timeout=600, check=False)
    rows = [d.strip().split("\x01") for d in out.stdout.split("\x00") if d.strip()]
    found = {r[0]: r[2] for r in rows if len(r) == 3}
    return {n: found.get(n, "(diff unavailable)") for n in names}


def recheck(root: Path, name: str) -> bool:
    """Whether a surviving mutant fails its tests in a fresh interpreter (mutant active from the first import).

    mutmut forks its workers after the modules are imported, so code that runs at import
    time (a table built once, a module constant computed by a function) never sees the
    mutant there. Each survivor's tests run once more with the mutant set from the start.
    """
    stats = json.loads((root / "mutants" / "mutmut-stats.json").read_text())
    tests = sorted(stats["tests_by_mangled_function_name"].get(name.partition("__mutmut_")[0], []))
    if not tests:
        return False
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"} | {"MUTANT_UNDER_TEST": name}
    try:
        done = subprocess.run([sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *tests],
                              cwd=root / "mutants", env=env, capture_output=True, timeout=120, check=False)
    except subprocess.TimeoutExpired:
        return True  # it hangs: the tests do not pass
    return done.returncode != 0


def last_survivors(workdir: Path, name: str) -> list[str]:
    """The mutants the previous run of module ``name`` left not killed (from its ``survivors.txt``)."""
    path = workdir / name / "survivors.txt"
    if not path.is_file():
        raise SystemExit(f"no earlier run of {name} in {workdir} (no survivors.txt): run it whole first")
    return [line.split(" (", 1)[0] for line in path.read_text(encoding="utf-8").splitlines()
            if line.startswith("cellcal.") and line.endswith(")")]


def run_module(name: str, module: dict[str, object], workdir: Path, timeout_s: float,
               children: int, only: list[str] | None = None) -> dict[str, object]:
    """Stage, mutate and test one module (only the mutants ``only`` names, when given); returns its figures."""
    print(f"[{name}] {module['file']}", flush=True)
    if only == []:
        print(f"[{name}] no mutant left to re-check")
        return {"module": name, "file": module["file"], "killed": 0, "total": 0, "rate_pct": float("nan"),
                "not_killed": 0, "survived": 0, "no_tests": 0, "seconds": 0, "complete": True, "counts": {}}
    root = stage(name, module, workdir)
    scope = only if only is not None else [str(p) for p in module.get("mutants", [])]  # type: ignore[attr-defined]
    started = time.monotonic()
    code, _ = mutmut(root, ["run", "--max-children", str(children), *scope], timeout_s, log=root / "mutmut.log")
    status = statuses(root, scope)
    counts = Counter(status.values())
    # a timeout is a mutant the tests caught (it hangs); survivors get a second chance in a fresh process
    late = {m for m, st in status.items() if st == "survived" and recheck(root, m)}
    left = sorted(m for m, st in status.items() if st not in DETECTED and m not in late)
    seconds = time.monotonic() - started
    total = len(status) - counts["not checked"] - counts["skipped"]
    killed = sum(counts[st] for st in DETECTED) + len(late)
    shown = diffs(root, left)
    (root / "survivors.txt").write_text("".join(f"{m} ({status[m]})\n{shown[m]}\n\n" for m in left),
                                        encoding="utf-8")
    rate = 100.0 * killed / total if total else float("nan")
    untested = sum(1 for m in left if status[m] == "no tests")
    print(f"[{name}] {killed}/{total} killed ({rate:.1f} %; {counts['timeout']} by a timeout, {len(late)} only in "
          f"a fresh process), {len(left) - untested} survived, {untested} reached by no test, {seconds:.0f} s"
          + ("" if code is not None else f" - STOPPED at the {timeout_s:.0f} s bound, figures are partial"), flush=True)
    for m in left:
        print(f"    {m} ({status[m]})\n      " + shown[m].replace("\n", "\n      "))
    return {"module": name, "file": module["file"], "killed": killed, "total": total, "rate_pct": round(rate, 1),
            "not_killed": len(left), "survived": len(left) - untested, "no_tests": untested,
            "seconds": round(seconds), "complete": code is not None, "counts": dict(counts)}


def main(argv: list[str] | None = None) -> int:
    """Command line entry: see the module docstring."""
    modules = tomllib.loads(MODULES.read_text(encoding="utf-8"))
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("modules", nargs="*", help=f"modules to run (default: all of {', '.join(modules)})")
    parser.add_argument("--timeout", type=float, default=900.0, help="wall-clock bound per module, s (default 900)")
    parser.add_argument("--max-children", type=int, default=1, help="parallel mutmut workers (default 1)")
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/cellcal-mutation"), help="staging folder")
    parser.add_argument("--list", action="store_true", help="list the modules and their tests, then exit")
    parser.add_argument("--mutants", nargs="+", metavar="PATTERN",
                        help="only these mutants (names or fnmatch patterns), instead of the module's selection")
    parser.add_argument("--survivors", action="store_true",
                        help="only the mutants the previous run of each module left (its survivors.txt)")
    args = parser.parse_args(argv)
    unknown = sorted(set(args.modules) - set(modules))
    if unknown:
        parser.error(f"unknown module(s) {', '.join(unknown)}; known: {', '.join(modules)}")
    if args.list:
        for name, module in modules.items():
            print(f"{name}: {module['file']} <- {' '.join(module['tests'])}")
        return 0
    names = args.modules or list(modules)
    only = {n: (last_survivors(args.workdir, n) if args.survivors else args.mutants) for n in names}
    results = [run_module(n, modules[n], args.workdir, args.timeout, args.max_children, only[n]) for n in names]
    (args.workdir / "summary.json").write_text(json.dumps(results, indent=1), encoding="utf-8")
    print("\n| module | file | mutants | killed | survived | no test reaches | score | time |\n"
          "|---|---|---|---|---|---|---|---|")
    for r in results:
        print(f"| {r['module']} | `{r['file']}` | {r['total']} | {r['killed']} | {r['survived']} | {r['no_tests']} | "
              f"{r['rate_pct']} % | {r['seconds']} s{'' if r['complete'] else ' (stopped)'} |")
    return 0 if all(r["complete"] for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
