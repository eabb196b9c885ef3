"""The UR emulator's RTDE codec against the wire facts of shared/spec/protocols.md C2."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellcal.devices.errors import ProtocolError
from cellcal.sims.ur import rtde_wire as w

#: What ur_rtde 1.6.5's RTDEReceiveInterface asks for by default at PolyScope 5.11 (observed).
RECEIVE_DEFAULT = (
    "timestamp,target_q,target_qd,target_qdd,target_current,target_moment,actual_q,actual_qd,actual_current,"
    "joint_control_output,actual_TCP_pose,actual_TCP_speed,actual_TCP_force,target_TCP_pose,target_TCP_speed,"
    "actual_digital_input_bits,joint_temperatures,actual_execution_time,robot_mode,joint_mode,safety_mode,"
    "actual_tool_accelerometer,speed_scaling,target_speed_fraction,actual_momentum,actual_main_voltage,"
    "actual_robot_voltage,actual_robot_current,actual_joint_voltage,actual_digital_output_bits,runtime_state,"
    "standard_analog_input0,standard_analog_input1,standard_analog_output0,standard_analog_output1,"
    "robot_status_bits,safety_status_bits,ft_raw_wrench,payload,payload_cog,payload_inertia,output_int_register_2,"
    + ",".join(f"output_int_register_{i}" for i in range(12, 20)) + ","
    + ",".join(f"output_double_register_{i}" for i in range(12, 20)) + ",")
#: The control interface's outputs (C2).
CONTROL_OUTPUTS = ("timestamp,robot_status_bits,safety_status_bits,runtime_state,output_int_register_0,"
                   "output_int_register_1,output_int_register_2," +
                   ",".join(f"output_double_register_{i}" for i in range(6)) + ",")
#: C2: the sizes ur_rtde decodes each default name with.
EXPECTED_SIZES = {"VECTOR6D": 48, "VECTOR3D": 24, "UINT64": 8, "INT32": 4, "UINT32": 4, "VECTOR6INT32": 24,
                  "DOUBLE": 8}


def test_every_name_ur_rtde_asks_for_has_the_type_it_decodes() -> None:
    freq, names = w.parse_output_setup(struct.pack(">d", 500.0) + RECEIVE_DEFAULT.encode())
    assert freq == 500.0 and len(names) == 58          # the trailing comma is no name
    types = {n: w.output_type(n) for n in names}
    assert None not in types.values()
    assert {n for n, t in types.items() if t == "VECTOR3D"} == {"actual_tool_accelerometer", "payload_cog"}
    assert {n for n, t in types.items() if t == "UINT64"} == {"actual_digital_input_bits",
                                                              "actual_digital_output_bits"}
    assert {n for n, t in types.items() if t == "UINT32"} == {"robot_status_bits", "safety_status_bits",
                                                              "runtime_state"}
    assert {n for n, t in types.items() if t == "INT32"} == {"robot_mode", "safety_mode"} | {
        n for n in names if n.startswith("output_int_register_")}
    assert types["joint_mode"] == "VECTOR6INT32"
    recipe = w.Recipe(1, names, tuple(t for t in types.values() if t is not None))
    assert recipe.size == sum(EXPECTED_SIZES[t] for t in recipe.types)
    _, control = w.parse_output_setup(struct.pack(">d", 500.0) + CONTROL_OUTPUTS.encode())
    assert [w.output_type(n) for n in control] == ["DOUBLE", "UINT32", "UINT32", "UINT32"] + ["INT32"] * 3 + [
        "DOUBLE"] * 6


@pytest.mark.parametrize(("name", "output", "writable"), [
    ("input_int_register_0", "INT32", "INT32"), ("input_double_register_47", "DOUBLE", "DOUBLE"),
    ("input_bit_register_64", "BOOL", "BOOL"), ("input_int_register_48", None, None),
    ("input_bit_register_63", None, None), ("output_int_register_3", "INT32", None),
    ("standard_digital_output_mask", "UINT8", "UINT8"), ("actual_TCP_pose", "VECTOR6D", None),
    ("no_such_field", None, None),
])
def test_field_types_and_which_may_be_written(name: str, output: str | None, writable: str | None) -> None:
    assert (w.output_type(name), w.input_type(name)) == (output, writable)


def test_framing_splits_messages_in_any_chunks_and_rejects_a_short_size() -> None:
    stream = w.message(86, b"\x00\x02") + w.message(118) + w.message(83)
    assert stream[:5] == b"\x00\x05V\x00\x02"           # u16 size (header included), type, payload
    reader = w.FrameReader()
    got = [m for byte in stream for m in reader.feed(bytes([byte]))]
    assert got == [(86, b"\x00\x02"), (118, b""), (83, b"")]
    with pytest.raises(ProtocolError, match="smaller than the 3-byte header"):
        w.FrameReader().feed(b"\x00\x02V")
    with pytest.raises(ProtocolError, match="exceeds"):
        w.message(85, bytes(70000))


def test_setup_requests_are_checked() -> None:
    assert w.parse_protocol_request(b"\x00\x02") == 2
    with pytest.raises(ProtocolError):
        w.parse_protocol_request(b"\x02")
    assert w.parse_input_setup(b"input_int_register_0,input_double_register_0,") == (
        "input_int_register_0", "input_double_register_0")
    for bad in (b"a,,b", b",", "r\u00e9gister".encode()):
        with pytest.raises(ProtocolError):
            w.parse_input_setup(bad)
    with pytest.raises(ProtocolError, match="too short"):
        w.parse_output_setup(b"\x00" * 8)


def test_replies_follow_the_spec_layouts() -> None:
    assert w.protocol_reply(True) == b"\x00\x04V\x01"
    assert w.version_reply(5, 11, 0, 0) == b"\x00\x13v" + struct.pack(">IIII", 5, 11, 0, 0)
    assert w.setup_reply(w.CONTROL_PACKAGE_SETUP_INPUTS, 4, ["INT32", "IN_USE"]) == b"\x00\x10I\x04INT32,IN_USE"
    assert w.start_reply(True) == b"\x00\x04S\x01" and w.pause_reply(False) == b"\x00\x04P\x00"
    msg = w.text_message("hi", "src", 2)
    assert msg == b"\x00\x0bM\x02hi\x03src\x02"


_VALUES = {
    "BOOL": st.booleans(), "UINT8": st.integers(0, 255), "UINT32": st.integers(0, 2**32 - 1),
    "UINT64": st.integers(0, 2**64 - 1), "INT32": st.integers(-(2**31), 2**31 - 1),
    "DOUBLE": st.floats(allow_nan=False, width=64),
    "VECTOR3D": st.tuples(*[st.floats(allow_nan=False)] * 3),
    "VECTOR6D": st.tuples(*[st.floats(allow_nan=False)] * 6),
    "VECTOR6INT32": st.tuples(*[st.integers(-(2**31), 2**31 - 1)] * 6),
    "VECTOR6UINT32": st.tuples(*[st.integers(0, 2**32 - 1)] * 6),
}


@settings(max_examples=80, deadline=None)
@given(st.lists(st.sampled_from(sorted(_VALUES)), min_size=1, max_size=12).flatmap(
    lambda kinds: st.tuples(st.just(kinds), st.tuples(*[_VALUES[k] for k in kinds]))))
def test_recipes_pack_and_unpack_every_type(case: tuple[list[str], tuple[object, ...]]) -> None:
    kinds, values = case
    names = tuple(f"f{i}" for i in range(len(kinds)))
    recipe = w.Recipe(3, names, tuple(kinds))
    body = recipe.pack(values)
    assert len(body) == recipe.size
    assert recipe.unpack(body) == dict(zip(names, values, strict=True))
    package = w.data_package(3, body)
    assert package[:3] == struct.pack(">HB", 3 + 1 + len(body), 85) and package[3] == 3
    with pytest.raises(ProtocolError):
        recipe.unpack(body + b"\x00")
