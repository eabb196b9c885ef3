"""The service's deployment files (docs/service/): the systemd unit and the container file run ``cellcal serve``
with the token from a file, never on the command line or in the environment they set, and with options the
command's own parser accepts. Neither is built or started here (no systemd or container engine in the tests).
"""

from __future__ import annotations

import json
import re
import shlex

from repo_paths import REPO_ROOT

from cellcal.core.cli.app import build_parser

UNIT = REPO_ROOT / "docs" / "service" / "cellcal-serve.service"
CONTAINERFILE = REPO_ROOT / "docs" / "service" / "Containerfile"


def parse_unit(text: str) -> dict[str, dict[str, list[str]]]:
    """A systemd unit's sections -> key -> values (a key may repeat); comments dropped, ``\\`` lines joined."""
    sections: dict[str, dict[str, list[str]]] = {}
    current: dict[str, list[str]] | None = None
    logical = re.sub(r"\\\n\s*", " ", text)  # a line ending in a backslash goes on on the next
    for raw in logical.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        header = re.fullmatch(r"\[([A-Za-z]+)\]", line)
        if header:
            current = sections.setdefault(header.group(1), {})
            continue
        key, sep, value = line.partition("=")
        assert current is not None and sep, f"not a unit line: {line!r}"
        current.setdefault(key.strip(), []).append(value.strip())
    return sections


def check_serve_argv(argv: list[str]) -> None:
    """``argv`` runs ``cellcal serve`` with a token file (no token itself), as the command's parser reads it."""
    assert argv[0].endswith("cellcal") and argv[1] == "serve", argv
    args = build_parser().parse_args(argv[1:])
    assert args.token_file, "the token must come from a file"
    assert [a for a in argv if a.startswith("--token") and a != "--token-file"] == []
    assert args.opcua_port is not None and args.opcua_cert and args.opcua_key  # a network bind: the secured face
    assert args.host == "0.0.0.0"


def test_the_systemd_unit_runs_serve_with_a_token_file() -> None:
    unit = parse_unit(UNIT.read_text(encoding="utf-8"))
    service = unit["Service"]
    (exec_start,) = service["ExecStart"]
    argv = shlex.split(exec_start)
    check_serve_argv(argv)
    token_file = argv[argv.index("--token-file") + 1]
    assert token_file == "%d/token" and "token:/etc/cellcal/token" in service["LoadCredential"]  # a credential
    assert not any("CELLCAL_SERVE_TOKEN" in e for e in service.get("Environment", []))
    assert service["KillSignal"] == ["SIGINT"] and service["SuccessExitStatus"] == ["130"]  # a run is cancelled
    assert unit["Install"]["WantedBy"] == ["multi-user.target"]


def test_the_container_file_runs_serve_with_a_secret_token_file() -> None:
    text = CONTAINERFILE.read_text(encoding="utf-8")
    entry = re.search(r"^ENTRYPOINT (\[.*\])$", text, flags=re.M)
    cmd = re.search(r"^CMD (\[.*\])$", text, flags=re.M)
    assert entry and cmd
    argv = json.loads(entry.group(1)) + json.loads(cmd.group(1))
    check_serve_argv(argv)
    assert argv[argv.index("--token-file") + 1].startswith("/run/secrets/")
    assert "CELLCAL_SERVE_TOKEN" not in text and re.search(r"^STOPSIGNAL SIGINT$", text, flags=re.M)
    assert re.search(r"^USER cellcal$", text, flags=re.M)  # not root
