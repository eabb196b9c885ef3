"""MkDocs hook of the documentation site: what the site takes from the code, so it cannot fall behind.

- ``on_config``: mkdocstrings reads the sources through a view of the tree as the import name
  ``cellcal`` (the folders install under it through setuptools' package-dir, which griffe cannot
  follow): a temporary folder ``cellcal/`` of links to the folders pyproject.toml maps; the
  docstrings' Sphinx roles are read as code (griffe extension ``griffe_rst.RstRoles``).
- ``on_page_markdown`` expands four markers (ADR 0048):
  ``<!-- cli-options: NAME -->`` the usage and every option of ``cellcal NAME`` from its argparse parser;
  ``<!-- config-table: ID -->`` a configuration table's heading, its docstring and every key with type,
  default and range from its config dataclass (IDs: :func:`config_tables`);
  ``<!-- reexports: MODULE -->`` a table of the names a lazy ``__init__`` re-exports, linked to where
  each is documented; ``<!-- adr-index -->`` the list of the decision records in docs/adr/.
  A marker naming something the code does not have fails the build.

It also makes the fence words docs/extending.md's own test reads (``file=PATH``, ``run``) something the
renderer accepts (:func:`fence_titles`).

tests/docs/test_site_covers_the_code.py checks that every command and every table has its marker, once.
"""

from __future__ import annotations

import argparse
import atexit
import dataclasses
import inspect
import os
import re
import shutil
import tempfile
import tomllib
import types
import typing
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal, get_args, get_origin, get_type_hints

from mkdocs.config.defaults import MkDocsConfig
from mkdocs.exceptions import PluginError
from mkdocs.plugins import event_priority
from mkdocs.structure.files import Files
from mkdocs.structure.pages import Page

REPO = Path(__file__).resolve().parents[2]
MARKER = re.compile(r"^<!-- (cli-options|config-table|reexports): (\S+) -->$|^<!-- (adr-index) -->$", re.M)


# ------------------------------------------------------------------------------------------ sources for griffe


def source_view(repo: Path, into: Path) -> Path:
    """A folder ``into/cellcal/`` whose entries link to the repository folders pyproject.toml maps; ``into``."""
    package_dir = tomllib.loads((repo / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"][
        "package-dir"]
    root = into / "cellcal"
    root.mkdir(parents=True, exist_ok=True)
    for package, folder in package_dir.items():
        (root / package.split(".", 1)[1]).symlink_to(repo / folder, target_is_directory=True)
    return into


@event_priority(100)  # before mkdocstrings' own on_config, which hands its handlers their configuration
def on_config(config: MkDocsConfig) -> MkDocsConfig:
    view = Path(tempfile.mkdtemp(prefix="cellcal-docs-src-"))
    atexit.register(shutil.rmtree, view, ignore_errors=True)
    source_view(REPO, view)
    python = config.plugins["mkdocstrings"].config["handlers"].setdefault("python", {})
    python["paths"] = [str(view)]
    options = python.setdefault("options", {})
    options["extensions"] = [*options.get("extensions", []), f"{Path(__file__).with_name('griffe_rst.py')}:RstRoles"]
    return config


# ------------------------------------------------------------------------------------------ commands


def subcommands() -> dict[str, argparse.ArgumentParser]:
    """``cellcal``'s subcommand name -> its parser, in ``cellcal --help``'s order."""
    from cellcal.core.cli.app import build_parser

    parser = build_parser()
    (sub,) = (a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def _cell(text: str) -> str:
    return " ".join(text.split()).replace("|", "\\|").replace("<", "&lt;")


def cli_options(name: str) -> str:
    """Markdown: the usage line and a table of every argument of ``cellcal name``."""
    parsers = subcommands()
    if name not in parsers:
        raise PluginError(f"cli-options: no subcommand {name!r} (cellcal has {', '.join(parsers)})")
    parser = parsers[name]
    usage = " ".join(parser.format_usage().removeprefix("usage: ").split())
    formatter = parser._get_formatter()
    rows = []
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        if action.option_strings:
            metavar = formatter._format_args(action, action.dest.upper()) if action.nargs != 0 else ""
            names = ", ".join(f"`{s}{' ' + metavar if metavar else ''}`" for s in action.option_strings)
        else:
            names = f"`{formatter._metavar_formatter(action, action.dest)(1)[0]}`"
        rows.append(f"| {names} | {_cell(formatter._expand_help(action) if action.help else '')} |")
    return "\n".join([f"```text\n{usage}\n```", "", "| argument | what it does |", "|---|---|", *rows, ""])


# ------------------------------------------------------------------------------------------ configuration


def _unwrap(tp: Any) -> Any:
    if get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return args[0]
    return tp


def _is_dataclass(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _nested(table_id: str, cls: type, array: bool = False) -> Iterator[tuple[str, type, bool]]:
    """``(id, dataclass, is an array of tables)`` of a table and every table nested in it."""
    from cellcal.devices.config import schema_of

    yield table_id, cls, array
    for key, (tp, _default, _meta) in schema_of(cls).items():
        inner = _unwrap(tp)
        if _is_dataclass(inner):
            yield from _nested(f"{table_id}.{key}", inner)
        elif get_origin(inner) in (tuple, list) and get_args(inner) and _is_dataclass(get_args(inner)[0]):
            yield from _nested(f"{table_id}.{key}", get_args(inner)[0], True)


def config_tables() -> dict[str, tuple[type, bool]]:
    """Every table a cell configuration can hold -> (its config dataclass, is an array of tables).

    IDs are dotted TOML keys (``plan``, ``plan.poses``, ``sim.artefacts``, ``camera.model``); a
    backend's ``[camera]`` or ``[arm]`` table is ``camera:NAME`` / ``arm:NAME``.
    """
    from cellcal.core.calibration.cameras import CamerasSection
    from cellcal.core.calibration.config import CellConfig
    from cellcal.devices.correction import CorrectionSection
    from cellcal.devices.measurement import MeasurementModel
    from cellcal.devices.registry import default_registry
    from cellcal.sims.world import SimConfig

    tables: dict[str, tuple[type, bool]] = {}
    hints = get_type_hints(CellConfig)
    for f in dataclasses.fields(CellConfig):
        if _is_dataclass(_unwrap(hints[f.name])):
            tables.update((i, (c, a)) for i, c, a in _nested(f.name, _unwrap(hints[f.name])))
    tables.update((i, (c, a)) for i, c, a in _nested("cameras", CamerasSection, True))
    tables.update((i, (c, a)) for i, c, a in _nested("sim", SimConfig))
    tables.update((i, (c, a)) for i, c, a in _nested("camera.model", MeasurementModel))
    tables.update((i, (c, a)) for i, c, a in _nested("camera.correction", CorrectionSection))
    registry = default_registry()
    for entry in registry.entries():
        config_cls = registry.get(entry.kind, entry.name).Config
        tables.update((i, (c, a)) for i, c, a in _nested(f"{entry.kind}:{entry.name}", config_cls))
    return tables


def anchor(table_id: str) -> str:
    """The heading id of a table on the site: ``plan.poses`` -> ``config-plan-poses``."""
    return "config-" + re.sub(r"[^a-z0-9]+", "-", table_id.lower()).strip("-")


def title(table_id: str, array: bool) -> str:
    """How the table is written in TOML: ``[[plan.poses]]``, ``[camera] backend = "o3r"``."""
    if ":" in table_id:
        head, _, backend = table_id.partition(":")
        kind, _, rest = head.partition(".")
        return f'`[{kind}{"." + rest if rest else ""}]` `backend = "{backend.split(".")[0]}"`'
    return f"`[[{table_id}]]`" if array else f"`[{table_id}]`"


def _type_words(tp: Any) -> str:
    tp = _unwrap(tp)
    origin, args = get_origin(tp), get_args(tp)
    if origin is Literal:
        return " | ".join(f'"{a}"' if isinstance(a, str) else str(a) for a in args)
    if origin in (tuple, list):
        if len(args) == 2 and args[1] is Ellipsis:
            return f"list of {_type_words(args[0])}"
        if args and all(a == args[0] for a in args):
            return f"{len(args)} × {_type_words(args[0])}"
        return "[" + ", ".join(_type_words(a) for a in args) + "]"
    if origin in (dict, typing.Mapping) or tp is dict:
        return "table"
    if _is_dataclass(tp):
        return "table"
    return {bool: "boolean", int: "integer", float: "number", str: "string"}.get(tp, getattr(tp, "__name__", str(tp)))


def _toml(value: Any) -> str:
    if value is dataclasses.MISSING:
        return "**required**"
    if value is None:
        return "unset"
    if isinstance(value, bool):
        return "`true`" if value else "`false`"
    if isinstance(value, str):
        return f'`"{value}"`'
    if dataclasses.is_dataclass(value) or isinstance(value, dict):
        return "see below"
    if isinstance(value, (tuple, list)):
        if value and all(dataclasses.is_dataclass(v) for v in value):
            return "see below"
        return "`[" + ", ".join(_toml(v).strip("`") for v in value) + "]`"
    return f"`{value!r}`"


def _range(meta: typing.Mapping[str, Any]) -> str:
    words = [f"{sym} {meta[op]:g}" if isinstance(meta[op], float) else f"{sym} {meta[op]}"
             for op, sym in (("gt", ">"), ("ge", "≥"), ("lt", "<"), ("le", "≤")) if op in meta]
    words += [f"{w} {meta[k]} {unit}{'' if meta[k] == 1 else 's'}"
              for k, w, unit in (("min_items", "at least", "item"), ("max_items", "at most", "item"),
                                 ("max_len", "at most", "character")) if k in meta]
    return ", ".join(words)


def _docstring(cls: type) -> str:
    """The class docstring's prose (before its first Google section), roles and RST quoting made markdown."""
    text = cls.__doc__ or ""
    lines = text.expandtabs().splitlines()
    body = [lines[0].strip()] if lines else []
    indent = min((len(x) - len(x.lstrip()) for x in lines[1:] if x.strip()), default=0)
    for line in lines[1:]:
        if re.match(r"^\s*(Attributes|Args|Raises|Returns|Example|Examples|Note):\s*$", line):
            break
        body.append(line[indent:])
    prose = re.sub(r"^``\[\[?[\w.]+\]\]?``:\s*", "", "\n".join(body).strip())
    prose = prose[:1].upper() + prose[1:]
    prose = re.sub(r":\w+:`~?(?:[\w.]+\.)?([\w]+)`", r"`\1`", prose)
    return prose.replace("``", "`")


def _attribute_docs(cls: type) -> dict[str, str]:
    """``key -> text`` from the class docstring's ``Attributes:`` section."""
    text = inspect.cleandoc(cls.__doc__ or "")
    section = re.split(r"^Attributes:\s*$", text, maxsplit=1, flags=re.M)
    if len(section) < 2:
        return {}
    docs: dict[str, str] = {}
    key = ""
    for line in section[1].splitlines():
        if line and not line[0].isspace():
            break  # the next section
        found = re.match(r"^ {4}(\w+)(?: \([^)]*\))?:\s*(.*)$", line)
        if found:
            key = found[1]
            docs[key] = found[2]
        elif key and line.strip():
            docs[key] += " " + line.strip()
    return docs


def _source_comments(cls: type) -> dict[str, str]:
    """``key -> text`` from the comments at a field in the class's source (``#:`` above it, ``#`` after it)."""
    try:
        lines = inspect.getsource(cls).splitlines()
    except (OSError, TypeError):
        return {}
    docs: dict[str, str] = {}
    above: list[str] = []
    for line in lines:
        stripped = line.strip()
        if stripped.startswith("#:"):
            above.append(stripped[2:].strip())
            continue
        found = re.match(r"^\s{4}(\w+)\s*:[^#]*?(?:#\s*(.*))?$", line)
        if found and not stripped.startswith(("def ", "@")):
            text = " ".join(above) or (found[2] or "")
            if text:
                docs.setdefault(found[1], text)
        above = []
    return docs


_TOML_HEADER = re.compile(r"^#?\s*\[\[?([\w.]+)\]\]?\s*(?:#.*)?$")
_TOML_KEY = re.compile(r"^#?\s*(\w+)\s*[=:]\s*(?:\[[^#]*\]|\"[^\"]*\"|[^#\s]+)?\s*#\s*(.+)$")


def _packaged_comments(repo: Path) -> dict[tuple[str, str], str]:
    """``(table id, key) -> comment`` from the commented keys of the packaged cells (configs/*.toml)."""
    docs: dict[tuple[str, str], str] = {}
    for path in sorted((repo / "configs").glob("*.toml")):
        table = ""
        last: tuple[str, str] | None = None  # the key whose comment a comment-only line below it continues
        for line in path.read_text(encoding="utf-8").splitlines():
            more = re.match(r"^#?\s{8,}#\s*(.+)$", line)
            if more and last is not None:
                docs[last] += " " + more[1].strip()
                continue
            last = None
            header = _TOML_HEADER.match(line)
            if header:
                table = header[1]
                continue
            backend = re.match(r'^backend\s*=\s*"([\w-]+)"', line)
            if backend and table in ("camera", "arm"):
                table = f"{table}:{backend[1]}"
                continue
            found = _TOML_KEY.match(line)
            if found and table and (table, found[1]) not in docs:
                docs[(table, found[1])] = found[2].strip()
                last = (table, found[1])
    return docs


def _rst(text: str) -> str:
    """RST quoting and roles of a docstring made markdown."""
    return re.sub(r":\w+:`~?(?:[\w.]+\.)?(\w+)`", r"`\1`", text).replace("``", "`")


def config_table(table_id: str) -> str:
    """Markdown: the table's heading, docstring and one row per key."""
    from cellcal.devices.config import schema_of

    tables = config_tables()
    if table_id not in tables:
        raise PluginError(f"config-table: no table {table_id!r} (the configuration has {', '.join(tables)})")
    cls, array = tables[table_id]
    attributes, comments, packaged = _attribute_docs(cls), _source_comments(cls), _packaged_comments(REPO)
    rows = []
    for key, (tp, default, meta) in schema_of(cls).items():
        meaning = meta.get("doc") or attributes.get(key) or comments.get(key) or packaged.get((table_id, key), "")
        rows.append(f"| `{key}` | {_cell(_type_words(tp))} | {_cell(_toml(default))} | {_cell(_range(meta))} "
                    f"| {_cell(_rst(str(meaning)))} |")
    if ":" in table_id:
        backend = table_id.split(":", 1)[1].split(".")[0]
        rows.insert(0, f'| `backend` | string | **required** | `"{backend}"` | this backend |')
    heading = f"### {title(table_id, array)} {{#{anchor(table_id)}}}"
    return "\n".join([heading, "", _docstring(cls), "",
                      "| key | type | default | range | meaning |", "|---|---|---|---|---|", *rows, ""])


# ------------------------------------------------------------------------------------------ API


def reexports(module_name: str) -> str:
    """Markdown: a table of the names a lazy ``__init__`` re-exports (``_EXPORTS``), each linked to its home."""
    import importlib

    module = importlib.import_module(module_name)
    homes: dict[str, str] = getattr(module, "_EXPORTS", {})
    if not homes:
        raise PluginError(f"reexports: {module_name} has no _EXPORTS table")
    rows = []
    for name in module.__all__:
        doc = inspect.getdoc(getattr(module, name)) or ""
        rows.append(f"| [`{name}`][{homes[name]}.{name}] | `{homes[name]}` | {_cell(_rst(doc.split(chr(10))[0]))} |")
    return "\n".join(["| name | defined in | what it is |", "|---|---|---|", *rows, ""])


# ------------------------------------------------------------------------------------------ decisions


def adr_index(docs_dir: Path, page_dir: Path) -> str:
    """Markdown: one line per decision record in docs/adr/, in number order, with its title."""
    lines = []
    for path in sorted((docs_dir / "adr").glob("[0-9][0-9][0-9][0-9]-*.md")):
        first = path.read_text(encoding="utf-8").splitlines()[0].lstrip("# ").strip()
        lines.append(f"- [{first}]({Path(os.path.relpath(path, page_dir)).as_posix()})")
    return "\n".join(lines) + "\n"


#: A fence's opening line with words after its language (docs/extending.md's ``python file=PATH``, ``console run``).
_FENCE_WORDS = re.compile(r"^(?P<indent>[ \t]*)(?P<fence>`{3,})(?P<lang>\w+)[ \t]+(?P<words>[^`\n]+)$", re.M)


def fence_titles(markdown: str) -> str:
    """Fence info words the doc tests read, made what the Markdown renderer accepts.

    ``file=PATH`` becomes ``title="PATH"`` (shown above the block); other bare words (``run``) are
    dropped. Without this the renderer takes such a block for text.
    """

    def rewrite(found: re.Match[str]) -> str:
        words = found["words"].split()
        if any("=" in w and not w.startswith("file=") for w in words):
            return found[0]  # already the renderer's own options (title="...", linenums="1")
        files = [w.removeprefix("file=") for w in words if w.startswith("file=")]
        title = f' title="{files[0]}"' if files else ""
        return f"{found['indent']}{found['fence']}{found['lang']}{title}"

    return _FENCE_WORDS.sub(rewrite, markdown)


def on_page_markdown(markdown: str, page: Page, config: MkDocsConfig, files: Files) -> str:
    docs_dir = Path(config.docs_dir)
    page_dir = (docs_dir / page.file.src_path).parent

    def expand(found: re.Match[str]) -> str:
        kind, target, adr = found.groups()
        if adr:
            return adr_index(docs_dir, page_dir)
        if kind == "reexports":
            return reexports(target)
        return cli_options(target) if kind == "cli-options" else config_table(target)

    return MARKER.sub(expand, fence_titles(markdown))
