"""Bad input: every config key and every CLI misuse -> exit 2 and ONE stderr line.

The config cases are enumerated from the schema, not listed by hand: the dataclass
fields of every top-level table (the fields of :class:`CellConfig` that are config
dataclasses, plus ``[sim]``), of every registered camera and arm backend's ``Config``
(found through the registry, so a new backend or key is covered the day it lands),
and of the tables nested in them (``[[plan.poses]]``, ``[[sim.boxes]]``,
``[sim.mount]``). For every key:

* (a) wrong types (a string where a number/bool/list/table belongs, a number where a
  string belongs, a float for an int, an int for a bool, a bool for a float, a list of
  the wrong length, ``inf`` for a float);
* (b) a value just outside each range limit of the field metadata (``gt``, ``ge``,
  ``lt``, ``le``, ``min_items``, ``max_items``, ``max_len``, the last two defaulting to
  ``devices.config.DEFAULT_LIMITS``), an integer beyond TOML's 64 bits, a string with a
  control character and, for names, a name outside the ``Literal``;
* (c) the key left out, where it has no default;

plus (d) an unknown key in every table and an unknown table. Each case is a config
file written from the packaged config that uses the backend (``configs/*.toml``; for
a backend with none, ``sim.toml`` with that section swapped in) and run through
``cellcal calibrate --check --config FILE`` in-process: ``--check`` loads the document
and builds both devices, so every backend section and ``[sim]`` are parsed, and it
touches no device. The case must exit with status 2 and print exactly one stderr line
naming the file, the dotted key and the expectation.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import tomllib
import types
import typing
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, get_args, get_origin, get_type_hints

import pytest
from fuzz_targets import CONFIG_DIR, dump_toml
from repo_paths import TEST_DATA

from cellcal.core.calibration.calibrator import build_devices
from cellcal.core.calibration.cameras import CameraPoseSection, CamerasSection
from cellcal.core.calibration.config import TOP_LEVEL_TABLES, CellConfig, load_config
from cellcal.core.calibration.sections import MountSection
from cellcal.core.cli import build_parser, main
from cellcal.devices.config import DEFAULT_LIMITS, INT_MAX, parse_section, schema_of
from cellcal.devices.registry import default_registry
from cellcal.sims.work import EventConfig
from cellcal.sims.world import SimConfig

DEFAULT_BASE = "sim.toml"
BOGUS = "bogus_key"

def _read(name: str) -> dict[str, Any]:
    return tomllib.loads((CONFIG_DIR / name).read_text(encoding="utf-8"))


# ---------------------------------------------------------------------- schema helpers


def _unwrap(tp: Any) -> Any:
    """``X | None`` -> ``X``; anything else unchanged."""
    if get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return args[0]
    return tp


def _is_seq(tp: Any) -> bool:
    return get_origin(tp) in (tuple, list)


def _fixed_len(tp: Any) -> int | None:
    args = get_args(tp)
    if get_origin(tp) is tuple and not (len(args) == 2 and args[1] is Ellipsis):
        return len(args)
    return None


def _item(tp: Any) -> Any:
    return get_args(tp)[0]


def _is_dataclass_type(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _in_range(v: Any, meta: typing.Mapping[str, Any]) -> bool:
    return not (("gt" in meta and not v > meta["gt"]) or ("ge" in meta and not v >= meta["ge"])
                or ("lt" in meta and not v < meta["lt"]) or ("le" in meta and not v <= meta["le"]))


#: Valid tables of the schemas whose required keys alone are not valid.
EXAMPLES: dict[type, dict[str, Any]] = {
    EventConfig: {"at_s": 1.0, "plane_point_m": [0.0, 0.0, 0.0], "plane_normal": [0.0, 0.0, 1.0]}}


def valid_value(tp: Any, meta: typing.Mapping[str, Any] = {}) -> Any:
    """Some value the schema accepts (to build nested tables with required keys)."""
    tp = _unwrap(tp)
    if tp is bool:
        return True
    if tp in (int, float):
        for c in (1, 2, 5, 10, 100, 1000, 10000, 0, -1):
            if _in_range(c, meta):
                return tp(c)
        raise AssertionError(f"no simple value fits {dict(meta)}")
    if tp is str:
        return "x"
    if get_origin(tp) is Literal:
        return get_args(tp)[0]
    if _is_seq(tp):
        n = _fixed_len(tp)
        if n is not None:
            return [valid_value(a, meta) for a in get_args(tp)]
        return [valid_value(_item(tp), meta)] * max(1, int(meta.get("min_items", 1)))
    if tp is dict or get_origin(tp) is dict:
        return {}
    if tp in EXAMPLES:  # a table whose validity spans its keys (e.g. an event must change something)
        return dict(EXAMPLES[tp])
    if _is_dataclass_type(tp):
        return {k: valid_value(t, m) for k, (t, d, m) in schema_of(tp).items() if d is dataclasses.MISSING}
    if tp is Any:
        return 1
    raise AssertionError(f"test does not know how to make a {tp!r}")


def _accepts_str(tp: Any) -> bool:
    if get_origin(tp) in (typing.Union, types.UnionType):
        return any(_accepts_str(a) for a in get_args(tp))
    if get_origin(tp) is Literal:
        return any(isinstance(a, str) for a in get_args(tp))
    return tp is str or tp is Any


def _type_words(tp: Any) -> tuple[str, ...]:
    """Words the 'expected ...' part of a message must contain for type ``tp``."""
    tp = _unwrap(tp)
    if tp is bool:
        return ("boolean",)
    if tp is int:
        return ("integer",)
    if tp is float:
        return ("number",)
    if tp is str:
        return ("string",)
    if get_origin(tp) is Literal:
        return tuple(repr(a) for a in get_args(tp))
    if _is_seq(tp):
        return ("list",)
    if tp is dict or get_origin(tp) is dict or _is_dataclass_type(tp):
        return ("table",)
    if get_origin(tp) in (typing.Union, types.UnionType):
        return tuple(w for a in get_args(tp) if a is not type(None) for w in _type_words(a))
    return ()


# ---------------------------------------------------------------------- tables


@dataclass(frozen=True)
class Table:
    """One table of the schema, placed in a base document.

    Attributes:
        dotted: Its dotted key in messages, e.g. ``"plan.poses[0]"``.
        path: Where it sits in the document, e.g. ``("plan", "poses", 0)``.
        cls: Its config dataclass.
        label: Names the base (file and backend) in case ids.
        doc: A valid base document that contains the table.
        ignore: Keys of the table that are not the dataclass's (``backend``).
    """

    dotted: str
    path: tuple[str | int, ...]
    cls: type
    label: str
    doc: dict[str, Any]
    ignore: tuple[str, ...] = ()


def _get(doc: Any, path: tuple[str | int, ...]) -> Any:
    for p in path:
        doc = doc[p]
    return doc


def _base_for_backend(kind: str, name: str) -> tuple[str, dict[str, Any]]:
    """The packaged config that uses backend ``name`` for ``kind``, else sim.toml with it swapped in."""
    for path in sorted(CONFIG_DIR.glob("*.toml")):
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
        if doc.get(kind, {}).get("backend") == name:
            return path.name, doc
    doc = _read(DEFAULT_BASE)
    cls = default_registry().get(kind, name).Config  # type: ignore[arg-type]
    doc[kind] = {"backend": name, **valid_value(cls)}
    return f"{DEFAULT_BASE}+{kind}={name}", doc


def _top_tables() -> Iterator[Table]:
    base = _read(DEFAULT_BASE)
    hints = get_type_hints(CellConfig)
    for f in dataclasses.fields(CellConfig):
        tp = _unwrap(hints[f.name])
        if _is_dataclass_type(tp):
            doc = json.loads(json.dumps(base))
            doc.setdefault(f.name, valid_value(tp))
            yield Table(f.name, (f.name,), tp, DEFAULT_BASE, doc)
    yield Table("sim", ("sim",), SimConfig, DEFAULT_BASE, base)
    registry = default_registry()
    for entry in registry.entries():
        cls = registry.get(entry.kind, entry.name).Config
        label, doc = _base_for_backend(entry.kind, entry.name)
        yield Table(entry.kind, (entry.kind,), cls, f"{label}[{entry.name}]", doc, ("backend",))


def _nested(table: Table) -> Iterator[Table]:
    """``table`` and every config dataclass nested in it (inserted into the document if absent)."""
    yield table
    for key, (tp, _default, _meta) in schema_of(table.cls).items():
        inner = _unwrap(tp)
        if _is_dataclass_type(inner):
            doc = json.loads(json.dumps(table.doc))
            parent = _get(doc, table.path)
            if not isinstance(parent.get(key), dict):
                parent[key] = valid_value(inner)
            yield from _nested(Table(f"{table.dotted}.{key}", (*table.path, key), inner, table.label, doc))
        elif _is_seq(inner) and _is_dataclass_type(_item(inner)):
            doc = json.loads(json.dumps(table.doc))
            parent = _get(doc, table.path)
            if not parent.get(key):
                parent[key] = [valid_value(_item(inner))]
            yield from _nested(Table(f"{table.dotted}.{key}[0]", (*table.path, key, 0), _item(inner),
                                     table.label, doc))


def _camera_tables() -> Iterator[Table]:
    """``[[cameras]]`` of configs/sim_multi.toml: a camera on the flange with its mount, a fixed one with its pose.

    Not through :func:`_nested`: an entry holds a mount or a pose by its place, never both.
    """
    multi = _read("sim_multi.toml")
    entries = multi["cameras"]
    flange = next(i for i, e in enumerate(entries) if e["on"] == "flange")
    fixed = next(i for i, e in enumerate(entries) if e["on"] == "base")
    multi["cameras"][flange].setdefault("mount", valid_value(MountSection))
    yield Table(f"cameras[{flange}]", ("cameras", flange), CamerasSection, "sim_multi.toml", multi, ("backend",))
    yield Table(f"cameras[{flange}].mount", ("cameras", flange, "mount"), MountSection, "sim_multi.toml", multi)
    yield Table(f"cameras[{fixed}].pose", ("cameras", fixed, "pose"), CameraPoseSection, "sim_multi.toml", multi)


def all_tables() -> list[Table]:
    return [t for top in _top_tables() for t in _nested(top)] + list(_camera_tables())


# ---------------------------------------------------------------------- cases


@dataclass(frozen=True)
class Case:
    """One bad config: ``doc`` must fail naming ``key`` with every word of ``expect``."""

    id: str
    doc: dict[str, Any]
    key: str
    expect: tuple[str, ...]
    table: str = ""
    kind: str = ""


def _with(table: Table, key: str, value: Any = ..., *, delete: bool = False) -> dict[str, Any]:
    doc = json.loads(json.dumps(table.doc))
    section = _get(doc, table.path)
    if delete:
        section.pop(key, None)
    else:
        section[key] = value
    return doc


def _bad_types(tp: Any) -> Iterator[tuple[str, Any, tuple[str, ...], str]]:
    """(name, value, expected words, key suffix) of wrong-typed values for ``tp``."""
    inner = _unwrap(tp)
    if inner is Any:
        return
    words = ("expected", *_type_words(tp))
    yield ("int" if _accepts_str(inner) else "str"), (42 if _accepts_str(inner) else "oops"), words, ""
    if inner is int:
        yield "float", 2.5, words, ""
        yield "int64", INT_MAX + 1, ("expected", "integer", "64-bit"), ""
    if inner is str:
        yield "control", "a\x1b[2Jb", ("expected", "string", "without control characters"), ""
    if inner is bool:
        yield "int", 1, words, ""
    if inner is float:
        yield "bool", True, words, ""
        yield "inf", math.inf, ("expected", "finite"), ""
    if get_origin(inner) is Literal and _accepts_str(inner):
        yield "name", "no_such_name", words, ""
    if _is_seq(inner):
        n = _fixed_len(inner)
        item = _unwrap(_item(inner))
        if n is not None:
            yield "length", [valid_value(a) for a in get_args(inner)] + [valid_value(item)], \
                ("expected", "list", f"{n + 1} items"), ""
        if item is float:
            yield "item-nan", [math.nan] * (n or 1), ("expected", "finite"), "[0]"
        if not _is_dataclass_type(item) and not _accepts_str(item):
            yield "item-str", ["oops"] * (n or 1), ("expected", *_type_words(item)), "[0]"
    if inner is dict or get_origin(inner) is dict or _is_dataclass_type(inner):
        yield "list", [1, 2], words, ""


_OPS = {"gt": ">", "ge": ">=", "lt": "<", "le": "<="}


def _outside(base: Any, op: str, bound: float) -> Any:
    if base is int:
        return {"gt": math.floor(bound), "ge": math.ceil(bound) - 1,
                "lt": math.ceil(bound), "le": math.floor(bound) + 1}[op]
    return {"gt": float(bound), "ge": float(bound) - 1.0, "lt": float(bound), "le": float(bound) + 1.0}[op]


def _bad_ranges(tp: Any, meta: typing.Mapping[str, Any]) -> Iterator[tuple[str, Any, tuple[str, ...]]]:
    inner = _unwrap(tp)
    seq = _is_seq(inner)
    base = _unwrap(_item(inner)) if seq else inner
    limits = {**DEFAULT_LIMITS, **meta}
    if base is str:
        n = int(limits["max_len"])
        yield "max_len", ["x" * (n + 1)] * (_fixed_len(inner) or 1) if seq else "x" * (n + 1), \
            (f"at most {n} characters",)
    if seq and _fixed_len(inner) is None:
        n = int(limits["max_items"])
        yield "max_items", [valid_value(_item(inner), meta)] * (n + 1), (f"at most {n} items",)
    if base in (int, float):
        for op, sym in _OPS.items():
            if op in meta:
                bad = _outside(base, op, meta[op])
                value = [bad] * (_fixed_len(inner) or 1) if seq else bad
                yield op, value, (f"must be {sym} {meta[op]}",)
    if seq and "min_items" in meta:
        n = int(meta["min_items"])
        yield "min_items", [valid_value(_item(inner), meta)] * (n - 1), (f"at least {n}",)


def schema_cases() -> list[Case]:
    cases: list[Case] = []
    for t in all_tables():
        tid = f"{t.label}:{t.dotted}"
        for key, (tp, default, meta) in schema_of(t.cls).items():
            dotted = f"{t.dotted}.{key}"
            for name, value, words, suffix in _bad_types(tp):
                cases.append(Case(f"{tid}.{key}:type-{name}", _with(t, key, value), dotted + suffix, words,
                                  tid, "type"))
            for name, value, words in _bad_ranges(tp, meta):
                cases.append(Case(f"{tid}.{key}:range-{name}", _with(t, key, value), dotted, words, tid, "range"))
            if default is dataclasses.MISSING:
                cases.append(Case(f"{tid}.{key}:missing", _with(t, key, delete=True), dotted, ("missing",), tid,
                                  "missing"))
        cases.append(Case(f"{tid}:unknown-key", _with(t, BOGUS, 1), f"{t.dotted}.{BOGUS}", ("unknown key",), tid,
                          "unknown"))
    return cases


def document_cases() -> list[Case]:
    """Table-level mistakes: unknown/missing tables, non-tables, backends, cross-key checks."""
    base = _read(DEFAULT_BASE)

    def doc(**changes: Any) -> dict[str, Any]:
        d = json.loads(json.dumps(base))
        for k, v in changes.items():
            if v is None:
                d.pop(k, None)
            else:
                d[k] = v
        return d

    cases = [Case("unknown-table", doc(bogus_table={"a": 1}), "bogus_table", ("unknown table",)),
             Case("missing-reference", doc(reference=None), "reference", ("[reference]",))]
    for name in TOP_LEVEL_TABLES:
        cases.append(Case(f"{name}:not-a-table", doc(**{name: 3}), name, ("expected a table",)))
    for kind in ("camera", "arm"):
        cases += [
            Case(f"{kind}:missing-table", doc(**{kind: None}), kind, ("missing table",)),
            Case(f"{kind}:missing-backend", doc(**{kind: {}}), f"{kind}.backend", ("backend",)),
            Case(f"{kind}:backend-int", doc(**{kind: {"backend": 3}}), f"{kind}.backend", ("string",)),
            Case(f"{kind}:backend-unknown", doc(**{kind: {"backend": "no_such_backend"}}), f"{kind}.backend",
                 (f"unknown {kind} backend 'no_such_backend'", "registered:")),
        ]
    # checks across keys (__post_init__): still one line naming file and table
    sim_arm = {"backend": "sim", "reach_m": 0.5, "min_radius_m": 0.6}
    cases += [
        Case("safety:min>=max", doc(safety={**base["safety"], "workspace_min_m": [0.0, 0.0, 1.0]}),
             "safety", ("workspace_min_m", "<")),
        Case("plan:window-even", doc(plan={**base["plan"], "window_px": 4}), "plan", ("odd",)),
        Case("sim:zero-normal", doc(sim={"plane_normal": [0.0, 0.0, 0.0]}), "sim.plane_normal", ("non-zero",)),
        Case("arm[sim]:reach<min_radius", doc(arm=sim_arm), "arm", ("reach_m", "min_radius_m")),
        Case("camera[sim]:max_range<min", doc(camera={"backend": "sim", "min_range_m": 3.0, "max_range_m": 2.0}),
             "camera", ("max_range_m", "min_range_m")),
        Case("arm[xarm-emulated]:firmware", doc(arm={"backend": "xarm-emulated", "firmware": "two"}),
             "arm.firmware", ("2.5.0",)),
        Case("arm[xarm]:default>max speed", doc(arm={"backend": "xarm", "default_speed_m_s": 0.5,
                                                     "max_speed_m_s": 0.2}), "arm", ("max_speed_m_s",)),
        Case("camera[o3r]:no port", doc(camera={"backend": "o3r", "port": ""}), "camera", ("pcic_port",)),
    ]
    return cases


SCHEMA_CASES = schema_cases()
DOCUMENT_CASES = document_cases()
print(f"test_bad_input: {len(SCHEMA_CASES)} schema cases over {len(all_tables())} tables, "
      f"{len(DOCUMENT_CASES)} document cases")


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def test_the_enumeration_covers_every_top_level_table() -> None:
    names = {t.path[0] for t in all_tables()}
    missing = set(TOP_LEVEL_TABLES) - names
    assert not missing, f"tables with no schema the bad-input enumeration can find: {sorted(missing)}"
    registry = default_registry()
    for kind in ("camera", "arm"):
        labels = {t.label for t in all_tables() if t.path == (kind,)}
        assert len(labels) == len(registry.names(kind)) >= 2  # type: ignore[arg-type]
    assert len(SCHEMA_CASES) > 300, len(SCHEMA_CASES)


@pytest.mark.parametrize("table", all_tables(), ids=lambda t: f"{t.label}:{t.dotted}")
def test_every_base_document_is_valid(tmp_path: Path, table: Table) -> None:
    """The cases below fail only because of their one change: the base parses (config and devices).

    A backend with no packaged config gets a synthesised section; when its constructor
    needs something outside the file (a recording, say), only its section is checked.
    """
    path = tmp_path / "base.toml"
    path.write_text(dump_toml(table.doc), encoding="utf-8")
    assert tomllib.loads(path.read_text()) == table.doc
    config = load_config(path)
    if "+" in table.label:
        kind = table.path[0]
        section = table.doc[kind]
        cls = default_registry().get(kind, section["backend"]).Config  # type: ignore[arg-type]
        parse_section(cls, section, where=str(kind), source=str(path), ignore=("backend",))
        return
    camera, arm = build_devices(config)
    assert camera.backend_name == config.camera_section["backend"]
    assert arm.inner.backend_name == table.doc["arm"]["backend"]


def _assert_one_line(code: int, err: str, *parts: str) -> str:
    lines = err.splitlines()
    assert code == 2, err
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for part in parts:
        assert part in lines[0], f"{part!r} not in {lines[0]!r}"
    return lines[0]


@pytest.mark.parametrize("case", SCHEMA_CASES + DOCUMENT_CASES, ids=lambda c: c.id)
def test_bad_config_is_one_line_naming_file_key_and_expectation(tmp_path: Path, case: Case,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "cell.toml"
    path.write_text(dump_toml(case.doc), encoding="utf-8")
    code, out, err = _run(["calibrate", "--check", "--config", str(path)], capsys)
    assert out == ""
    _assert_one_line(code, err, str(path), f"key '{case.key}'", *case.expect)


# ---------------------------------------------------------------------- the CLI itself


def _is_numeric(tp: Any) -> bool:
    """Whether an argparse ``type=`` parses numbers (and so must reject ``abc``; a path type takes both)."""
    if _accepts(tp, "abc/def"):
        return False
    for text in ("1", "2", "0.5", "1.5", "45.5", "100"):
        try:
            tp(text)
        except (ValueError, TypeError, argparse.ArgumentTypeError):
            continue
        return True
    return False


def _is_real(tp: Any) -> bool:
    return _is_numeric(tp) and any(_accepts(tp, text) for text in ("0.5", "1.5", "45.5", "100.5"))


def _accepts(tp: Any, text: str) -> bool:
    try:
        tp(text)
    except (ValueError, TypeError, argparse.ArgumentTypeError):
        return False
    return True


def _subcommands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def _numeric_options() -> list[tuple[str, list[str], str, Any, Any]]:
    """(command, required positionals, option, type, nargs) of every numeric option of every subcommand."""
    out = []
    for command, p in _subcommands().items():
        positionals = ["x" for a in p._actions if not a.option_strings and a.required]
        for action in p._actions:
            if action.option_strings and action.type is not None and _is_numeric(action.type):
                out.append((command, positionals, action.option_strings[-1], action.type, action.nargs))
    return out


NUMERIC_OPTIONS = _numeric_options()
#: Options a command checks itself when it runs (before any work), not in the parser.
RUN_TIME_CHECKED = {("paper", "--true-angle")}
PAPER_TABLE = TEST_DATA / "paper_table2.csv"


def _values(value: str, nargs: Any) -> list[str]:
    return [value] * (nargs if isinstance(nargs, int) else 1)


@pytest.mark.parametrize(("command", "positionals", "option", "tp", "nargs"), NUMERIC_OPTIONS,
                         ids=[f"{c}{o}" for c, _, o, _, _ in NUMERIC_OPTIONS])
def test_every_numeric_option_rejects_a_non_number_and_a_missing_value(
        command: str, positionals: list[str], option: str, tp: Any, nargs: Any,
        capsys: pytest.CaptureFixture[str]) -> None:
    cases = [[command, *positionals, option, *_values("abc", nargs)]]
    if nargs != "?":                            # an optional value (--viz-wait [S]) may be left out
        cases.append([command, *positionals, option])
    for argv in cases:
        with pytest.raises(SystemExit) as info:
            main(argv)
        _assert_one_line(int(info.value.code or 0), capsys.readouterr().err, option)


REAL_OPTIONS = [o for o in NUMERIC_OPTIONS if _is_real(o[3]) and o[:3:2] not in RUN_TIME_CHECKED]


@pytest.mark.parametrize(("command", "positionals", "option", "tp", "nargs"), REAL_OPTIONS,
                         ids=[f"{c}{o}" for c, _, o, _, _ in REAL_OPTIONS])
@pytest.mark.parametrize("value", ["nan", "inf"])
def test_every_real_option_rejects_non_finite_values(command: str, positionals: list[str], option: str,
                                                     tp: Any, nargs: Any, value: str,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """Checked by the parser itself (argparse ``type=``, e.g. :func:`cellcal.core.cli.argtypes.real`)."""
    with pytest.raises(SystemExit) as info:
        build_parser().parse_args([command, *positionals, option, *_values(value, nargs)])
    _assert_one_line(int(info.value.code or 0), capsys.readouterr().err, option, "finite")


@pytest.mark.parametrize(("argv", "option"), [
    (["devices", "--timeout", "0"], "--timeout"), (["devices", "--timeout", "-1"], "--timeout"),
    (["paper", "t.csv", "--fov", "0", "45"], "--fov"), (["paper", "t.csv", "--fov", "60", "180"], "--fov"),
    (["paper", "t.csv", "--image-size", "0", "172"], "--image-size"),
    (["paper", "t.csv", "--image-size", "224.5", "172"], "--image-size"),
], ids=lambda a: " ".join(a) if isinstance(a, list) else "")
def test_out_of_range_numbers_are_usage_errors(argv: list[str], option: str,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        build_parser().parse_args(argv)
    _assert_one_line(int(info.value.code or 0), capsys.readouterr().err, option)


@pytest.mark.parametrize(("argv", "option"), [
    *[(["paper", str(PAPER_TABLE), f"--true-angle={v}"], "--true-angle") for v in ("nan", "inf", "0", "-5", "91")],
], ids=lambda a: " ".join(a[:1] + a[-1:]) if isinstance(a, list) else "")
def test_options_checked_at_run_time_fail_before_any_work(argv: list[str], option: str,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    assert (argv[0], option) in RUN_TIME_CHECKED
    if argv[0] not in _subcommands():
        pytest.skip(f"no {argv[0]} subcommand in this tree")
    code = main(argv)
    _assert_one_line(code, capsys.readouterr().err, option)


@pytest.mark.parametrize("argv", [
    [], ["frobnicate"], ["calibrate", "--bogus"], ["calibrate", "--config"], ["calibrate", "--out"],
    ["calibrate", "extra-positional"], ["devices", "--scan=yes"], ["paper"], ["paper", "a.csv", "b.csv"],
    ["paper", "t.csv", "--fov", "60"], ["--version-of-nothing"],
], ids=lambda a: " ".join(a) or "<none>")
def test_cli_misuse_is_one_line_and_status_2(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(argv)
    _assert_one_line(int(info.value.code or 0), capsys.readouterr().err, "error:")


#: One case per table and kind of mistake, also run without ``--check``: the real command
#: fails the same way before it connects to anything.
SAMPLE = list({(c.table, c.kind): c for c in SCHEMA_CASES}.values())


@pytest.mark.parametrize("case", SAMPLE, ids=lambda c: c.id)
def test_calibrate_without_check_fails_the_same_way(tmp_path: Path, case: Case,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "cell.toml"
    path.write_text(dump_toml(case.doc), encoding="utf-8")
    code, out, err = _run(["calibrate", "--quiet", "--config", str(path), "--out", str(tmp_path / "out")], capsys)
    _assert_one_line(code, err, str(path), f"key '{case.key}'", *case.expect)
    assert out == "" and not (tmp_path / "out").exists()
