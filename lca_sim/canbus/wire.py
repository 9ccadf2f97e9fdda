"""python-can-remote's wire protocol: the CAN frame as a websocket payload, and the framing.

Subprotocol "can.binary+json.v1": after the HTTP upgrade and a JSON `bus_request` /
`bus_response`, one binary websocket message per CAN frame::

    01 | timestamp f64 | arbitration id u32 | dlc u8 | flags u8 | data      (big-endian)

Only the little of RFC 6455 the relay and its client need (docs/can-transport.md).
"""

from __future__ import annotations

import base64
import hashlib
import random
import struct
from collections.abc import Sequence
from urllib.parse import urlsplit

import can

from lca_sim.errors import InvalidValueError, LcaHilError

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 54701  # python-can-remote's default port
PROTOCOL = "can.binary+json.v1"  # python-can-remote's binary subprotocol (the only one relayed)
MESSAGE_TYPE = 0x01
HEADER = struct.Struct(">BdIBB")  # type, timestamp, arbitration id, dlc, flags
IS_EXTENDED_ID = 0x01
IS_REMOTE_FRAME = 0x02
IS_ERROR_FRAME = 0x04
IS_FD = 0x08
IS_BRS = 0x10
IS_ESI = 0x20
MAX_PAYLOAD = HEADER.size + 64  # the longest CAN FD frame
MAX_BASE_ID = 0x7FF  # the largest 11-bit identifier
MAX_HTTP_REQUEST = 16384
WS_GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
OP_TEXT, OP_BINARY, OP_CLOSE, OP_PING, OP_PONG = 0x1, 0x2, 0x8, 0x9, 0xA
RECV_CHUNK = 65536


# --- the frame codec (python-can-remote's binary message) -------------------------------------


def encode_message(msg: can.Message) -> bytes:
    """One CAN frame as python-can-remote's binary websocket payload."""
    flags = (
        (IS_EXTENDED_ID if msg.is_extended_id else 0)
        | (IS_REMOTE_FRAME if msg.is_remote_frame else 0)
        | (IS_ERROR_FRAME if msg.is_error_frame else 0)
        | (IS_FD if msg.is_fd else 0)
        | (IS_BRS if msg.bitrate_switch else 0)
        | (IS_ESI if msg.error_state_indicator else 0)
    )
    header = HEADER.pack(MESSAGE_TYPE, msg.timestamp, msg.arbitration_id, msg.dlc, flags)
    return header + bytes(msg.data)


def encode_data_frame(arbitration_id: int, data: bytes) -> bytes:
    """`encode_message` of a new classical 11-bit data frame (no flags, timestamp 0), at once."""
    return HEADER.pack(MESSAGE_TYPE, 0.0, arbitration_id, len(data), 0) + bytes(data)


def decode_data_frame(payload: bytes | bytearray) -> tuple[int, bytes] | None:
    """(COB-ID, data) of a classical 11-bit data frame of at most 8 bytes, else None.

    Every frame of a CANopen cycle is one; `decode_message` takes the others (29-bit, remote,
    error and CAN FD frames, a DLC that does not match the data) and refuses what is no frame.
    """
    if len(payload) < HEADER.size or payload[0] != MESSAGE_TYPE:
        return None
    _type, _sent, arbitration_id, dlc, flags = HEADER.unpack_from(payload)
    data = bytes(payload[HEADER.size :])
    if flags or arbitration_id > MAX_BASE_ID or dlc > 8 or dlc != len(data):
        return None
    return arbitration_id, data


def decode_message(payload: bytes | bytearray, timestamp: float) -> can.Message:
    """A binary payload back into a frame, stamped `timestamp`; ValueError if it is not one."""
    if len(payload) < HEADER.size or payload[0] != MESSAGE_TYPE:
        raise InvalidValueError(f"not a CAN frame message ({len(payload)} bytes)")
    _type, _sent, arbitration_id, dlc, flags = HEADER.unpack_from(payload)
    data = payload[HEADER.size :]
    if not flags:  # a classical base data frame (all of CANopen's): half the keywords to parse
        return can.Message(
            timestamp=timestamp,
            arbitration_id=arbitration_id,
            is_extended_id=False,
            dlc=dlc,
            data=data,
        )
    return can.Message(
        timestamp=timestamp,
        arbitration_id=arbitration_id,
        is_extended_id=flags & IS_EXTENDED_ID != 0,
        is_remote_frame=flags & IS_REMOTE_FRAME != 0,
        is_error_frame=flags & IS_ERROR_FRAME != 0,
        is_fd=flags & IS_FD != 0,
        bitrate_switch=flags & IS_BRS != 0,
        error_state_indicator=flags & IS_ESI != 0,
        dlc=dlc,
        data=data,
    )


# --- websocket framing (RFC 6455, the little of it this needs) --------------------------------


class ProtocolError(LcaHilError):
    """The peer broke the websocket framing."""


def _xor_mask(data: bytes, key: bytes) -> bytes:
    n = len(data)
    pad = (key * (n // 4 + 1))[:n]
    return (int.from_bytes(data, "little") ^ int.from_bytes(pad, "little")).to_bytes(n, "little")


def ws_frame(opcode: int, payload: bytes, mask: bool = False) -> bytes:
    """One final websocket frame; masked (as a client must send) with a random key if `mask`."""
    n = len(payload)
    if n < 126:
        head = bytes((0x80 | opcode, (0x80 if mask else 0) | n))
    elif n < 65536:
        head = bytes((0x80 | opcode, (0x80 if mask else 0) | 126)) + struct.pack(">H", n)
    else:
        head = bytes((0x80 | opcode, (0x80 if mask else 0) | 127)) + struct.pack(">Q", n)
    if not mask:
        return head + payload
    key = random.getrandbits(32).to_bytes(4, "little")
    return head + key + _xor_mask(payload, key)


def masked_data_frames(frames: Sequence[tuple[int, bytes]]) -> bytes:
    """Classical 11-bit data frames as a client sends them: one masked binary message each.

    The bytes of `ws_frame(OP_BINARY, encode_data_frame(id, data), mask=True)` for each frame,
    keys drawn alike (RFC 6455 5.3: a fresh key per frame), in one call for all: a drive's
    TPDOs after every SYNC go this way.
    """
    keys = random.getrandbits(32 * len(frames)).to_bytes(4 * len(frames), "little")
    out = bytearray()
    for k, (arbitration_id, data) in enumerate(frames):
        payload = encode_data_frame(arbitration_id, data)  # < 126 bytes: the short length form
        key = keys[4 * k : 4 * k + 4]
        out += bytes((0x80 | OP_BINARY, 0x80 | len(payload)))
        out += key
        out += _xor_mask(payload, key)
    return bytes(out)


def parse_frames(buf: bytearray, limit: int = 65536) -> list[tuple[int, bytes]]:
    """Take every complete frame off the front of `buf`: (opcode, unmasked payload) each."""
    frames: list[tuple[int, bytes]] = []
    pos = 0
    size = len(buf)
    while size - pos >= 2:
        b1, b2 = buf[pos], buf[pos + 1]
        if not b1 & 0x80:
            raise ProtocolError("fragmented websocket messages are not supported")
        n = b2 & 0x7F
        head = 2
        if n == 126:
            if size - pos < 4:
                break
            (n,) = struct.unpack_from(">H", buf, pos + 2)
            head = 4
        elif n == 127:
            if size - pos < 10:
                break
            (n,) = struct.unpack_from(">Q", buf, pos + 2)
            head = 10
        if n > limit:
            raise ProtocolError(f"websocket frame of {n} bytes")
        masked = b2 & 0x80
        end = pos + head + (4 if masked else 0) + n
        if end > size:
            break
        if masked:
            key = bytes(buf[pos + head : pos + head + 4])
            payload = _xor_mask(bytes(buf[end - n : end]), key)
        else:
            payload = bytes(buf[end - n : end])
        frames.append((b1 & 0x0F, payload))
        pos = end
    del buf[:pos]
    return frames


def accept_key(key: str) -> str:
    """Sec-WebSocket-Accept for a Sec-WebSocket-Key."""
    return base64.b64encode(hashlib.sha1(key.encode("ascii") + WS_GUID).digest()).decode()


def channel_url(channel: object) -> tuple[str, int, str]:
    """host, port, url of a channel: "ws://host:port/", "host:port" or "host" (default port)."""
    text = str(channel) if channel is not None else f"{DEFAULT_HOST}:{DEFAULT_PORT}"
    if "://" not in text:
        text = "ws://" + text
    parts = urlsplit(text)
    if parts.scheme != "ws":
        raise InvalidValueError(f"channel {channel!r}: only ws:// is supported")
    host = parts.hostname or DEFAULT_HOST
    port = parts.port or DEFAULT_PORT
    return host, port, f"ws://{host}:{port}{parts.path or '/'}"
