"""``cellcal serve``: the cell's calibration service over HTTP (FastAPI under uvicorn, one worker), with
XML-RPC for robot programs and OPC UA for a PLC on ports of their own when asked.

Binds 127.0.0.1 unless ``--host`` says otherwise; any other address needs a token (from
``--token-file F`` or the environment's ``CELLCAL_SERVE_TOKEN``, never the command line),
which every state-changing request must then carry. Ctrl-C cancels a run in progress (the
arm told to stop, as a command's Ctrl-C does) and ends with exit status 130.
"""

from __future__ import annotations

import argparse
import ipaddress
import os
from typing import Any

from cellcal.core.cli.argtypes import integer, path_arg, real
from cellcal.core.cli.exits import EXIT_OK
from cellcal.core.console import say
from cellcal.devices.errors import ConfigError

__all__ = ["DEFAULT_PORT", "TOKEN_ENV", "is_loopback", "read_token", "register", "run"]

HELP = ("run the cell's calibration service over HTTP, XML-RPC and OPC UA (runs, calibration, pixel_to_base, "
        "events, history, metrics)")
#: The port served by default.
DEFAULT_PORT = 8470
#: The environment variable holding the token (when there is no --token-file).
TOKEN_ENV = "CELLCAL_SERVE_TOKEN"
#: Largest token file read, bytes.
MAX_TOKEN_BYTES = 4096
#: Shortest token accepted, characters.
MIN_TOKEN_CHARS = 16


def register(sub: Any) -> None:
    """Add the ``serve`` subcommand."""
    p = sub.add_parser("serve", help=HELP,
                       description="Serve the cell's calibration over HTTP under /v1/ (OpenAPI at /v1/openapi.json): "
                       "start a calibrate, handeye or depthcal run (one at a time per cell), follow and cancel it, "
                       "read each camera's current plane and mount with their intervals, map pixels to the plane "
                       "in the base frame (pixel_to_base), and follow it all as server-sent events (/v1/events). "
                       "Needs the 'serve' extra.")
    p.add_argument("--config", metavar="PATH", type=path_arg, action="append",
                   help="a cell configuration (TOML), once per cell; default: the packaged sim.toml")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind (default: %(default)s); any other than loopback needs a token")
    p.add_argument("--port", metavar="N", type=integer(ge=0, le=65535), default=DEFAULT_PORT,
                   help="port (default: %(default)s; 0: any free port, said on stdout)")
    p.add_argument("--token-file", metavar="F", type=path_arg,
                   help=f"file holding the token state-changing requests need as 'Authorization: Bearer <token>' "
                   f"(else the environment's {TOKEN_ENV}; never on the command line)")
    p.add_argument("--out", metavar="DIR", default="cellcal-out", type=path_arg,
                   help="output directory: each camera's runs write into DIR/<cell>/<camera>/ (default: %(default)s)")
    p.add_argument("--rate", metavar="N", type=real(gt=0, le=1e6), default=None,
                   help="requests a second each client may make (bursts of as many); beyond: 429")
    p.add_argument("--opcua-port", metavar="N", type=integer(ge=0, le=65535), default=None,
                   help="also serve OPC UA on port N (same host; 0: any free port, said on stdout); default: off")
    p.add_argument("--opcua-writable", action="store_true",
                   help="let OPC UA clients call StartRun and CancelRun (else they are refused: read-only)")
    p.add_argument("--opcua-cert", metavar="F", type=path_arg,
                   help="the OPC UA server's certificate: Basic256Sha256 SignAndEncrypt only, sessions log in with "
                   "the token (needed for a non-loopback --host)")
    p.add_argument("--opcua-key", metavar="F", type=path_arg, help="the private key of --opcua-cert (PEM or DER)")
    p.add_argument("--history", metavar="URL",
                   help="the history database: sqlite:///PATH or postgresql://user@host:port/db (default: "
                   "OUT/cellcal-history.sqlite)")
    p.add_argument("--xmlrpc-port", metavar="N", type=integer(ge=0, le=65535), default=None,
                   help="also serve XML-RPC for robot programs at http://HOST:N/RPC2 (0: any free port, said on "
                   "stdout); default: off")
    p.add_argument("--print-openapi", action="store_true",
                   help="print the HTTP API's OpenAPI schema (JSON) and exit (docs/service/openapi-v1.json is it)")
    p.set_defaults(func=run)


def is_loopback(host: str) -> bool:
    """Whether ``host`` is a loopback address (``localhost`` counts; any other name does not)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def read_token(token_file: str | None) -> str | None:
    """The token from ``token_file``, else from :data:`TOKEN_ENV`; None when neither gives one.

    Raises:
        ConfigError: An unreadable or oversized file, or a token shorter than :data:`MIN_TOKEN_CHARS`.
    """
    source = token_file or f"${TOKEN_ENV}"
    if token_file:
        from cellcal.core.cli.options import check_input_file

        check_input_file(token_file, MAX_TOKEN_BYTES)
        try:
            with open(token_file, encoding="utf-8") as fh:
                token = fh.read().strip()
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(f"cannot read the token: {getattr(exc, 'strerror', None) or exc}",
                              source=token_file) from None
    else:
        token = os.environ.get(TOKEN_ENV, "").strip()
        if not token:
            return None
    if len(token) < MIN_TOKEN_CHARS or any(c.isspace() for c in token):
        raise ConfigError(f"the token must be at least {MIN_TOKEN_CHARS} characters without spaces", source=source)
    return token


def _print_openapi() -> int:
    import json

    from cellcal.core.service.http import openapi_document

    print(json.dumps(openapi_document(), indent=2, sort_keys=True))
    return EXIT_OK


def _fastapi() -> None:
    """Refuse to start without the ``serve`` extra (one line naming it)."""
    from cellcal.devices.errors import MissingDependencyError

    try:
        import fastapi  # noqa: F401
        import uvicorn  # noqa: F401
    except ImportError as exc:
        raise MissingDependencyError(exc.name or "fastapi", "serve") from None


def run(args: argparse.Namespace) -> int:
    """Run ``cellcal serve``; returns the exit status (130 after Ctrl-C)."""
    _fastapi()
    if args.print_openapi:
        return _print_openapi()
    token = read_token(args.token_file)
    if token is None and not is_loopback(args.host):
        raise ConfigError(f"--host {args.host} is not loopback: give a token with --token-file or {TOKEN_ENV} "
                          "(every state-changing request will need it)")
    xmlrpc: Any = None
    opcua, security, opcua_port = None, None, getattr(args, "opcua_port", None)
    if opcua_port is not None:
        from cellcal.core.service.opcua_nodes import opcua_security

        security = opcua_security(is_loopback(args.host), args.opcua_cert, args.opcua_key, token)  # refused: exit 2
    from cellcal.core.service import Service
    from cellcal.core.service.http import create_app

    service = Service(args.config or [None], args.out, history=_history_url(args))
    options = {} if args.rate is None else {"rate_per_s": args.rate, "burst": max(1, int(args.rate))}
    app = create_app(service, token=token, **options)
    try:
        if opcua_port is not None:
            opcua = _start_opcua(service, args, security)
        if args.xmlrpc_port is not None:
            xmlrpc = _start_xmlrpc(service, args.host, args.xmlrpc_port, token, options)
        _serve(app, args.host, args.port, service)
    finally:
        if xmlrpc is not None:
            xmlrpc.close()
        if opcua is not None:
            opcua.stop()
        service.close()  # a run still in progress (the server stopped otherwise) is cancelled, its arm stopped
        for stopped in service.stopped:
            done = stopped.to_dict()
            say(f"cellcal serve: {stopped.kind} run {stopped.id} on {stopped.cell}/{stopped.camera} {done['state']} "
                f"at {done['progress']['poses_done']}/{done['progress']['poses_total']} poses"
                + ("; the arm was told to stop" if stopped.state == "cancelled" else ""))
    return EXIT_OK


def _start_opcua(service: Any, args: argparse.Namespace, security: Any) -> Any:
    """Start the OPC UA face (asyncua, its own thread); says once where it listens."""
    try:
        from cellcal.core.service.opcua import OpcUaFace
    except ImportError as exc:
        from cellcal.devices.errors import MissingDependencyError

        raise MissingDependencyError(exc.name or "asyncua", "serve") from None
    face = OpcUaFace(service, args.host, args.opcua_port, writable=args.opcua_writable, security=security)
    face.start()
    print(f"cellcal serve: OPC UA on {face.endpoint} ({'writable' if face.writable else 'read-only'}; security "
          f"{'None' if security is None else 'Basic256Sha256 SignAndEncrypt'})", flush=True)
    return face


def _history_url(args: argparse.Namespace) -> str:
    """``--history``, else the SQLite file beside the output (``OUT/cellcal-history.sqlite``, OUT made if new)."""
    if args.history:
        return str(args.history)
    from cellcal.core.service.history import DEFAULT_FILENAME, sqlite_url

    try:
        os.makedirs(args.out, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"cannot make the output directory: {exc.strerror or exc}", source=str(args.out)) from None
    return sqlite_url(os.path.abspath(os.path.join(args.out, DEFAULT_FILENAME)))  # HistoryStore.beside(OUT)


def _start_xmlrpc(service: Any, host: str, port: int, token: str | None, options: dict[str, Any]) -> Any:
    """Start the XML-RPC face (its own thread); says once where it listens."""
    from cellcal.core.service.xmlrpc import XmlRpcFace

    try:
        face = XmlRpcFace(service, host, port, token=token, **options).start()
    except OSError as exc:
        raise ConfigError(f"cannot serve XML-RPC on {host}:{port}: {exc.strerror or exc}") from None
    print(f"cellcal serve: XML-RPC on {face.url} (rpc_factory(\"xmlrpc\", \"{face.url}\"))", flush=True)
    return face


def _serve(app: Any, host: str, port: int, service: Any) -> None:
    """Serve ``app`` until Ctrl-C (uvicorn: programmatic, one worker); says once where it listens."""
    import uvicorn

    class Server(uvicorn.Server):
        async def startup(self, sockets: Any = None) -> None:
            await super().startup(sockets)
            for server in getattr(self, "servers", []):
                for sock in server.sockets:
                    bound = sock.getsockname()
                    print(f"cellcal serve: listening on http://{_url_host(bound[0])}:{bound[1]}/v1/ "
                          f"(cells: {', '.join(service.cells)}; Ctrl-C stops)", flush=True)

    config = uvicorn.Config(app, host=host, port=port, workers=1, log_level="warning", access_log=False,
                            lifespan="on", timeout_graceful_shutdown=3, server_header=False)
    Server(config).run()


def _url_host(host: str) -> str:
    return f"[{host}]" if ":" in host else host
