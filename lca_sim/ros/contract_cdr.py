"""The plant contract's per-cycle messages as serialized CDR, ready for `Publisher.publish(bytes)`.

And the other way for the command arrays: `float64_multi_array_data` reads a taken
Float64MultiArray's data from its bytes (the bridge's polled commands, `BridgeCommands.poll`).

rclpy's `publish` of a message converts it field by field from Python to C, most of the CPU a
publish costs; a `bytes` payload goes to the middleware as it is (docs/can-transport.md).
`ContractCdr` writes joint_states / motor_states (sensor_msgs/JointState), /clock
(rosgraph_msgs/Clock) and drive_chain_states (diagnostic_msgs/DiagnosticArray) as the bytes
rclpy's serializer produces: XCDR1 little endian (encapsulation 00 01 00 00, every field
aligned to its size counted from after those four bytes, no padding after the last field),
padding bytes zero (Fast CDR leaves them as it finds them; readers skip them). Whatever is the
same every cycle (frame_id, the joint names, keys, status names, sequence lengths, padding) is
laid out once, at construction.

The drive-chain values are the contract's strings (`lca_control.contract`): the drive-state
name (also the status message) or UNKNOWN for a code outside the snapshot's `state_names`, the
motion-state name or UNKNOWN, numbers as repr(float) ('nan', 'inf', '-0.0' included), the
faults text or NO_FAULTS. No ROS import: the tests hold it to rclpy's own serializer.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass

from lca_control import contract as pc
from lca_control.contract import PlantSnapshot
from lca_sim.errors import LcaHilError

ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR_LE: representation 0x0001, options 0
LEVEL_OK = 0  # diagnostic_msgs/DiagnosticStatus.OK
_U32 = struct.Struct("<I")
# The length fields of the numbers' texts: repr() of a float is at most 24 characters.
_HEADS = tuple(_U32.pack(length + 1) for length in range(32))

_Piece = tuple[bytes, int]  # a string's length field and UTF-8 text (no NUL), its length mod 4


@dataclass(frozen=True, slots=True)
class DriveChainRows:
    """drive_chain_states' values, per joint as plain floats, in the snapshot's joint order.

    Attributes:
        motion_state, drive_state: the codes as in `PlantSnapshot` (NaN or out of range:
            UNKNOWN).
        numbers: per joint, the `DRIVE_NUMBER_KEYS` values in that order.
        state_names: the robot's drive-state names.
        faults: per joint, the `faults` text; (): NO_FAULTS on every joint.
    """

    motion_state: Sequence[float]
    drive_state: Sequence[float]
    numbers: Sequence[Sequence[float]]
    state_names: tuple[str, ...]
    faults: tuple[str, ...] = ()


def drive_chain_rows(snap: PlantSnapshot) -> DriveChainRows:
    """A snapshot's drive-chain values as plain lists."""
    return DriveChainRows(
        snap.motion_state.tolist(),
        snap.drive_state.tolist(),
        list(zip(*(getattr(snap, key).tolist() for key in pc.DRIVE_NUMBER_KEYS), strict=True)),
        snap.state_names,
        snap.faults,
    )


def stamp_parts(t_s: float) -> tuple[int, int]:
    """Seconds to builtin_interfaces/Time's (sec, nanosec), nanoseconds rounded."""
    sec = math.floor(t_s)
    nanosec = round((t_s - sec) * 1e9)
    if nanosec >= 1_000_000_000:
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    return sec, nanosec


def _piece(text: str) -> _Piece:
    """A string's length field (bytes with the NUL) and its UTF-8 text, without the NUL."""
    data = text.encode()
    return _U32.pack(len(data) + 1) + data, len(data) & 3


class _Layout:
    """Constant CDR bytes laid out from a known offset (construction time only)."""

    def __init__(self, offset: int) -> None:
        self.offset = offset
        self._parts: list[bytes] = []

    def _put(self, data: bytes) -> None:
        self._parts.append(data)
        self.offset += len(data)

    def align(self, size: int) -> None:
        self._put(bytes(-self.offset % size))

    def u8(self, value: int) -> None:
        self._put(bytes((value,)))

    def u32(self, value: int) -> None:
        self.align(4)
        self._put(_U32.pack(value))

    def string(self, text: str) -> None:
        self.align(4)
        data = text.encode()
        self._put(_U32.pack(len(data) + 1) + data + b"\x00")

    def skip(self, size: int) -> None:
        """Bytes written by someone else (the varying fields)."""
        self.offset += size

    def take(self) -> bytes:
        """The bytes laid out since the last take."""
        data = b"".join(self._parts)
        self._parts.clear()
        return data


def _joiners(after: Sequence[tuple[str, int | str]], *, last: bool = False) -> tuple[bytes, ...]:
    """What follows a varying string, indexed by its UTF-8 length mod 4.

    Its NUL, the constant fields `after` (("u8", value), ("u32", value) or ("string", text)),
    then the padding before the next varying string's length field (none after the message's
    last field: `last`).
    """
    tables = []
    for mod in range(4):
        layout = _Layout(mod)  # the string's text started 4-aligned
        layout.u8(0)  # its NUL
        for kind, value in after:
            if kind == "string":
                layout.string(str(value))
            elif kind == "u32":
                layout.u32(int(value))
            else:
                layout.u8(int(value))
        if not last:
            layout.align(4)
        tables.append(layout.take())
    return tuple(tables)


class ContractCdr:
    """The serialized state messages of one plant, for a fixed joint tuple.

    Args:
        joints: the joint names, in the order every snapshot carries them.
    """

    def __init__(self, joints: Sequence[str]) -> None:
        self.joints = tuple(joints)
        n = len(self.joints)
        layout = _Layout(8)  # after the stamp (sec int32, nanosec uint32)
        layout.string("")  # frame_id
        layout.u32(n)
        for name in self.joints:
            layout.string(name)
        layout.u32(n)
        layout.align(8)
        self._names = layout.take()
        layout.skip(8 * n)
        layout.u32(n)
        layout.align(8)
        self._between = layout.take()  # the same between position/velocity and velocity/effort
        self._joint_state = struct.Struct(
            f"<4siI{len(self._names)}s{n}d{len(self._between)}s{n}d{len(self._between)}s{n}d"
        )
        self._clock = struct.Struct("<4siI")

        # drive_chain_states: the constant run up to the first status's message, then a joiner
        # table after each varying string (the message, then each key's value, in
        # DRIVE_STATE_KEYS order: motion_state, drive_state, the numbers, faults).
        statuses = [pc.DRIVE_STATUS_PREFIX + joint for joint in self.joints]
        layout = _Layout(8)
        layout.string("")  # frame_id
        layout.u32(n)
        if statuses:
            layout.u8(LEVEL_OK)
            layout.string(statuses[0])
            layout.align(4)
        self._drive_head = layout.take()
        self._drive_start = struct.Struct(f"<4siI{len(self._drive_head)}s")
        keys = pc.DRIVE_STATE_KEYS
        self._after_message = _joiners([("string", ""), ("u32", len(keys)), ("string", keys[0])])
        after_value = [_joiners([("string", key)]) for key in keys[1:]]
        self._after_motion, self._after_drive = after_value[:2]
        # a number's text is at most 31 bytes: its joiners by length, not length mod 4
        self._after_numbers = tuple(
            tuple(table[length & 3] for length in range(len(_HEADS))) for table in after_value[2:]
        )
        self._after_faults = (  # the next status's level and name; nothing after the last
            *(_joiners([("u8", LEVEL_OK), ("string", status)]) for status in statuses[1:]),
            _joiners([], last=True),
        )
        self._motion_pieces = {code: _piece(name) for code, name in pc.MOTION_STATE_NAMES.items()}
        self._unknown = _piece(pc.UNKNOWN)
        self._no_faults = _piece(pc.NO_FAULTS)
        self._state_names: tuple[str, ...] = ()
        self._drive_pieces: tuple[_Piece, ...] = ()

    def joint_state(
        self,
        sec: int,
        nanosec: int,
        position: Sequence[float],
        velocity: Sequence[float],
        effort: Sequence[float],
    ) -> bytes:
        """A sensor_msgs/JointState: the stamp, empty frame_id, the joints, the three arrays.

        The values are plain floats in joint order (an array's `tolist()`).
        """
        between = self._between
        return self._joint_state.pack(
            ENCAPSULATION,
            sec,
            nanosec,
            self._names,
            *position,
            between,
            *velocity,
            between,
            *effort,
        )

    def clock(self, sec: int, nanosec: int) -> bytes:
        """A rosgraph_msgs/Clock."""
        return self._clock.pack(ENCAPSULATION, sec, nanosec)

    def drive_chain(self, sec: int, nanosec: int, rows: DriveChainRows) -> bytes:
        """A diagnostic_msgs/DiagnosticArray: one `drive_chain/<joint>` status per joint.

        Level OK, the drive-state name as the message, no hardware_id, the DRIVE_STATE_KEYS
        values in the contract's text form (module docstring).
        """
        names = rows.state_names
        if names is not self._state_names:  # a robot's vocabulary: the same tuple every cycle
            self._drive_pieces = tuple(_piece(name) for name in names)
            self._state_names = names
        drive_pieces = self._drive_pieces
        n_names = len(drive_pieces)
        motion_pieces = self._motion_pieces
        unknown = self._unknown
        after_message, after_motion, after_drive = (
            self._after_message,
            self._after_motion,
            self._after_drive,
        )
        after_numbers, after_faults = self._after_numbers, self._after_faults
        heads = _HEADS
        motion = rows.motion_state
        drive = rows.drive_state
        faults = rows.faults
        out = [self._drive_start.pack(ENCAPSULATION, sec, nanosec, self._drive_head)]
        for a, numbers in enumerate(rows.numbers):
            code = drive[a]
            state, state_mod = drive_pieces[int(code)] if 0 <= code < n_names else unknown
            moving, moving_mod = motion_pieces.get(motion[a], unknown)
            out += (
                state,
                after_message[state_mod],
                moving,
                after_motion[moving_mod],
                state,
                after_drive[state_mod],
            )
            for joiner, number in zip(after_numbers, numbers, strict=True):
                text = repr(number).encode()
                length = len(text)
                out += (heads[length], text, joiner[length])
            fault, fault_mod = _piece(faults[a]) if faults else self._no_faults
            out += (fault, after_faults[a][fault_mod])
        return b"".join(out)


class CdrError(LcaHilError, ValueError):
    """Bytes that are not the serialized message they were taken as."""


def float64_multi_array_data(cdr: bytes) -> list[float]:
    """The `data` of a serialized std_msgs/Float64MultiArray (XCDR1 little endian).

    The layout (its dims' labels, sizes and strides, and data_offset) is read past, not kept:
    the command topics carry plain arrays in joint order (docs/contract.md).

    Raises:
        CdrError: not little-endian CDR, or shorter than its lengths say.
    """
    if cdr[:2] != ENCAPSULATION[:2]:
        raise CdrError(f"not little-endian CDR: encapsulation {cdr[:4].hex()}")
    try:
        (n_dims,) = _U32.unpack_from(cdr, 4)
        at = 8
        for _ in range(n_dims):  # MultiArrayDimension: label (string), size, stride (uint32)
            (label_length,) = _U32.unpack_from(cdr, at)
            at += 4 + label_length
            at += -(at - 4) % 4 + 8
        at += -(at - 4) % 4 + 4  # data_offset
        (count,) = _U32.unpack_from(cdr, at)
        at += 4
        at += -(at - 4) % 8
        return list(struct.unpack_from(f"<{count}d", cdr, at))
    except struct.error as exc:
        raise CdrError(f"a Float64MultiArray cut short ({len(cdr)} bytes): {exc}") from exc
