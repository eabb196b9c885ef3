"""The UR dashboard server (port 29999) through ur_rtde's ``DashboardClient``: :class:`DashboardLink`.

Identity (model, serial, PolyScope version), the remote-control check and the recovery
commands of ``URArm.clear_errors``. ``dashboard_client`` is imported only in :meth:`DashboardLink.open`.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import time
from collections.abc import Callable
from typing import Any

from cellcal.devices.errors import (
    CellcalError,
    DeviceConnectionError,
    DeviceTimeoutError,
    MissingDependencyError,
    ProtocolError,
    VendorError,
)

from .fd_capture import captured_output
from .rtde_probe import open_port

log = logging.getLogger(__name__)

LOCAL_CONTROL = "the pendant is in Local Control (switch it to Remote Control)"
#: Longest greeting line accepted from the dashboard server, bytes (its greeting is ~45).
MAX_LINE_BYTES = 4096


def read_greeting(host: str, port: int, timeout: float) -> str:
    """The dashboard server's greeting line, read with a plain socket within ``timeout`` s and 4 KiB.

    ur_rtde's client reads a line without bound: a peer streaming bytes without a line end held
    ``connect(timeout=6)`` for 7-10 s. This check runs first, under the caller's deadline.

    Raises:
        DeviceConnectionError: If the port is refused or closes before a line.
        DeviceTimeoutError: If no line arrives within ``timeout``.
        ProtocolError: If :data:`MAX_LINE_BYTES` arrive without a line end.
    """
    deadline = time.monotonic() + timeout
    with open_port(host, port, timeout, "dashboard") as sock:
        return _read_line(sock, host, port, deadline, "greeting line")


def _read_line(sock: Any, host: str, port: int, deadline: float, what: str) -> str:
    """One line from the dashboard port, at most :data:`MAX_LINE_BYTES`, before ``deadline`` (monotonic s)."""
    received = bytearray()
    while b"\n" not in received:
        if len(received) >= MAX_LINE_BYTES:
            raise ProtocolError(f"ur {host}: the dashboard port {port} sent {len(received)} bytes without a "
                                "line end: not a UR dashboard server")
        left = deadline - time.monotonic()
        if left <= 0:
            raise DeviceTimeoutError(f"ur {host}: no {what} from the dashboard port {port} within the deadline")
        sock.settimeout(left)
        try:
            chunk = sock.recv(1)  # a byte at a time: what follows the line stays in the socket
        except TimeoutError:
            continue  # the deadline check above ends it
        except OSError as exc:
            raise DeviceConnectionError(f"ur {host}: dashboard port {port}: {exc.strerror or exc}") from None
        if not chunk:
            raise DeviceConnectionError(f"ur {host}: the dashboard port {port} closed before its {what}")
        received += chunk
    return received.split(b"\n", 1)[0].decode("utf-8", "replace").strip()


def stop_program(host: str, port: int, timeout: float) -> str:
    """Send the dashboard's ``stop`` over a plain socket (no ur_rtde) and return its answer.

    The channel left when ur_rtde's worker process has died: stopping the running program
    (ur_rtde's control script) brings a moving arm to a stop.

    Raises:
        DeviceConnectionError / DeviceTimeoutError / ProtocolError: As :func:`read_greeting`.
        VendorError: If the controller answers other than ``Stopped``.
    """
    deadline = time.monotonic() + timeout
    with open_port(host, port, timeout, "dashboard") as sock:
        _read_line(sock, host, port, deadline, "greeting line")
        try:
            sock.sendall(b"stop\n")
        except OSError as exc:
            raise DeviceConnectionError(f"ur {host}: dashboard port {port}: {exc.strerror or exc}") from None
        answer = _read_line(sock, host, port, deadline, "answer to 'stop'")
    if not answer.lower().startswith("stopped"):
        raise VendorError("ur", 0, f"dashboard 'stop' answered {answer[:80]!r}")
    return answer


class DashboardLink:
    """One dashboard connection, opened on demand.

    Args:
        host: Controller address.
        port: Dashboard server port (29999).

    Attributes:
        client: The connected ``dashboard_client.DashboardClient``, or None.
        identity: ``model``, ``serial`` and ``polyscope`` once opened.
    """

    def __init__(self, host: str, port: int, *, load: Callable[[str], Any] = importlib.import_module) -> None:
        self.host = host
        self.port = port
        self._load = load
        self.client: Any = None
        self.identity: dict[str, str] = {}

    def open(self, timeout: float, *, required: bool) -> Any:
        """The connected client (reused while connected); None if unavailable and not ``required``.

        Raises:
            MissingDependencyError: If ur_rtde is not installed.
            DeviceConnectionError: If ``required`` and the dashboard cannot be reached.
        """
        if self.client is not None and self.client.isConnected():
            return self.client
        try:
            dashboard_client = self._load("dashboard_client")
        except (ImportError, MissingDependencyError):
            raise MissingDependencyError("ur_rtde (dashboard_client)", "ur") from None
        started = time.monotonic()
        try:  # a plain, bounded look at the greeting first (ur_rtde's own read has no bound)
            read_greeting(self.host, self.port, timeout)
        except CellcalError as exc:
            reason = str(exc).removeprefix(f"ur {self.host}: ")
            if required and isinstance(exc, DeviceConnectionError):
                raise DeviceConnectionError(f"ur {self.host}: dashboard server port {self.port}: {reason}") from None
            if required:
                raise  # silent, or not a dashboard: typed, one line
            log.warning("ur %s: dashboard unavailable (%s); identity unknown", self.host, reason)
            return None
        timeout = max(0.001, timeout - (time.monotonic() - started))
        dash = dashboard_client.DashboardClient(self.host, self.port)
        try:
            with captured_output(f"ur {self.host}: dashboard connect"):  # ur_rtde's own lines: debug log only
                dash.connect(max(1, int(timeout * 1000)))
            self.identity = {"model": str(dash.getRobotModel()), "serial": str(dash.getSerialNumber()),
                             "polyscope": str(dash.polyscopeVersion())}
        except (RuntimeError, OSError) as exc:
            reason = self._why_not(timeout, exc)
            if required:
                raise DeviceConnectionError(f"ur {self.host}: dashboard server port {self.port}: {reason}") from None
            log.warning("ur %s: dashboard unavailable (%s); identity unknown", self.host, reason)
            return None
        self.client = dash
        return dash

    def _why_not(self, timeout: float, exc: BaseException) -> str:
        """Why the dashboard connect failed: ur_rtde says "Timeout" for a refused port too, so ask a plain socket."""
        try:
            open_port(self.host, self.port, min(timeout, 1.0), "dashboard").close()
        except CellcalError as refused:
            return str(refused).removeprefix(f"ur {self.host}: ")
        return str(exc)

    def call(self, method: str, what: str) -> None:
        """Run one dashboard command (e.g. ``"powerOn"``); a refusal is a :class:`VendorError`."""
        try:
            getattr(self.client, method)()
        except RuntimeError as exc:
            raise VendorError("ur", 0, f"dashboard '{what}' failed: {exc}") from None

    def require_remote_control(self) -> None:
        """Raise :class:`DeviceConnectionError` if the dashboard says the pendant is in Local Control."""
        dash = self.client
        with contextlib.suppress(RuntimeError):
            if dash is not None and dash.isConnected() and not dash.isInRemoteControl():
                raise DeviceConnectionError(f"ur {self.host}: {LOCAL_CONTROL}")

    def remote_control_hint(self) -> str:
        """``"; the pendant is in Local Control ..."`` when it is, else "" (for messages; never raises)."""
        dash = self.client
        try:
            if dash is not None and dash.isConnected() and not dash.isInRemoteControl():
                return f"; {LOCAL_CONTROL}"
        except Exception:
            pass
        return ""

    def close(self) -> None:
        """Disconnect (cheap: the dashboard client has no receive thread)."""
        dash, self.client = self.client, None
        if dash is not None:
            with contextlib.suppress(Exception):
                dash.disconnect()
