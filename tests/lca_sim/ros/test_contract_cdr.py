"""ContractCdr: the plant's serialized state messages are rclpy's own, byte for byte.

Each message is also built the slow way, as an rclpy message from the snapshot with the
contract's vocabulary functions, and serialized by rclpy (`serialize_message` needs no
`rclpy.init`, no DDS: nothing here starts ROS). rclpy's serializer (Fast CDR) leaves padding
bytes as it finds them in a fresh buffer, so the comparison skips the padding, located by a
walk of the message's fields written here apart from the codec, and requires ours to be zero
there. rclpy's deserializer reads our bytes back to the values.
"""

from __future__ import annotations

import dataclasses
import math
import os
import struct
import subprocess
import sys
from typing import Any

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from hypothesis import given, settings
from hypothesis import strategies as st
from rclpy.serialization import deserialize_message, serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from lca_control import contract as pc
from lca_control.contract import PlantSnapshot
from lca_sim.ros.contract_cdr import (
    CdrError,
    ContractCdr,
    drive_chain_rows,
    float64_multi_array_data,
    stamp_parts,
)
from lca_sim.ros.node_util import to_stamp

ENCAPSULATION = 4  # bytes before the CDR body; alignment counts from after them

names_st = st.from_regex(r"[a-z][a-z0-9_]{0,14}", fullmatch=True)
joints_st = st.lists(names_st, min_size=1, max_size=6, unique=True).map(tuple)
stamp_st = st.floats(0.0, 2.0**31 - 2.0)
any_float_st = st.floats(allow_nan=True, allow_infinity=True)  # -0.0, NaNs of any payload
code_st = st.one_of(
    st.integers(-2, 6).map(float), st.sampled_from([-0.0, 0.5, 2.5, math.nan]), any_float_st
)
text_st = st.text(st.characters(exclude_categories=["Cs"], exclude_characters="\x00"))


@st.composite
def snapshots(draw: st.DrawFn, joints: tuple[str, ...] | None = None) -> PlantSnapshot:
    """A snapshot of any values.

    Floats of every kind, drive and motion codes in and out of range, faults text or none.
    """
    joints = draw(joints_st) if joints is None else joints
    n = len(joints)

    def floats(elements: st.SearchStrategy[float] = any_float_st) -> Any:
        return np.array(draw(st.lists(elements, min_size=n, max_size=n)), dtype=np.float64)

    fields = {key: floats() for key in ("position", "velocity", "effort", *pc.DRIVE_NUMBER_KEYS)}
    return PlantSnapshot(
        stamp_s=draw(stamp_st),
        joints=joints,
        motor_position_rad=floats(),
        motor_velocity_rad_s=floats(),
        motion_state=floats(code_st),
        drive_state=floats(code_st),
        state_names=tuple(draw(st.lists(names_st, min_size=1, max_size=5))),
        faults=draw(st.one_of(st.just(()), st.lists(text_st, min_size=n, max_size=n).map(tuple))),
        **fields,
    )


# ------------------------------------------------------------------------ the slow way, rclpy's


def stamp_of(snap: PlantSnapshot) -> Time:
    return to_stamp(snap.stamp_s)


def joint_state_msg(snap: PlantSnapshot, motor: bool = False) -> JointState:
    arrays = (
        (snap.motor_position_rad, snap.motor_velocity_rad_s, snap.current_a)
        if motor
        else (snap.position, snap.velocity, snap.effort)
    )
    msg = JointState(name=list(snap.joints), position=arrays[0].tolist())
    msg.velocity, msg.effort = arrays[1].tolist(), arrays[2].tolist()
    msg.header.stamp = stamp_of(snap)
    return msg


def drive_chain_msg(snap: PlantSnapshot) -> DiagnosticArray:
    array = DiagnosticArray()
    array.header.stamp = stamp_of(snap)
    for a, joint in enumerate(snap.joints):
        values = {
            "motion_state": pc.motion_state_name(float(snap.motion_state[a])),
            "drive_state": pc.drive_state_name(float(snap.drive_state[a]), snap.state_names),
            **{key: repr(float(getattr(snap, key)[a])) for key in pc.DRIVE_NUMBER_KEYS},
            "faults": snap.faults[a] if snap.faults else pc.NO_FAULTS,
        }
        array.status.append(
            DiagnosticStatus(
                level=DiagnosticStatus.OK,
                name=pc.DRIVE_STATUS_PREFIX + joint,
                message=values["drive_state"],
                values=[KeyValue(key=key, value=values[key]) for key in pc.DRIVE_STATE_KEYS],
            )
        )
    return array


class Padding:
    """Where XCDR1 pads a message: offsets into its serialized bytes.

    Each field is aligned to its own size counted from after the encapsulation; a double
    sequence's data to 8 even when it is empty.
    """

    def __init__(self, msg: Any) -> None:
        self.at: set[int] = set()
        self._pos = 0
        self._message(msg)

    def _align(self, size: int) -> None:
        while self._pos % size:
            self.at.add(ENCAPSULATION + self._pos)
            self._pos += 1

    def _fixed(self, size: int) -> None:
        self._align(size)
        self._pos += size

    def _string(self, text: str) -> None:
        self._fixed(4)
        self._pos += len(text.encode()) + 1

    def _sequence(self, kind: str, items: Any) -> None:
        self._fixed(4)
        if kind == "sequence<double>":
            self._align(8)
            self._pos += 8 * len(items)
            return
        for item in items:
            self._string(item) if kind == "sequence<string>" else self._message(item)

    def _message(self, msg: Any) -> None:
        for field, kind in msg.get_fields_and_field_types().items():
            value = getattr(msg, field)
            if kind in ("int32", "uint32"):
                self._fixed(4)
            elif kind == "octet":
                self._fixed(1)
            elif kind == "string":
                self._string(value)
            elif kind.startswith("sequence<"):
                self._sequence(kind, value)
            else:
                self._message(value)


def assert_rclpy_bytes(ours: bytes, msg: Any) -> None:
    """`ours` is what rclpy serializes `msg` to, padding aside (zero in ours), and reads back."""
    theirs = serialize_message(msg)
    assert len(ours) == len(theirs)
    pads = Padding(msg).at
    assert max(pads, default=0) < len(ours)
    differ = [i for i, (a, b) in enumerate(zip(ours, theirs, strict=True)) if a != b]
    assert set(differ) <= pads, f"bytes {sorted(set(differ) - pads)} differ from rclpy's"
    assert all(ours[i] == 0 for i in pads)
    assert same(deserialize_message(ours, type(msg)), msg)


def same(a: Any, b: Any) -> bool:
    """Message equality with floats compared bit for bit (a NaN equals the same NaN)."""
    if hasattr(a, "get_fields_and_field_types"):
        return all(same(getattr(a, f), getattr(b, f)) for f in a.get_fields_and_field_types())
    if isinstance(a, float):
        return struct.pack("<d", a) == struct.pack("<d", b)
    if isinstance(a, str | bytes | int):
        return bool(a == b)
    return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))


# --------------------------------------------------------------------------------------- tests


@settings(deadline=None)
@given(snapshots())
def test_joint_and_motor_states_are_rclpys_bytes(snap: PlantSnapshot) -> None:
    """joint_states and motor_states: rclpy's bytes for any joints, stamp and floats."""
    cdr = ContractCdr(snap.joints)
    sec, nanosec = stamp_parts(snap.stamp_s)
    assert_rclpy_bytes(
        cdr.joint_state(
            sec, nanosec, snap.position.tolist(), snap.velocity.tolist(), snap.effort.tolist()
        ),
        joint_state_msg(snap),
    )
    motor = cdr.joint_state(
        sec,
        nanosec,
        snap.motor_position_rad.tolist(),
        snap.motor_velocity_rad_s.tolist(),
        snap.current_a.tolist(),
    )
    assert_rclpy_bytes(motor, joint_state_msg(snap, motor=True))


@settings(deadline=None)
@given(snapshots())
def test_drive_chain_states_are_rclpys_bytes(snap: PlantSnapshot) -> None:
    """drive_chain_states: rclpy's bytes, the contract's texts, for any values and faults."""
    sec, nanosec = stamp_parts(snap.stamp_s)
    assert_rclpy_bytes(
        ContractCdr(snap.joints).drive_chain(sec, nanosec, drive_chain_rows(snap)),
        drive_chain_msg(snap),
    )


@settings(deadline=None)
@given(stamp_st)
def test_clock_and_stamps_are_rclpys(stamp_s: float) -> None:
    """/clock: rclpy's bytes; the stamp split is node_util.to_stamp's."""
    sec, nanosec = stamp_parts(stamp_s)
    stamp = to_stamp(stamp_s)
    assert (sec, nanosec) == (stamp.sec, stamp.nanosec)
    assert_rclpy_bytes(ContractCdr(("a",)).clock(sec, nanosec), Clock(clock=stamp))


# Names 1-4 characters long (every string padding), an odd count of 12-byte names (4 bytes
# of padding before the doubles); the robot's joints.
@pytest.mark.parametrize(
    "joints", [("a", "bc", "def", "ghij"), ("l_arm", "pivot", "c_arc", "lift")]
)
@settings(max_examples=30, deadline=None)
@given(data=st.data())
def test_names_of_every_length_mod_4_keep_the_alignment(
    joints: tuple[str, ...], data: st.DataObject
) -> None:
    """Every padding, before a length field and before the doubles, is where rclpy puts it.

    A layout off by a byte anywhere fails here; one codec makes the messages cycle after cycle.
    """
    snap = data.draw(snapshots(joints))
    cdr = ContractCdr(snap.joints)
    for shift in (0.0, 1.5e-9, 0.25):  # one codec, several cycles
        stamp_s = snap.stamp_s + shift
        sec, nanosec = stamp_parts(stamp_s)
        moved = dataclasses.replace(snap, stamp_s=stamp_s)
        js = cdr.joint_state(
            sec, nanosec, snap.position.tolist(), snap.velocity.tolist(), snap.effort.tolist()
        )
        assert_rclpy_bytes(js, joint_state_msg(moved))
        chain = cdr.drive_chain(sec, nanosec, drive_chain_rows(moved))
        assert_rclpy_bytes(chain, drive_chain_msg(moved))


def test_serialization_needs_no_ros_context() -> None:
    """Serializing needs no rclpy.init (no context, no DDS): these tests start no ROS."""
    code = (
        "import rclpy\n"
        "from rclpy.serialization import deserialize_message, serialize_message\n"
        "from sensor_msgs.msg import JointState\n"
        "data = serialize_message(JointState(name=['a']))\n"
        "assert deserialize_message(data, JointState).name == ['a']\n"
        "assert not rclpy.ok()\n"
    )
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": "218"}
    subprocess.run([sys.executable, "-c", code], check=True, env=env, timeout=120)


label_st = st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E), max_size=9)
dims_st = st.lists(
    st.builds(
        MultiArrayDimension,
        label=label_st,
        size=st.integers(0, 2**32 - 1),
        stride=st.integers(0, 2**32 - 1),
    ),
    max_size=3,
)


@given(
    dims=dims_st,
    data_offset=st.integers(0, 2**32 - 1),
    data=st.lists(any_float_st, max_size=8),
)
@settings(deadline=None)
def test_a_command_array_reads_back_from_rclpy_bytes(
    dims: list[Any], data_offset: int, data: list[float]
) -> None:
    """Any layout (labels of every length mod 4), any floats: the data, bit for bit."""
    msg = Float64MultiArray(data=data)
    msg.layout.dim = dims
    msg.layout.data_offset = data_offset
    cdr = serialize_message(msg)
    assert struct.pack(f"<{len(data)}d", *float64_multi_array_data(cdr)) == struct.pack(
        f"<{len(data)}d", *data
    )
    with pytest.raises(CdrError, match="cut short"):
        float64_multi_array_data(cdr[: len(cdr) - 1] if data else cdr[:10])


def test_big_endian_bytes_are_refused_not_misread() -> None:
    """CDR_BE (encapsulation 00 00) is no command this host's rmw sends: an error, not numbers."""
    cdr = serialize_message(Float64MultiArray(data=[1.0, 2.0]))
    with pytest.raises(CdrError, match="not little-endian"):
        float64_multi_array_data(b"\x00\x00" + cdr[2:])
