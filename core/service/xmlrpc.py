"""The service's XML-RPC face, for robot programs (URScript's ``rpc_factory("xmlrpc", URL)`` speaks only XML-RPC).

The standard library's HTTP server on its own port (``cellcal serve --xmlrpc-port N``), path
``/RPC2``, a thin adapter over :class:`~cellcal.core.service.cell.Service`:

- ``start_run([token,] kind, camera[, options])`` -> the run's id (a string);
- ``run_state(run_id)`` -> a struct (``state``, ``poses_done``, ``poses_total``, ``error``...);
  ``run_status(run_id)`` -> the state alone, a string;
- ``plane(camera)`` -> a struct: the current plane in the base frame (``normal``, ``offset_m`` with
  ``normal . x + offset_m = 0``, ``anchor_m``) and its 95 % half-widths (``tilt_halfwidth_rad``,
  ``height_halfwidth_m``);
- ``pixel_to_base(camera, u, v, flange_pose)`` -> ``[x, y, z, sigma_x, sigma_y, sigma_z]``, metres, base frame;
  ``flange_pose`` is a UR pose ``p[x, y, z, rx, ry, rz]`` (m, rotation vector in rad) as a list of 6 or the
  struct URScript sends for a pose;
- ``cancel_run([token,] run_id)`` -> the run's state struct;
- ``track_start([token,] [cell[, options]])``, ``track_stop([token,] [cell])``, ``track_state([cell])`` -> the
  session's struct (``state``, ``frames``, ``change_open``, ``drift_events``, ``last_drift``); the same for
  ``monitor_*``; ``cell`` may be left out (or "") when the service has one cell.

``camera`` is ``<cell>/<camera>``, or the camera's name alone when one cell has it. When the service
has a token, the methods that change state take it as their first argument. A request body over
:data:`MAX_BODY_BYTES` is refused (HTTP 413) before it is parsed; the XML is parsed by defusedxml (no
DTD, no entities). Every refusal is a fault whose ``faultString`` is one line and whose
``faultCode`` is the HTTP status the HTTP face would answer (:data:`FAULT_CODES`); never a traceback.
"""

from __future__ import annotations

import hmac
import http.server
import logging
import math
import socket
import threading
import xmlrpc.client
from collections.abc import Callable
from typing import Any

import numpy as np
from defusedxml.xmlrpc import DefusedExpatParser
from scipy.spatial.transform import Rotation

from cellcal.core.service.calibration import Z95
from cellcal.core.service.cell import CellService, Service
from cellcal.core.service.errors import NotFoundError, RequestError, ServiceError
from cellcal.core.service.httpguard import DEFAULT_BURST, DEFAULT_RATE_PER_S, TokenBucket, one_line
from cellcal.core.service.runs import Run
from cellcal.core.service.watch import ACTIVITIES
from cellcal.devices.errors import CellcalError

__all__ = ["FAULT_CODES", "MAX_BODY_BYTES", "RPC_PATH", "XmlRpcFace", "XmlRpcMethods", "parse_call"]

log = logging.getLogger(__name__)

#: The path the methods are served at.
RPC_PATH = "/RPC2"
#: Largest request body, bytes (a call is a few hundred bytes).
MAX_BODY_BYTES = 64 << 10
#: A body over the limit but under this is read and dropped, so the client reads the 413; beyond, the
#: connection is closed at once.
_DRAIN_BYTES = 4 << 20
#: Connections served at once; more are closed at once.
MAX_CONNECTIONS = 64
#: Seconds a connection may stay silent mid-request.
SOCKET_TIMEOUT_S = 30.0
#: faultCode -> meaning (the HTTP face's status for the same refusal).
FAULT_CODES = {400: "malformed request (not an XML-RPC call, or XML it refuses)",
               401: "a state-changing method without the right token",
               404: "no such method, cell, camera, run or calibration",
               409: "the cell is busy, the run has ended, or the cell's state cannot answer",
               422: "wrong arguments (number, type or value)",
               500: "internal error (a bug; the service keeps running)"}
#: Methods that change state (they take the token first when one is set).
STATE_CHANGING = frozenset({"start_run", "cancel_run", "track_start", "track_stop", "monitor_start", "monitor_stop"})


def parse_call(body: bytes) -> tuple[str, tuple[Any, ...]]:
    """The method name and parameters of an XML-RPC call, parsed by defusedxml (no DTD, no entities).

    Raises:
        xmlrpc.client.Fault: Code 400, naming what is wrong.
    """
    target = xmlrpc.client.Unmarshaller(use_builtin_types=True)
    parser = DefusedExpatParser(target, forbid_dtd=True)  # type: ignore[no-untyped-call]
    try:
        parser.feed(body)
        parser.close()
        params = target.close()
        method = target.getmethodname()
    except Exception as exc:  # expat's, defusedxml's and the unmarshaller's errors alike
        raise xmlrpc.client.Fault(400, one_line(f"malformed XML-RPC request: {type(exc).__name__}: {exc}")) from None
    if not isinstance(method, str) or not method:
        raise xmlrpc.client.Fault(400, "malformed XML-RPC request: no methodName")
    return method, tuple(params)


def _number(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise RequestError(f"{name} must be a finite number")
    return float(value)


def flange_pose_of(value: Any) -> dict[str, list[float]]:
    """A UR pose ``[x, y, z, rx, ry, rz]`` (m; rotation vector, rad) or URScript's pose struct, as the core's
    ``flange_pose`` (``translation_m``, ``quaternion_xyzw``).

    Raises:
        RequestError: Anything else (an empty list included: a camera on the flange needs the pose).
    """
    if isinstance(value, dict):
        value = [value.get(k) for k in ("x", "y", "z", "rx", "ry", "rz")]
    if isinstance(value, (list, tuple)) and not value:
        raise RequestError("the camera is on the flange: give the flange pose p[x, y, z, rx, ry, rz] "
                           "(get_actual_tool_flange_pose())")
    if not isinstance(value, (list, tuple)) or len(value) != 6:
        raise RequestError("flange_pose must be a pose [x, y, z, rx, ry, rz] (m, rotation vector in rad)")
    xyz = [_number(v, "flange_pose") for v in value]
    quaternion = Rotation.from_rotvec(xyz[3:]).as_quat()  # x, y, z, w
    return {"translation_m": xyz[:3], "quaternion_xyzw": [float(q) for q in quaternion]}


def run_struct(run: Run) -> dict[str, Any]:
    """A run as an XML-RPC struct (no nil: an absent text is "", an absent id -1)."""
    data = run.to_dict()
    return {"id": data["id"], "cell": data["cell"], "camera": data["camera"], "kind": data["kind"],
            "state": data["state"], "final": run.final, "poses_done": data["progress"]["poses_done"],
            "poses_total": data["progress"]["poses_total"], "error": data["error"] or "",
            "cancel_requested": data["cancel_requested"], "result_file": data["result_file"] or "",
            "history_id": -1 if run.history_id is None else run.history_id}


class XmlRpcMethods:
    """The methods, callable without a socket (:meth:`call`); thread-safe as the service is.

    Args:
        service: The service core.
        token: The token state-changing methods take first (None: none; they take none).
    """

    def __init__(self, service: Service, token: str | None = None) -> None:
        self.service = service
        self.token = token
        self._methods: dict[str, tuple[int, int, Callable[..., Any]]] = {  # fewest and most arguments
            "start_run": (2, 3, self.start_run), "run_state": (1, 1, self.run_state),
            "run_status": (1, 1, self.run_status), "plane": (1, 1, self.plane),
            "pixel_to_base": (4, 4, self.pixel_to_base), "cancel_run": (1, 1, self.cancel_run)}
        for kind in ACTIVITIES:  # track_start([cell[, options]]), track_stop([cell]), track_state([cell]); monitor_*
            self._methods.update({f"{kind}_start": (0, 2, self._watch_call(kind, "start")),
                                  f"{kind}_stop": (0, 1, self._watch_call(kind, "stop")),
                                  f"{kind}_state": (0, 1, self._watch_call(kind, "state"))})

    def call(self, method: str, params: tuple[Any, ...]) -> Any:
        """The result of ``method(*params)``.

        Raises:
            xmlrpc.client.Fault: Every refusal, with a code of :data:`FAULT_CODES` and one line.
        """
        try:
            if method not in self._methods:
                raise NotFoundError(f"no method {method!r} (methods: {', '.join(sorted(self._methods))})")
            fewest, most, function = self._methods[method]
            if method in STATE_CHANGING and self.token is not None:
                params = self._authorised(method, params)
            if not fewest <= len(params) <= most:
                takes = f"{fewest}" if fewest == most else f"{fewest} or {most}"
                raise RequestError(f"{method} takes {takes} argument{'s' if most > 1 else ''}"
                                   f"{' after the token' if method in STATE_CHANGING and self.token else ''}, "
                                   f"got {len(params)}")
            return function(*params)
        except xmlrpc.client.Fault:
            raise
        except ServiceError as exc:
            raise xmlrpc.client.Fault(exc.status, one_line(str(exc))) from None
        except CellcalError as exc:
            raise xmlrpc.client.Fault(409, one_line(f"cannot answer with the cell's current state: {exc}")) from None
        except Exception as exc:  # a bug: one line, the service goes on
            log.error("xml-rpc %s: internal error: %s: %s", method, type(exc).__name__, exc)
            raise xmlrpc.client.Fault(500, f"internal error ({type(exc).__name__}); the service keeps running") \
                from None

    def _authorised(self, method: str, params: tuple[Any, ...]) -> tuple[Any, ...]:
        assert self.token is not None
        given = params[0] if params else None
        if not isinstance(given, str) or not given:
            raise xmlrpc.client.Fault(401, f"{method} changes state: give the service's token as its first argument")
        if not hmac.compare_digest(given.encode("utf-8"), self.token.encode("utf-8")):
            raise xmlrpc.client.Fault(401, "wrong token")
        return params[1:]

    def _camera(self, name: Any) -> tuple[CellService, str]:
        """``<cell>/<camera>``, or a camera's name alone when exactly one cell has it."""
        if not isinstance(name, str) or not name:
            raise RequestError("camera must be a string: '<cell>/<camera>' or the camera's name")
        if "/" in name:
            cell, _, camera = name.partition("/")
            found = self.service.cell(cell)
            found.camera_config(camera)
            return found, camera
        having = [c for c in self.service.cells.values() if name in c.configs]
        if len(having) != 1:
            raise (NotFoundError(f"no cell has a camera {name!r}") if not having else
                   RequestError(f"cells {', '.join(c.name for c in having)} have a camera {name!r}: give "
                                "'<cell>/<camera>'"))
        return having[0], name

    def _cell(self, name: Any) -> str:
        """A cell's name, or the only cell's when none is given ("" or no argument)."""
        if name is None or name == "":
            if len(self.service.cells) != 1:
                raise RequestError(f"the service has {len(self.service.cells)} cells: name one "
                                   f"({', '.join(sorted(self.service.cells))})")
            return next(iter(self.service.cells))
        if not isinstance(name, str):
            raise RequestError("cell must be a string: the cell's name")
        return self.service.cell(name).name

    def _watch_call(self, kind: str, action: str) -> Callable[..., dict[str, Any]]:
        """``<kind>_start(cell, options)``, ``<kind>_stop(cell)``, ``<kind>_state(cell)``: the session's summary
        (``state``, ``frames``, ``change_open``, ``drift_events``, ``last_drift``...; no nil)."""

        def call(cell: Any = None, options: Any = None) -> dict[str, Any]:
            name = self._cell(cell)
            watches = self.service.watches
            if action == "start":
                if options is not None and not isinstance(options, dict):
                    raise RequestError("options must be a struct (camera, duration_s, max_frames, baseline)")
                return watches.start(name, kind, options).summary()
            if action == "stop":
                watches.stop(name, kind)
            found = watches.latest(name, kind)
            return {"kind": kind, "cell": name, "state": "idle"} if found is None else found.summary()

        return call

    def start_run(self, kind: Any, camera: Any, options: Any = None) -> str:
        """Start a ``kind`` run (calibrate, handeye, depthcal) on ``camera`` (``options``: a struct of
        ``report``, ``resume``, ``plan`` as over HTTP); its id."""
        if not isinstance(kind, str):
            raise RequestError("kind must be a string: calibrate, handeye or depthcal")
        if options is not None and not isinstance(options, dict):
            raise RequestError("options must be a struct (report, resume, plan)")
        cell, name = self._camera(camera)
        run: Run = self.service.start_run(cell.name, kind, name, options)
        return run.id

    def run_state(self, run_id: Any) -> dict[str, Any]:
        """The run's state and progress."""
        if not isinstance(run_id, str):
            raise RequestError("run_id must be a string")
        return run_struct(self.service.run(run_id))

    def run_status(self, run_id: Any) -> str:
        """The run's state alone (``queued``, ``running``, ``ok``, ``failed``, ``cancelled``): for a program that
        reads no struct."""
        state: str = self.run_state(run_id)["state"]
        return state

    def cancel_run(self, run_id: Any) -> dict[str, Any]:
        """Cancel the run (it stops at its next safe point, the arm told to stop); its state."""
        if not isinstance(run_id, str):
            raise RequestError("run_id must be a string")
        return run_struct(self.service.cancel_run(run_id))

    def plane(self, camera: Any) -> dict[str, Any]:
        """The camera's current plane in the base frame and its 95 % half-widths."""
        cell, name = self._camera(camera)
        calibration = cell.calibration(name)
        if calibration is None:
            raise NotFoundError(f"camera {name!r} of cell {cell.name!r} has no calibration yet")
        data = calibration.to_dict()
        plane = data["plane_base"]
        return {"cell": cell.name, "camera": name, "kind": data["kind"], "created_utc": data["created_utc"],
                "normal": [float(x) for x in plane["normal"]], "offset_m": float(plane["offset_m"]),
                "anchor_m": [float(x) for x in plane["anchor_m"]], "confidence": data["confidence"],
                "tilt_halfwidth_rad": [Z95 * float(s) for s in plane["tilt_sigma_rad"]],
                "height_halfwidth_m": float(plane["height_halfwidth_m"])}

    def pixel_to_base(self, camera: Any, u: Any, v: Any, flange_pose: Any) -> list[float]:
        """Pixel ``(u, v)`` seen from ``flange_pose`` -> ``[x, y, z, sigma_x, sigma_y, sigma_z]`` (m, base frame)."""
        cell, name = self._camera(camera)
        pixel = [_number(u, "u"), _number(v, "v")]
        cell.flange_config(name)
        found = cell.pixel_to_base(name, pixel, flange_pose_of(flange_pose))
        values = np.concatenate([found.points_m[0], found.sigma_m[0]])
        if not np.all(np.isfinite(values)):
            raise RequestError(f"the ray of pixel ({pixel[0]:g}, {pixel[1]:g}) misses the calibrated plane")
        return [float(x) for x in values]


class _Handler(http.server.BaseHTTPRequestHandler):
    """One connection: POST /RPC2 with a bounded body; anything else a plain HTTP refusal."""

    server: _Server
    protocol_version = "HTTP/1.1"
    timeout = SOCKET_TIMEOUT_S

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("xml-rpc %s: " + format, self.client_address[0], *args)

    def _plain(self, status: int, text: str, headers: dict[str, str] | None = None) -> None:
        body = (one_line(text) + "\n").encode("utf-8")
        self.send_response(status)
        self.send_header("Content-Type", "text/plain; charset=utf-8")
        self.send_header("Content-Length", str(len(body)))
        for key, value in (headers or {}).items():
            self.send_header(key, value)
        self.end_headers()
        self.wfile.write(body)

    def do_GET(self) -> None:
        self.close_connection = True
        self._plain(405, f"XML-RPC: POST a call to {RPC_PATH}", {"Allow": "POST"})

    def do_POST(self) -> None:
        refusal = self._refusal()
        if refusal is not None:
            self.close_connection = True
            self._plain(*refusal)
            return
        body = self.rfile.read(int(self.headers["Content-Length"]))
        try:
            method, params = parse_call(body)
            response = xmlrpc.client.dumps((self.server.methods.call(method, params),), methodresponse=True)
        except xmlrpc.client.Fault as fault:
            response = xmlrpc.client.dumps(fault, methodresponse=True)
        data = response.encode("utf-8")
        self.send_response(200)
        self.send_header("Content-Type", "text/xml")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    def _refusal(self) -> tuple[int, str] | tuple[int, str, dict[str, str]] | None:
        """Why the request is refused before its body is parsed (status, line[, headers]); None: it is not."""
        if self.path != RPC_PATH:
            return 404, f"no such path: XML-RPC is served at {RPC_PATH}"
        wait = self.server.bucket.take(self.client_address[0])
        if wait > 0:
            return 429, f"too many requests; retry in {wait:.3f} s", {"Retry-After": str(max(1, round(wait + 0.5)))}
        if self.headers.get("Content-Encoding", "identity").lower() != "identity":
            return 415, "compressed requests are not accepted"
        try:
            size = int(self.headers.get("Content-Length", ""))
        except ValueError:
            return 411, "a Content-Length is needed"
        if size < 0:
            return 400, "malformed Content-Length"
        if size > self.server.max_body_bytes:
            if size <= _DRAIN_BYTES:  # read and dropped unparsed, so that the client sees the answer
                left = size
                while left > 0:
                    chunk = self.rfile.read(min(left, 1 << 16))
                    if not chunk:
                        break
                    left -= len(chunk)
            return 413, f"request body over {self.server.max_body_bytes} bytes"
        return None


class _Server(http.server.ThreadingHTTPServer):
    daemon_threads = True
    methods: XmlRpcMethods
    bucket: TokenBucket
    max_body_bytes: int
    slots: threading.BoundedSemaphore

    def process_request(self, request: Any, client_address: Any) -> None:
        if not self.slots.acquire(blocking=False):  # too many connections: this one is closed at once
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self.slots.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self.slots.release()


class XmlRpcFace:
    """The XML-RPC server of ``service`` on ``host:port`` (0: any free port), in a thread of its own.

    Args:
        service: The service core.
        host: Address to bind (the HTTP face's: loopback unless told otherwise).
        port: Port (0: any free one; :attr:`port` tells which).
        token: The token state-changing methods take first (None: none).
        max_body_bytes: Largest request body (413 beyond, unparsed).
        rate_per_s, burst: Each client's token bucket (429 when empty).
    """

    def __init__(self, service: Service, host: str = "127.0.0.1", port: int = 0, *, token: str | None = None,
                 max_body_bytes: int = MAX_BODY_BYTES, rate_per_s: float = DEFAULT_RATE_PER_S,
                 burst: int = DEFAULT_BURST) -> None:
        server_class = type("_Server6", (_Server,), {"address_family": socket.AF_INET6}) if ":" in host else _Server
        self._server = server_class((host, port), _Handler, bind_and_activate=True)
        self._server.methods = XmlRpcMethods(service, token)
        self._server.bucket = TokenBucket(rate_per_s, burst)
        self._server.max_body_bytes = max_body_bytes
        self._server.slots = threading.BoundedSemaphore(MAX_CONNECTIONS)
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        """The port it listens on."""
        return int(self._server.server_address[1])

    @property
    def url(self) -> str:
        """``http://HOST:PORT/RPC2``."""
        host = str(self._server.server_address[0])
        return f"http://{f'[{host}]' if ':' in host else host}:{self.port}{RPC_PATH}"

    def start(self) -> XmlRpcFace:
        """Serve in a daemon thread; returns itself."""
        self._thread = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="cellcal-xmlrpc", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop serving and close the socket. Idempotent."""
        if self._thread is not None:
            self._server.shutdown()
            self._thread.join()
            self._thread = None
        self._server.server_close()

    def __enter__(self) -> XmlRpcFace:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
