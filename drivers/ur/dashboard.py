"""The UR dashboard server (port 29999) through ur_rtde's ``DashboardClient``: :class:`DashboardLink`.

Identity (model, serial, PolyScope version), the remote-control check and the recovery
commands of ``URArm.clear_errors``. ``dashboard_client`` is imported only in :meth:`DashboardLink.open`.
"""

from __future__ import annotations

import contextlib
import logging
from typing import Any

from cellcal.devices.errors import CellcalError, DeviceConnectionError, MissingDependencyError, VendorError

from .fd_capture import captured_output
from .rtde_probe import open_port

log = logging.getLogger(__name__)

LOCAL_CONTROL = "the pendant is in Local Control (switch it to Remote Control)"


class DashboardLink:
    """One dashboard connection, opened on demand.

    Args:
        host: Controller address.
        port: Dashboard server port (29999).

    Attributes:
        client: The connected ``dashboard_client.DashboardClient``, or None.
        identity: ``model``, ``serial`` and ``polyscope`` once opened.
    """

    def __init__(self, host: str, port: int) -> None:
        self.host = host
        self.port = port
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
            import dashboard_client
        except ImportError:
            raise MissingDependencyError("ur_rtde (dashboard_client)", "ur") from None
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
