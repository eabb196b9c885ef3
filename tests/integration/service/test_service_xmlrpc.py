"""The XML-RPC face over a real socket with the standard library's client (as URScript's rpc_factory would call it):
start a run, poll it to ok, read the plane, pixel_to_base equal to the HTTP answer, a wrong token, a huge body."""

from __future__ import annotations

import http.client
import time
import xmlrpc.client
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from conftest import WAIT_S, Arms, serving, sim_config
from scipy.spatial.transform import Rotation
from test_service_http import CAMERA

from cellcal.core.service import Service
from cellcal.core.service.calibration import Z95
from cellcal.core.service.xmlrpc import MAX_BODY_BYTES, XmlRpcFace

TOKEN = "xmlrpc-test-token-0123456789"


def poll(proxy: Any, run_id: str) -> dict[str, Any]:
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        state: dict[str, Any] = proxy.run_state(run_id)
        if state["final"]:
            return state
        time.sleep(0.05)
    raise AssertionError(f"run {run_id} did not end")


def test_a_robot_program_s_calls_over_xml_rpc(tmp_path: Path, arms: Arms) -> None:
    service = Service([sim_config(tmp_path)], tmp_path / "out", build=arms)
    with serving(service, token=TOKEN) as base, XmlRpcFace(service, "127.0.0.1", 0, token=TOKEN) as face, \
            httpx.Client(base_url=base, timeout=WAIT_S) as client:
        proxy = xmlrpc.client.ServerProxy(face.url)
        assert face.url.endswith("/RPC2")
        with pytest.raises(xmlrpc.client.Fault) as wrong:
            proxy.start_run("not-the-token-0123456789", "calibrate", "camera")
        assert wrong.value.faultCode == 401 and wrong.value.faultString == "wrong token"
        assert service.runs() == [] and arms.built == []  # nothing started, nothing moved
        run_id = proxy.start_run(TOKEN, "calibrate", "camera", {"report": False})
        state = poll(proxy, run_id)
        assert state["state"] == "ok" and state["poses_done"] == state["poses_total"] == 3 and state["error"] == ""
        assert proxy.run_status(run_id) == "ok"
        with pytest.raises(xmlrpc.client.Fault) as ended:
            proxy.cancel_run(TOKEN, run_id)
        assert ended.value.faultCode == 409 and "has ended" in ended.value.faultString
        # the plane, as the HTTP face has it
        plane = proxy.plane("paper-sim/camera")
        over_http = client.get(f"{CAMERA}/calibration").json()["plane_base"]
        assert plane["normal"] == over_http["normal"] and plane["offset_m"] == over_http["offset_m"]
        assert plane["height_halfwidth_m"] == over_http["height_halfwidth_m"] > 0
        assert plane["tilt_halfwidth_rad"] == pytest.approx([Z95 * s for s in over_http["tilt_sigma_rad"]],
                                                            rel=1e-15)
        # pixel_to_base from a UR pose p[x, y, z, rx, ry, rz], against HTTP with the same pose as a quaternion
        result = client.get(f"/runs/{run_id}/result").json()["result"]
        flange = result["poses"][1]["reported_flange_pose"]
        ur_pose = [*flange["translation_m"], *flange["rotvec_rad"]]
        quaternion = Rotation.from_rotvec(ur_pose[3:]).as_quat().tolist()
        for u, v in ((111.5, 85.5), (20, 30.75), (200.25, 150)):  # an int is a pixel too
            got = proxy.pixel_to_base("camera", u, v, ur_pose)
            want = client.post(f"{CAMERA}/pixel_to_base", json={
                "pixels": [u, v], "flange_pose": {"translation_m": flange["translation_m"],
                                                  "quaternion_xyzw": quaternion}}).json()
            assert len(got) == 6
            assert np.max(np.abs(np.array(got[:3]) - want["points_m"][0])) <= 1e-12  # metres
            assert np.max(np.abs(np.array(got[3:]) - want["sigma_m"][0])) <= 1e-12
            assert all(s > 0 for s in got[3:])
        struct = dict(zip(("x", "y", "z", "rx", "ry", "rz"), ur_pose, strict=True))  # URScript's pose struct
        assert proxy.pixel_to_base("camera", 111.5, 85.5, struct) == proxy.pixel_to_base("camera", 111.5, 85.5,
                                                                                         ur_pose)
        # a body over the bound is refused before it is parsed; the face serves on
        with pytest.raises(xmlrpc.client.ProtocolError) as huge:
            proxy.plane("x" * (2 * MAX_BODY_BYTES))
        assert huge.value.errcode == 413
        assert proxy.run_state(run_id)["state"] == "ok"
        # XML that is not a call: a fault of one line, no traceback
        port = face.port
        raw = http.client.HTTPConnection("127.0.0.1", port, timeout=WAIT_S)
        raw.request("POST", "/RPC2", body=b"<methodCall><methodName>plane", headers={"Content-Type": "text/xml"})
        answer = raw.getresponse()
        assert answer.status == 200
        with pytest.raises(xmlrpc.client.Fault) as malformed:
            xmlrpc.client.loads(answer.read())
        assert malformed.value.faultCode == 400 and "\n" not in malformed.value.faultString
        raw.request("GET", "/RPC2")
        refused = raw.getresponse()
        assert refused.status == 405 and refused.read().count(b"\n") == 1
        raw.close()
