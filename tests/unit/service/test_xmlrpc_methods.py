"""The XML-RPC face without a socket: defused parsing, UR poses, the token rule, faults of one line."""

from __future__ import annotations

import xmlrpc.client
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cellcal.core.service import Service
from cellcal.core.service.errors import RequestError
from cellcal.core.service.xmlrpc import FAULT_CODES, XmlRpcMethods, flange_pose_of, parse_call

SIM_TOML = resources.files("cellcal.configs").joinpath("sim.toml").read_text()
TOKEN = "unit-test-token-0123456789"
BOMB = b"""<?xml version="1.0"?>
<!DOCTYPE lolz [<!ENTITY lol "lol"><!ENTITY lol2 "&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;">]>
<methodCall><methodName>plane</methodName><params><param><value><string>&lol2;</string></value></param>
</params></methodCall>"""


def test_a_call_is_parsed_and_an_entity_or_a_dtd_is_refused_before_anything_runs() -> None:
    body = xmlrpc.client.dumps(("paper-sim/camera", 111.5, 85, []), methodname="pixel_to_base").encode()
    assert parse_call(body) == ("pixel_to_base", ("paper-sim/camera", 111.5, 85, []))
    for bad in (BOMB, b"<methodCall><methodName>plane</methodName><params>", b"not xml at all", b"<a/>"):
        with pytest.raises(xmlrpc.client.Fault) as caught:
            parse_call(bad)
        assert caught.value.faultCode == 400 and "\n" not in caught.value.faultString


def test_a_ur_pose_becomes_the_flange_pose_as_a_list_or_as_urscript_s_struct() -> None:
    pose = [0.26, 0.01, 0.46, -2.1301581545216086, 0.3, 0.1]
    got = flange_pose_of(pose)
    assert got["translation_m"] == pose[:3]
    want = Rotation.from_rotvec(pose[3:]).as_quat()
    assert np.max(np.abs(np.array(got["quaternion_xyzw"]) - want)) == 0.0  # the same conversion, bit for bit
    struct = dict(zip(("x", "y", "z", "rx", "ry", "rz"), pose, strict=True))
    assert flange_pose_of(struct) == got
    for bad in ([], [0.1, 0.2], [0.1] * 5 + ["a"], [0.1] * 5 + [float("nan")], "p[0,0,0,0,0,0]"):
        with pytest.raises(RequestError):
            flange_pose_of(bad)


@pytest.fixture
def service(tmp_path: Path) -> Service:
    configs = []
    for cell in ("paper-sim", "second-sim"):
        path = tmp_path / f"{cell}.toml"
        path.write_text(SIM_TOML.replace('name = "paper-sim"', f'name = "{cell}"'))
        configs.append(path)
    found = Service(configs, tmp_path / "out")
    assert set(found.cells) == {"paper-sim", "second-sim"}
    return found


def fault(methods: XmlRpcMethods, method: str, *params: object) -> xmlrpc.client.Fault:
    with pytest.raises(xmlrpc.client.Fault) as caught:
        methods.call(method, params)
    assert caught.value.faultCode in FAULT_CODES and "\n" not in caught.value.faultString
    assert "Traceback" not in caught.value.faultString
    return caught.value


def test_the_token_comes_first_in_a_state_changing_call_and_every_refusal_is_one_line(service: Service) -> None:
    methods = XmlRpcMethods(service, TOKEN)
    assert fault(methods, "start_run", "calibrate", "paper-sim/camera").faultCode == 401  # no token
    assert fault(methods, "start_run", "not-the-token-000000", "calibrate", "paper-sim/camera").faultString == \
        "wrong token"
    assert fault(methods, "cancel_run", "nope").faultCode == 401
    assert fault(methods, "start_run", TOKEN, "calibrate").faultCode == 422  # too few after the token
    assert fault(methods, "start_run", TOKEN, "paint", "paper-sim/camera").faultCode == 422
    assert fault(methods, "cancel_run", TOKEN, "no-such-run").faultCode == 404
    assert not service.runs() and all(c.active is None for c in service.cells.values())  # nothing started
    # reading needs no token
    assert fault(methods, "run_state", "no-such-run").faultCode == 404
    assert fault(methods, "plane", "paper-sim/camera").faultCode == 404  # no calibration yet
    assert fault(methods, "plane", "camera").faultCode == 422  # two cells have it: which?
    assert fault(methods, "plane", "nowhere/camera").faultCode == 404
    assert fault(methods, "pixel_to_base", "paper-sim/camera", 1.0, True, []).faultCode == 422  # a bool is no pixel
    assert fault(methods, "pixel_to_base", "paper-sim/camera", 1.0, 2.0, []).faultCode == 422  # the flange pose
    assert fault(methods, "system.listMethods").faultCode == 404
    # without a token set, the state-changing methods take none
    open_methods = XmlRpcMethods(service, None)
    assert "after the token" not in fault(open_methods, "start_run", TOKEN, "calibrate", "camera", {}, 1).faultString
    service.close()
