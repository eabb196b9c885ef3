"""Write a configuration document as TOML (the tests' small writer; tomllib only reads)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def write_toml(path: Path, doc: dict[str, Any]) -> Path:
    def value(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(v)

    lines = []
    for table, values in doc.items():
        plain = {k: v for k, v in values.items() if not (isinstance(v, list) and v and isinstance(v[0], dict))}
        lines.append(f"[{table}]")
        lines += [f"{k} = {value(v)}" for k, v in plain.items()]
        for k, v in values.items():
            if k not in plain:
                for item in v:
                    lines.append(f"[[{table}.{k}]]")
                    lines += [f"{kk} = {value(vv)}" for kk, vv in item.items()]
    path.write_text("\n".join(lines) + "\n")
    return path
