"""The service's OPC UA face (asyncua): the companion a PLC expects, a thin adapter over :class:`Service`.

It runs in a thread of its own with its own asyncio loop (:class:`OpcUaFace`: started and
stopped with the service, the stop bounded). Every node is in the namespace
:data:`~cellcal.core.service.opcua_nodes.NAMESPACE` with a string NodeId:
``.Cellcal`` (the root object) -> ``<cell>`` (the run's variables and the methods
``StartRun``, ``CancelRun``, ``PixelToBase``) -> ``<cell>/<camera>`` (the plane and the mount
with their 95 % half-widths); a variable or method is ``<object>.<Name>``. The variables follow
the service's event bus (a run's state and progress are written as its events come) and each
camera's result files are looked at once a second. The methods that change state answer
``BadUserAccessDenied`` unless the face is writable. Imported only when the face is served
(asyncua is in the ``serve`` extra).
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import logging
import math
import threading
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from asyncua import ua
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.server.server import Server
from asyncua.ua.status_codes import StatusCodes

from cellcal.core.service.cell import Service
from cellcal.core.service.errors import BusyError, NotFoundError, RequestError, ServiceError
from cellcal.core.service.opcua_nodes import (
    CAMERA_VARIABLES,
    CELL_VARIABLES,
    NAMESPACE,
    ROOT_ID,
    USERNAME,
    WATCH_VARIABLES,
    OpcUaSecurity,
    camera_values,
    cell_id,
    variable_id,
)
from cellcal.core.service.watch import watch_values
from cellcal.devices.errors import CellcalError, ConfigError

__all__ = ["APPLICATION_URI", "POLL_S", "STOP_WAIT_S", "OpcUaFace"]

log = logging.getLogger(__name__)

#: Seconds between looks at each camera's result files (a run of another process is seen within this).
POLL_S = 1.0
#: Longest wait, s, for a new event before the loop looks at its stop flag and the files.
_TICK_S = 0.25
#: Seconds :meth:`OpcUaFace.start` waits for the server to listen, and :meth:`OpcUaFace.stop` for it to end.
START_WAIT_S = 60.0
STOP_WAIT_S = 10.0
#: The server's ApplicationUri (a certificate given with --opcua-cert should name it in its subjectAltName).
APPLICATION_URI = f"{NAMESPACE}:server"
_TYPES = {"Boolean": ua.VariantType.Boolean, "String": ua.VariantType.String, "Double": ua.VariantType.Double,
          "UInt32": ua.VariantType.UInt32}
#: Events after which a cell's tracking and monitoring variables are written again.
_WATCH_EVENTS = ("track.", "monitor.", "drift.")
_STATUS = {RequestError: StatusCodes.BadInvalidArgument, NotFoundError: StatusCodes.BadNotFound,
           BusyError: StatusCodes.BadInvalidState}


class _TokenUsers:
    """Sessions log in as :data:`USERNAME` with the service's token (compared in constant time); no one else."""

    def __init__(self, token: str) -> None:
        self._token = token.encode()

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> User | None:
        given = (password or "").encode()
        if username == USERNAME and hmac.compare_digest(given, self._token):
            return User(role=UserRole.User, name=USERNAME)
        return None


def _argument(name: str, kind: str, description: str, length: int = 0) -> ua.Argument:
    """A method's argument: a scalar of ``kind``, or an array of ``length`` of them."""
    arg = ua.Argument()
    arg.Name = name
    arg.DataType = ua.NodeId(_TYPES[kind].value)  # type: ignore[arg-type]  # asyncua's own NewTypes
    arg.ValueRank = 1 if length else -1
    arg.ArrayDimensions = [length] if length else []
    arg.Description = ua.LocalizedText(description)
    return arg


class OpcUaFace:
    """The OPC UA server over ``service``, in its own thread (:meth:`start`, :meth:`stop`).

    Args:
        service: The service core.
        host: Address to bind (the CLI's ``--host``).
        port: Port (0: any free one; :attr:`port` tells which once started).
        writable: Whether ``StartRun`` and ``CancelRun`` may change state (else ``BadUserAccessDenied``).
        security: None: no security, anonymous sessions (loopback); else Basic256Sha256 Sign&Encrypt only, and
            every session logs in with the token (:func:`~cellcal.core.service.opcua_nodes.opcua_security`).
    """

    def __init__(self, service: Service, host: str = "127.0.0.1", port: int = 4840, *, writable: bool = False,
                 security: OpcUaSecurity | None = None) -> None:
        self.service = service
        self.host = host
        self.port = port
        self.writable = writable
        self.security = security
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._failure: str | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._server: Server | None = None
        self._ns = 0
        self._values: dict[str, Any] = {}  # NodeId string -> the value last written

    @property
    def endpoint(self) -> str:
        """The endpoint URL clients connect to (``opc.tcp://host:port/cellcal/``)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"opc.tcp://{host}:{self.port}/cellcal/"

    @property
    def namespace_index(self) -> int:
        """The index of :data:`NAMESPACE` on this server (known once started)."""
        return self._ns

    def start(self, wait_s: float = START_WAIT_S) -> None:
        """Start the server's thread and wait until it listens.

        Raises:
            ConfigError: One line: it cannot listen there (the port is taken, the address is not this machine's,
                the certificate or key cannot be read), or it did not start within ``wait_s``.
        """
        self._thread = threading.Thread(target=self._run, name="cellcal-opcua", daemon=True)
        self._thread.start()
        if not self._ready.wait(wait_s):
            self.stop()
            raise ConfigError(f"the OPC UA server did not start within {wait_s:g} s")
        if self._failure is not None:
            self._thread.join(STOP_WAIT_S)
            raise ConfigError(f"cannot serve OPC UA on {self.host}:{self.port}: {self._failure}")

    def stop(self, wait_s: float = STOP_WAIT_S) -> bool:
        """Stop the server (its sessions closed) and wait at most ``wait_s`` seconds; whether it ended. Idempotent."""
        loop, flag = self._loop, self._stop
        if loop is not None and flag is not None:
            with contextlib.suppress(RuntimeError):  # its loop has ended already
                loop.call_soon_threadsafe(flag.set)
        if self._thread is None:
            return True
        self._thread.join(wait_s)
        return not self._thread.is_alive()

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except Exception as exc:  # anything the server raised before listening is a one-line refusal
            self._failure = f"{type(exc).__name__}: {exc}".replace("\n", " ")
        finally:
            self._ready.set()

    async def _main(self) -> None:
        self._loop, self._stop = asyncio.get_running_loop(), asyncio.Event()
        sub = self.service.bus.subscribe()  # before the first values: no change is missed in between
        try:
            server = await self._build()
            try:
                await server.start()
            except OSError as exc:
                self._failure = exc.strerror or str(exc)
                return
            self.port = server.bserver.port if server.bserver is not None else self.port
            self._ready.set()
            try:
                await self._follow(sub)
            finally:
                with contextlib.suppress(Exception):  # a session that breaks while closing leaves the stop bounded
                    await asyncio.wait_for(server.stop(), STOP_WAIT_S / 2)
        finally:
            sub.close()

    async def _build(self) -> Server:
        """The server with its endpoint, security and every node (not listening yet)."""
        sec = self.security
        server = Server(user_manager=None if sec is None else _TokenUsers(sec.token))  # type: ignore[arg-type]
        await server.init()
        server.set_endpoint(self.endpoint)
        server.set_server_name("cellcal service")
        await server.set_application_uri(APPLICATION_URI)
        if sec is None:
            server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
            server.set_identity_tokens([ua.AnonymousIdentityToken])
        else:
            await server.load_certificate(str(sec.certificate), format=_file_format(sec.certificate))
            await server.load_private_key(str(sec.private_key), format=_file_format(sec.private_key))
            server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt])
            server.set_identity_tokens([ua.UserNameIdentityToken])
        self._server = server
        self._ns = await server.register_namespace(NAMESPACE)
        root = await server.nodes.objects.add_object(_node(ROOT_ID, self._ns), ua.QualifiedName("Cellcal",
                                                                                                       self._ns))
        await self._variable(root, ROOT_ID, "Writable", "Boolean", self.writable)
        await self._variable(root, ROOT_ID, "Security", "String",
                             "None" if sec is None else "Basic256Sha256 SignAndEncrypt")
        for name, cell in self.service.cells.items():
            obj = await root.add_object(_node(cell_id(name), self._ns), ua.QualifiedName(name, self._ns))
            for var, (kind, _) in CELL_VARIABLES.items():
                await self._variable(obj, cell_id(name), var, kind, "idle" if var == "RunState" else _blank(kind))
            await self._methods(obj, name)
            for camera in cell.configs:
                cam = await obj.add_object(_node(cell_id(name, camera), self._ns),
                                           ua.QualifiedName(camera, self._ns))
                for var, (kind, _) in CAMERA_VARIABLES.items():
                    await self._variable(cam, cell_id(name, camera), var, kind, _blank(kind))
                for var, value in watch_values(self.service.watches, name, camera).items():
                    await self._variable(cam, cell_id(name, camera), var, WATCH_VARIABLES[var][0], value)
        return server

    async def _variable(self, parent: Any, owner: str, name: str, kind: str, value: Any) -> None:
        node_id = variable_id(owner, name)
        await parent.add_variable(_node(node_id, self._ns), ua.QualifiedName(name, self._ns),
                                  ua.Variant(value, _TYPES[kind]))
        self._values[node_id] = value

    async def _methods(self, obj: Any, cell: str) -> None:
        owner = cell_id(cell)

        def method(name: str, call: Callable[..., Awaitable[list[ua.Variant]]], changes: bool
                   ) -> Callable[..., Awaitable[Any]]:
            async def handler(_parent: ua.NodeId, *args: ua.Variant) -> Any:
                if changes and not self.writable:
                    return await self._refuse(cell, StatusCodes.BadUserAccessDenied,
                                              f"{name}: the OPC UA face is read-only (cellcal serve --opcua-writable)")
                try:
                    return await call(*(a.Value if isinstance(a, ua.Variant) else a for a in args))
                except ServiceError as exc:
                    return await self._refuse(cell, _STATUS.get(type(exc), StatusCodes.BadInvalidArgument),
                                              f"{name}: {exc}")
                except (CellcalError, TypeError, ValueError) as exc:
                    return await self._refuse(cell, StatusCodes.BadInvalidArgument, f"{name}: {exc}")

            return handler

        async def start_run(kind: str, camera: str) -> list[ua.Variant]:
            run = await asyncio.to_thread(self.service.start_run, cell, str(kind), str(camera))
            return [ua.Variant(run.id, ua.VariantType.String)]

        async def cancel_run(run_id: str) -> list[ua.Variant]:
            run = self.service.run(str(run_id))
            if run.cell != cell:
                raise NotFoundError(f"run {run_id!r} is not on cell {cell!r}")
            self.service.cancel_run(run.id)
            return []

        async def pixel_to_base(camera: str, u: float, v: float, translation: Any, quaternion: Any
                                ) -> list[ua.Variant]:
            pose = {"translation_m": list(translation), "quaternion_xyzw": list(quaternion)}
            found = self.service.cell(cell).pixel_to_base(str(camera), [float(u), float(v)], pose)
            values = [*found.points_m[0], *found.sigma_m[0]]
            if not all(math.isfinite(x) for x in values[:3]):
                raise RequestError("the pixel's ray misses the plane (parallel to it, or it lies behind the camera)")
            return [ua.Variant(float(x), ua.VariantType.Double) for x in values]

        s = "String"
        specs: list[tuple[str, Callable[..., Awaitable[list[ua.Variant]]], bool, list[ua.Argument],
                          list[ua.Argument]]] = [
            ("StartRun", start_run, True, [_argument("kind", s, "calibrate, handeye or depthcal"),
                                           _argument("camera", s, "the camera's name")],
             [_argument("run_id", s, "the run's id")]),
            ("CancelRun", cancel_run, True, [_argument("run_id", s, "the run to stop at its next safe point")], []),
            ("PixelToBase", pixel_to_base, False, [
                _argument("camera", s, "the camera's name"), _argument("u", "Double", "pixel column, px"),
                _argument("v", "Double", "pixel row, px"),
                _argument("flange_translation_m", "Double", "T_base_flange's translation, m", 3),
                _argument("flange_quaternion_xyzw", "Double", "T_base_flange's unit quaternion", 4)],
             [*(_argument(a, "Double", f"the point's {a}, base frame, m") for a in "xyz"),
              *(_argument(f"sigma_{a}", "Double", f"1-sigma of {a}, m") for a in "xyz")]),
        ]
        for name, call, changes, inputs, outputs in specs:
            await obj.add_method(_node(variable_id(owner, name), self._ns), ua.QualifiedName(name, self._ns),
                                 method(name, call, changes), inputs, outputs)

    async def _refuse(self, cell: str, code: int, why: str) -> ua.StatusCode:
        """Answer a method call with ``code``; its one-line reason goes to the cell's ``LastRefusal``."""
        await self._write(cell_id(cell), {"LastRefusal": why.replace("\n", " ")}, CELL_VARIABLES)
        return ua.StatusCode(code)  # type: ignore[arg-type]  # asyncua's own NewTypes

    async def _write(self, owner: str, values: dict[str, Any], kinds: dict[str, tuple[str, str]]) -> None:
        """Write the values that changed (a subscriber is told of a change, not of a rewrite)."""
        assert self._server is not None
        for name, value in values.items():
            node_id = variable_id(owner, name)
            if self._values.get(node_id) == value and not (isinstance(value, float) and math.isnan(value)):
                continue
            self._values[node_id] = value
            variant = ua.Variant(value, _TYPES[kinds[name][0]])
            await self._server.write_attribute_value(_node(node_id, self._ns), ua.DataValue(variant))

    async def _follow(self, sub: Any) -> None:
        """Keep the variables current: each run event as it comes, each camera's files once a second."""
        assert self._stop is not None
        for run in self.service.runs():  # the latest run of each cell, before any event
            await self._run_values(run.to_dict())
        next_poll = 0.0
        while not self._stop.is_set():
            if time.monotonic() >= next_poll:
                await self._cameras()
                next_poll = time.monotonic() + POLL_S
            if sub.closed:  # the service is closing: nothing more will come
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._stop.wait(), _TICK_S)
                continue
            event = await sub.aget(min(_TICK_S, max(0.0, next_poll - time.monotonic())))
            if event is None:
                continue
            if event.type in ("run.state", "run.progress"):
                await self._run_values(event.data)
            elif event.type == "calibration.changed":
                next_poll = 0.0  # read its files now
            elif event.type.startswith(_WATCH_EVENTS) and event.data.get("cell") in self.service.cells:
                await self._watch_values(str(event.data["cell"]))

    async def _watch_values(self, cell: str) -> None:
        """The cell's cameras' tracking and monitoring variables, from its sessions now."""
        for camera in self.service.cells[cell].configs:
            values = watch_values(self.service.watches, cell, camera)
            await self._write(cell_id(cell, camera), values, WATCH_VARIABLES)

    async def _run_values(self, run: Any) -> None:
        cell = run.get("cell")
        if cell not in self.service.cells:
            return
        progress = run.get("progress", {})
        await self._write(cell_id(cell), {
            "RunId": str(run.get("id", "")), "RunKind": str(run.get("kind", "")),
            "RunCamera": str(run.get("camera", "")), "RunState": str(run.get("state", "")),
            "PosesDone": int(progress.get("poses_done", 0)), "PosesTotal": int(progress.get("poses_total", 0)),
            "LastError": str(run.get("error") or "")}, CELL_VARIABLES)

    async def _cameras(self) -> None:
        """Every camera's calibration values, read off the loop (the files are looked at once a second)."""
        def read() -> dict[str, dict[str, Any]]:
            out = {}
            for name, cell in self.service.cells.items():
                for camera in cell.configs:
                    try:
                        values = camera_values(cell.calibration(camera))
                    except CellcalError as exc:
                        values = {**camera_values(None), "CalibrationError": str(exc).replace("\n", " ")}
                    out[cell_id(name, camera)] = values
            return out

        for owner, values in (await asyncio.to_thread(read)).items():
            await self._write(owner, values, CAMERA_VARIABLES)


def _node(identifier: str, namespace: int) -> ua.NodeId:
    """The string NodeId ``ns=<namespace>;s=<identifier>``."""
    return ua.NodeId(identifier, namespace)  # type: ignore[arg-type]  # asyncua's own NewTypes


def _file_format(path: Path) -> str:
    """``pem`` or ``der``, from the file's first bytes (a systemd credential or a secret has no telling suffix)."""
    with open(path, "rb") as fh:
        return "pem" if fh.read(64).lstrip().startswith(b"-----BEGIN") else "der"


def _blank(kind: str) -> Any:
    return {"Boolean": False, "String": "", "Double": 0.0, "UInt32": 0}[kind]
