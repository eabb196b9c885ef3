"""``cellcal serve``'s OPC UA face on the simulated cell, with asyncua's own Client over a real socket (127.0.0.1).

Browse the nodes; StartRun (writable) -> the progress variable seen changing through a
subscription -> the plane and mount variables equal to the service's calibration; PixelToBase
equal to the service's ``pixel_to_base`` to 1e-9 m; a read-only face refuses StartRun with
BadUserAccessDenied and nothing moves; the secured face (Basic256Sha256 SignAndEncrypt) lets in
only a session that logs in with the token; a non-loopback bind without a certificate is refused.
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
import time
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import WAIT_S, Arms

asyncua = pytest.importorskip("asyncua")

from asyncua import Client, ua  # noqa: E402

from cellcal.core.service import Service  # noqa: E402
from cellcal.core.service.opcua import APPLICATION_URI, OpcUaFace  # noqa: E402
from cellcal.core.service.opcua_nodes import (  # noqa: E402
    CAMERA_VARIABLES,
    CELL_VARIABLES,
    NAMESPACE,
    ROOT_ID,
    USERNAME,
    WATCH_VARIABLES,
    OpcUaSecurity,
    camera_values,
)
from cellcal.devices.pose import Pose  # noqa: E402

CELL, CAMERA = "paper-sim", "camera"
TOKEN = "opcua-test-token-0123456789"
#: A flange pose looking down at the table, and pixels across the image.
FLANGE = Pose.from_xyz_rpy([0.3, 0.05, 0.5], np.radians([180.0, 8.0, 5.0]))
PIXELS = [(112.0, 86.0), (10.5, 20.25), (200.0, 160.0)]


class Changes:
    """A subscription handler keeping every (node id, value) it was told of."""

    def __init__(self) -> None:
        self.seen: list[tuple[str, Any]] = []

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        self.seen.append((node.nodeid.Identifier, val))


def run_async(body: Callable[[], Coroutine[Any, Any, Any]]) -> Any:
    return asyncio.run(asyncio.wait_for(body(), WAIT_S))


def face_of(service: Service, **options: Any) -> OpcUaFace:
    face = OpcUaFace(service, "127.0.0.1", 0, **options)
    face.start()
    return face


async def value(client: Client, ns: int, node_id: str) -> Any:
    return await client.get_node(ua.NodeId(node_id, ns)).read_value()


async def until(client: Client, ns: int, node_id: str, done: Callable[[Any], bool]) -> Any:
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        got = await value(client, ns, node_id)
        if done(got):
            return got
        await asyncio.sleep(0.05)
    raise AssertionError(f"{node_id} did not get there: {got!r}")


def test_calibrate_over_opcua_progress_plane_and_pixel_to_base(make_service: Any) -> None:
    service: Service = make_service(settle_s=0.2)  # a few tenths of a second per pose: progress steps apart
    face = face_of(service, writable=True)

    async def body() -> dict[str, Any]:
        async with Client(face.endpoint, timeout=30) as client:
            ns = await client.get_namespace_index(NAMESPACE)
            root = client.get_node(ua.NodeId(ROOT_ID, ns))
            names = {(await n.read_browse_name()).Name for n in await root.get_children()}
            assert names == {"Writable", "Security", CELL}
            cell = client.get_node(ua.NodeId(CELL, ns))
            names = {(await n.read_browse_name()).Name for n in await cell.get_children()}
            assert names == {*CELL_VARIABLES, "StartRun", "CancelRun", "PixelToBase", CAMERA}
            camera = client.get_node(ua.NodeId(f"{CELL}/{CAMERA}", ns))
            assert {(await n.read_browse_name()).Name for n in await camera.get_children()} == \
                {*CAMERA_VARIABLES, *WATCH_VARIABLES}
            assert await value(client, ns, f"{CELL}.RunState") == "idle"
            assert await value(client, ns, f"{CELL}/{CAMERA}.Calibrated") is False

            changes = Changes()
            subscription = await client.create_subscription(20, changes)
            await subscription.subscribe_data_change([client.get_node(ua.NodeId(f"{CELL}.PosesDone", ns)),
                                                      client.get_node(ua.NodeId(f"{CELL}.RunState", ns))])
            run_id = await cell.call_method(ua.QualifiedName("StartRun", ns), "calibrate", CAMERA)
            assert service.run(run_id).kind == "calibrate"
            await until(client, ns, f"{CELL}.RunState", lambda s: s in ("ok", "failed", "cancelled"))
            total = await value(client, ns, f"{CELL}.PosesTotal")
            await until(client, ns, f"{CELL}/{CAMERA}.Calibrated", bool)
            read = {name: await value(client, ns, f"{CELL}/{CAMERA}.{name}") for name in CAMERA_VARIABLES}
            answers = [await cell.call_method(ua.QualifiedName("PixelToBase", ns), CAMERA, u, v,
                                              list(FLANGE.translation), list(FLANGE.as_quat_xyzw()))
                       for u, v in PIXELS]
            with pytest.raises(ua.uaerrors.BadNotFound):
                await cell.call_method(ua.QualifiedName("PixelToBase", ns), "nocam", 1.0, 1.0, [0.0] * 3,
                                       [0.0, 0.0, 0.0, 1.0])
            refusal = await value(client, ns, f"{CELL}.LastRefusal")
            with pytest.raises(ua.uaerrors.BadInvalidState):  # the run has ended: nothing to cancel
                await cell.call_method(ua.QualifiedName("CancelRun", ns), run_id)
            await subscription.delete()
            return {"run_id": run_id, "total": total, "read": read, "answers": answers, "refusal": refusal,
                    "seen": changes.seen, "state": await value(client, ns, f"{CELL}.RunState")}

    try:
        got = run_async(body)
    finally:
        assert face.stop()
        service.close()
    assert got["state"] == "ok", service.run(got["run_id"]).error
    done = [v for k, v in got["seen"] if k == f"{CELL}.PosesDone"]
    states = [v for k, v in got["seen"] if k == f"{CELL}.RunState"]
    assert got["total"] >= 3 and done[-1] == got["total"]
    assert len(set(done) - {0}) >= 2 and done == sorted(done)  # the progress seen changing, pose by pose
    assert states[0] == "idle" and "running" in states and states[-1] == "ok"
    calibration = service.cells[CELL].calibration(CAMERA)
    assert got["read"] == camera_values(calibration)  # every plane and mount value, exactly
    assert got["read"]["PlaneHeightHalfWidth"] > 0
    points = service.cells[CELL].pixel_to_base(CAMERA, PIXELS, {"translation_m": list(FLANGE.translation),
                                                                "quaternion_xyzw": list(FLANGE.as_quat_xyzw())})
    answers = np.array(got["answers"])
    assert np.max(np.abs(answers[:, :3] - points.points_m)) < 1e-9
    assert np.max(np.abs(answers[:, 3:] - points.sigma_m)) < 1e-9 and np.all(answers[:, 3:] > 0)
    assert got["refusal"] == f"PixelToBase: cell '{CELL}' has no camera 'nocam' (has: {CAMERA})"


def test_a_read_only_face_refuses_to_start_a_run(make_service: Any, arms: Arms) -> None:
    service: Service = make_service()
    face = face_of(service)

    async def body() -> tuple[bool, str]:
        async with Client(face.endpoint, timeout=30) as client:
            ns = await client.get_namespace_index(NAMESPACE)
            cell = client.get_node(ua.NodeId(CELL, ns))
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await cell.call_method(ua.QualifiedName("StartRun", ns), "calibrate", CAMERA)
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await cell.call_method(ua.QualifiedName("CancelRun", ns), "0123")
            refusal = await value(client, ns, f"{CELL}.LastRefusal")
            with pytest.raises(ua.uaerrors.BadNotFound):  # reading is allowed: no calibration yet
                await cell.call_method(ua.QualifiedName("PixelToBase", ns), CAMERA, 1.0, 1.0, [0.0] * 3,
                                       [0.0, 0.0, 0.0, 1.0])
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):  # a client cannot write a variable either
                await client.get_node(ua.NodeId(f"{CELL}.RunState", ns)).write_value("ok")
            return await value(client, ns, f"{ROOT_ID}.Writable"), refusal

    try:
        writable, refusal = run_async(body)
    finally:
        assert face.stop()
        service.close()
    assert writable is False and refusal.startswith("CancelRun: the OPC UA face is read-only")
    assert service.runs() == [] and arms.built == []  # nothing ran, no arm was built


def test_the_secured_face_needs_encryption_and_the_token(tmp_path: Path, make_service: Any) -> None:
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    async def make(name: str, uri: str, use: Any, suffix: str = ".pem") -> tuple[Path, Path]:
        key, cert = tmp_path / f"{name}-key{suffix}", tmp_path / f"{name}-cert.der"  # a PEM key, a DER certificate
        await setup_self_signed_certificate(key, cert, uri, "localhost", [use], {"commonName": name})
        return cert, key

    server_cert, server_key = asyncio.run(make("server", APPLICATION_URI, ExtendedKeyUsageOID.SERVER_AUTH, ""))
    client_cert, client_key = asyncio.run(make("client", "urn:cellcal:test:client", ExtendedKeyUsageOID.CLIENT_AUTH))
    service: Service = make_service()
    face = face_of(service, security=OpcUaSecurity(server_cert, server_key, TOKEN))  # told PEM or DER by content
    secure = f"Basic256Sha256,SignAndEncrypt,{client_cert},{client_key}"

    async def connect(password: str | None, security: str | None) -> str:
        client = Client(face.endpoint, timeout=30)
        client.application_uri = "urn:cellcal:test:client"
        if security is not None:
            await client.set_security_string(security)
        if password is not None:
            client.set_user(USERNAME)
            client.set_password(password)
        try:
            async with client:
                ns = await client.get_namespace_index(NAMESPACE)
                return str(await value(client, ns, f"{ROOT_ID}.Security"))
        except Exception as exc:  # the refusal, whichever asyncua raises for it
            return f"refused: {type(exc).__name__}"

    async def body() -> tuple[str, str, str, list[str]]:
        endpoints = await Client(face.endpoint, timeout=30).connect_and_get_server_endpoints()
        offered = [f"{e.SecurityPolicyUri.rsplit('#')[-1]} {e.SecurityMode.name}" for e in endpoints]
        return (await connect(TOKEN, secure), await connect("wrong-token-0123456789", secure),
                await connect(None, secure), offered)

    try:
        good, wrong, anonymous, offered = run_async(body)
    finally:
        assert face.stop()
        service.close()
    assert offered == ["Basic256Sha256 SignAndEncrypt"]  # nothing in the clear
    assert good == "Basic256Sha256 SignAndEncrypt"
    assert wrong.startswith("refused") and anonymous.startswith("refused")


def test_a_non_loopback_opcua_bind_without_a_certificate_is_refused(tmp_path: Path) -> None:
    token = tmp_path / "token"
    token.write_text(TOKEN)
    done = subprocess.run([sys.executable, "-m", "cellcal.core.cli", "serve", "--host", "0.0.0.0", "--port", "0",
                           "--token-file", str(token), "--opcua-port", "0", "--out", str(tmp_path / "out")],
                          stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=WAIT_S)
    assert done.returncode == 2
    assert done.stderr.strip().count("\n") == 0 and "--opcua-cert and --opcua-key" in done.stderr
    assert "Basic256Sha256 SignAndEncrypt" in done.stderr and "Traceback" not in done.stderr
    assert done.stdout == "" and not (tmp_path / "out").exists()  # it never listened, nothing ran
