"""The O3R configuration channel without sockets: XML-RPC reply parsing, JSON, and the checks of the tree."""

from __future__ import annotations

import json
import re
import xmlrpc.client
from typing import Any

import pytest

from cellcal.devices.config import parse_section
from cellcal.devices.errors import ConfigError, ProtocolError, VendorError
from cellcal.drivers.o3r.camera import O3RConfig
from cellcal.drivers.o3r.xmlrpc_config import MAX_DEPTH, parse_json_object, parse_reply
from cellcal.drivers.o3r_json import clip, firmware, pointer, port_info, show

WHERE = "O3R XML-RPC 10.0.0.1:80 get(['/ports'])"
WHERE_RE = re.escape(WHERE)


def reply(*values: Any) -> bytes:
    return xmlrpc.client.dumps(values, methodresponse=True, allow_none=True).encode()


def fault(code_xml: str, text_xml: str = "<string>no such key</string>") -> bytes:
    return (f"<methodResponse><fault><value><struct><member><name>faultCode</name><value>{code_xml}</value>"
            f"</member><member><name>faultString</name><value>{text_xml}</value></member></struct></value>"
            f"</fault></methodResponse>").encode()


def doc(**port2: Any) -> dict[str, Any]:
    p2: dict[str, Any] = {"data": {"pcicTCPPort": 50012}, "state": "IDLE",
                          "info": {"features": {"type": "3D", "resolution": {"width": 224, "height": 172}}}}
    p2.update(port2)
    return {"ports": {"port0": {}, "port2": p2}, "device": {"swVersion": {"firmware": "1.4.30"}}}


# ---------------------------------------------------------------------- XML-RPC
def test_reply_value_round_trips() -> None:
    assert parse_reply(reply('{"a": 1}'), WHERE) == '{"a": 1}'
    assert parse_reply(reply(None), WHERE) is None
    assert parse_reply(reply([1, {"k": 2.5}]), WHERE) == [1, {"k": 2.5}]


def test_well_formed_fault_is_vendor_error_naming_the_call() -> None:
    with pytest.raises(VendorError, match=r"^o3r error 101000: O3R XML-RPC 10.0.0.1:80 get\(\['/ports'\]\): "
                                          r"no such key$") as ei:
        parse_reply(fault("<int>101000</int>"), WHERE)
    assert ei.value.code == 101000
    with pytest.raises(VendorError, match=r"no\\nsuch\\tkey$"):  # control characters escaped: one line
        parse_reply(fault("<int>7</int>", "<string>no\nsuch\tkey</string>"), WHERE)


@pytest.mark.parametrize(("code_xml", "text_xml", "shown"), [
    ("<string>abc</string>", "<string>x</string>", "faultCode 'abc' and faultString 'x'"),
    ("<boolean>1</boolean>", "<string>x</string>", "faultCode True"),
    ("<double>1e308</double>", "<string>x</string>", "faultCode 1e+308"),
    ("<int>3</int>", "<int>4</int>", "faultCode 3 and faultString 4"),
    ("<array><data></data></array>", "<string>x</string>", "faultCode an array"),
])
def test_fault_with_wrong_types_is_protocol_error(code_xml: str, text_xml: str, shown: str) -> None:
    with pytest.raises(ProtocolError, match=f"^{WHERE_RE}: fault reply with {re.escape(shown)}"):
        parse_reply(fault(code_xml, text_xml), WHERE)


@pytest.mark.parametrize(("body", "why"), [
    (b"<!DOCTYPE x [<!ENTITY a 'aaaa'><!ENTITY b '&a;&a;&a;&a;'>]><methodResponse/>", "DTDForbidden"),
    (b"<methodResponse><params><param><value><int>12x</int></value></param></params></methodResponse>",
     "ValueError"),
    (b"<methodResponse><params><param><value><int>" + b"9" * 5000 + b"</int></value></param></params>"
     b"</methodResponse>", "ValueError"),
    (b"<methodResponse><params><param><value><boolean>2</boolean></value></param></params></methodResponse>",
     "TypeError"),
    (b"<methodResponse><params><param><value><struct><value><int>1</int></value></struct></value></param>"
     b"</params></methodResponse>", "IndexError"),
    (b"<methodResponse><params><param><value><array><data></struct></value></param></params></methodResponse>",
     "ExpatError"),
    (b"<methodResponse><params><param><value><foo>1</foo></value></param></params></methodResponse>",
     "ResponseError"),
    (b"<methodResponse><fault><value><struct></struct></value></fault></methodResponse>", "TypeError"),
    (b"", "ExpatError"),
    (b"\xff\xfe<", "ExpatError"),
])
def test_malformed_replies_are_protocol_errors(body: bytes, why: str) -> None:
    with pytest.raises(ProtocolError, match=rf"malformed XML-RPC reply \(\w*{why}: ") as ei:
        parse_reply(body, WHERE)
    assert "\n" not in str(ei.value) and len(str(ei.value)) < 250


def test_nesting_and_value_count_are_bounded() -> None:
    deep = (b"<methodResponse><params><param>" + b"<value><array><data>" * (MAX_DEPTH + 1)
            + b"</data></array></value>" * (MAX_DEPTH + 1) + b"</param></params></methodResponse>")
    with pytest.raises(ProtocolError, match=f"nested deeper than {MAX_DEPTH}"):
        parse_reply(deep, WHERE)
    ok = deep.replace(b"<value><array><data>", b"", 1).replace(b"</data></array></value>", b"", 1)
    value = parse_reply(ok, WHERE)
    for _ in range(MAX_DEPTH - 1):
        value = value[0]
    assert value == []
    with pytest.raises(ProtocolError, match="holds 2 values, expected 1"):
        parse_reply(reply("a").replace(b"</param>", b"</param><param><value>b</value></param>"), WHERE)
    with pytest.raises(ProtocolError, match="holds 0 values"):
        parse_reply(b"<methodResponse><params></params></methodResponse>", WHERE)


# ---------------------------------------------------------------------- JSON
@pytest.mark.parametrize(("text", "match"), [
    ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
    ('{"a": NaN}', r"not JSON \(NaN is not JSON\)"),
    ('{"a": -Infinity}', "-Infinity is not JSON"),
    ('{"a": 1' + "0" * 5000 + "}", "not JSON"),
    ("nope", "not JSON"),
    ("[1]", "is an array, expected an object"),
    ('"x"', "is 'x', expected an object"),
    (42, "answered 42, expected a JSON string"),
    (["a"], "answered an array, expected a JSON string"),
])
def test_json_answers_are_checked(text: Any, match: str) -> None:
    with pytest.raises(ProtocolError, match=match):
        parse_json_object(text, WHERE)


# ---------------------------------------------------------------------- the tree
def test_port_info_of_a_documented_tree() -> None:
    info = port_info(json.loads(json.dumps(doc())), "port2", host="10.0.0.1", where=WHERE)
    assert (info.pcic_port, info.type, info.state, info.width, info.height) == (50012, "3D", "IDLE", 224, 172)
    no_res = doc(info={"features": {"type": "2D"}})
    assert port_info(no_res, "port2", host="h", where=WHERE).width == 0
    assert firmware(doc(), WHERE) == "1.4.30"


@pytest.mark.parametrize(("patch", "message"), [
    ({"data": {"pcicTCPPort": 1e308}}, "/ports/port2/data/pcicTCPPort must be an integer in 1..65535, got 1e+308"),
    ({"data": {"pcicTCPPort": 2**70}}, "/ports/port2/data/pcicTCPPort must be an integer in 1..65535, got an "
                                       "integer of 71 bits"),
    ({"data": {"pcicTCPPort": False}}, "/ports/port2/data/pcicTCPPort must be an integer in 1..65535, got False"),
    ({"state": ["RUN"]}, "/ports/port2/state must be one of RUN, IDLE, CONF, got an array"),
    ({"state": "run"}, "/ports/port2/state must be one of RUN, IDLE, CONF, got 'run'"),
    ({"info": {"features": {"type": "x" * 65}}}, "/ports/port2/info/features/type must be a printable string of "
                                                  "1..64 characters, got 'xxxxxxxxxx"),
    ({"info": {"features": []}}, "/ports/port2/info/features must be an object, got an array"),
    ({"info": {"features": {"type": "3D", "resolution": {"width": 0, "height": 1}}}},
     "/ports/port2/info/features/resolution/width must be an integer in 1..8192, got 0"),
    ({"info": {"features": {"type": "3D", "resolution": 5}}}, "/ports/port2/info/features/resolution must be an "
                                                              "object, got 5"),
])
def test_port_info_names_the_pointer_of_a_bad_value(patch: dict[str, Any], message: str) -> None:
    with pytest.raises(ProtocolError, match=f"^{WHERE_RE}: {re.escape(message)}"):
        port_info(doc(**patch), "port2", host="10.0.0.1", where=WHERE)


def test_unknown_port_is_a_config_error_and_bad_firmware_a_protocol_error() -> None:
    with pytest.raises(ConfigError, match=r"no port 'port5' \(ports: port0, port2\)") as ei:
        port_info(doc(), "port5", host="10.0.0.1", where=WHERE)
    assert ei.value.key == "camera.port"
    bad = doc()
    bad["device"]["swVersion"]["firmware"] = ["1"]
    with pytest.raises(ProtocolError, match="/device/swVersion/firmware must be a printable string"):
        firmware(bad, WHERE)


def test_show_clip_and_pointer() -> None:
    assert show("a\nb") == r"'a\nb'"
    assert show(b"HTTP/1.1 \x00") == r"b'HTTP/1.1 \x00'"
    assert show(None) == "null" and show(True) == "True" and show({}) == "an object"
    assert show("é" * 100).endswith("...'") and len(show("é" * 100)) <= 48
    assert clip("x" * 500, 20) == "x" * 17 + "..."
    assert pointer("ports", "a/b", "c~d") == "/ports/a~1b/c~0d"


# ---------------------------------------------------------------------- config ranges
@pytest.mark.parametrize(("key", "value", "match"), [
    ("io_timeout_s", 5e-324, "must be >= 0.01"),
    ("connect_timeout_s", 1e308, "must be <= 120"),
    ("reconnect_backoff_s", 0.0, "must be >= 0.001"),
    ("max_frame_bytes", 10**12, "must be <= 268435456"),
    ("max_buffered_bytes", 100, "must be >= 4096"),
    ("max_rpc_reply_bytes", -1, "must be >= 4096"),
    ("xmlrpc_port", 65536, "must be <= 65535"),
    ("pcic_port", 80, "is also the XML-RPC port"),
])
def test_o3r_config_keys_have_ranges_a_real_cell_can_have(key: str, value: Any, match: str) -> None:
    with pytest.raises(ConfigError, match=rf"^cell.toml: key 'camera.{key}': .*{match}"):
        parse_section(O3RConfig, {key: value}, where="camera", source="cell.toml")
    assert parse_section(O3RConfig, {}, where="camera").max_rpc_reply_bytes == 4 * 1024 * 1024
