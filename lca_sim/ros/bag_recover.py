"""`lca-record --recover BAG`: make a bag whose recorder was killed readable again.

    lca-record --recover out/run1

A recorder killed with SIGKILL (or by a power cut) never writes the MCAP summary, the footer or
`metadata.yaml`, so no reader opens the bag; it holds every message received up to at most
`--flush-period-s` before the kill (`lca_sim.ros.record_bag`), then at most one partly written
chunk. Recovery reads the MCAP record by record, keeps every schema, channel and message of the
complete chunks (a chunk with a CRC must match it), stops at the first record that runs past the
end of the file, writes the bag anew with `rosbags` (as the recorder does) and replaces the
damaged file. A complete bag (footer and metadata.yaml present) is left alone. The format
details are in docs/plotting.md ("Recording a run"), the loss bound in docs/reliability.md.

No ROS 2 here: the launcher runs it before rclpy is imported.
"""

from __future__ import annotations

import shutil
import struct
import sys
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

from rosbags.rosbag2 import StoragePlugin, Writer, WriterError
from rosbags.rosbag2.metadata import parse_qos
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from lca_sim.errors import EXIT_BAD_INPUT, EXIT_OK, FOLDER_NOT_FOUND, LcaHilError
from lca_sim.ros.tool_args import record_parser

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER = 0x01
OP_FOOTER = 0x02
OP_SCHEMA = 0x03
OP_CHANNEL = 0x04
OP_MESSAGE = 0x05
OP_CHUNK = 0x06
OP_DATA_END = 0x0F
RECORD_PREFIX = 9  # opcode byte + uint64 length
FOOTER_SIZE = RECORD_PREFIX + 20 + len(MAGIC)
QOS_KEY = "offered_qos_profiles"
WORK_DIR = ".recover"
BAG_VERSION: Final = 9


class BagRecoveryError(LcaHilError):
    """The bag cannot be recovered: no MCAP file, not an MCAP file, or an unsupported chunk."""


@dataclass(frozen=True, slots=True)
class McapChannel:
    """A channel record: a topic with its message type and offered QoS (YAML text)."""

    topic: str
    schema_id: int
    encoding: str
    qos_yaml: str


@dataclass(slots=True)
class Salvage:
    """What the readable part of an MCAP file holds.

    Attributes:
        schemas: schema id -> (message type, message definition text).
        channels: channel id -> the channel.
        messages: (channel id, log time ns, serialized data), in file order.
        complete: the file ended with a data-end record or a footer (nothing was cut off).
        kept_bytes: the length of the readable part; the rest of the file is lost.
    """

    schemas: dict[int, tuple[str, str]] = field(default_factory=dict)
    channels: dict[int, McapChannel] = field(default_factory=dict)
    messages: list[tuple[int, int, bytes]] = field(default_factory=list)
    complete: bool = False
    kept_bytes: int = 0


@dataclass(frozen=True, slots=True)
class Recovery:
    """The outcome of `recover_bag`: messages kept per topic and the bytes dropped."""

    counts: dict[str, int]
    dropped_bytes: int
    was_complete: bool


class _Cursor:
    """Reads MCAP primitives (little-endian) from a record body."""

    def __init__(self, data: bytes | memoryview) -> None:
        self.data = memoryview(data)
        self.pos = 0

    def take(self, size: int) -> memoryview:
        if self.pos + size > len(self.data):
            raise BagRecoveryError("MCAP record shorter than its fields")
        out = self.data[self.pos : self.pos + size]
        self.pos += size
        return out

    def u16(self) -> int:
        return int(struct.unpack_from("<H", self.take(2))[0])

    def u32(self) -> int:
        return int(struct.unpack_from("<I", self.take(4))[0])

    def u64(self) -> int:
        return int(struct.unpack_from("<Q", self.take(8))[0])

    def string(self) -> str:
        return bytes(self.take(self.u32())).decode("utf-8")

    def rest(self) -> bytes:
        return bytes(self.take(len(self.data) - self.pos))


def iter_records(data: memoryview, start: int) -> Iterator[tuple[int, memoryview, int]]:
    """The complete records from `start`: (opcode, body, end offset); stops at a cut-off one."""
    pos = start
    while pos + RECORD_PREFIX <= len(data):
        opcode = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        end = pos + RECORD_PREFIX + length
        if end > len(data):
            return
        yield opcode, data[pos + RECORD_PREFIX : end], end
        pos = end


def scan_mcap(data: bytes) -> Salvage:
    """The schemas, channels and messages of the complete records of an MCAP file.

    Raises:
        BagRecoveryError: Not an MCAP file, or a chunk with unsupported compression.
    """
    view = memoryview(data)
    if bytes(view[: len(MAGIC)]) != MAGIC:
        raise BagRecoveryError("not an MCAP file (bad magic)")
    salvage = Salvage(kept_bytes=len(MAGIC))
    for opcode, body, end in iter_records(view, len(MAGIC)):
        if opcode in (OP_DATA_END, OP_FOOTER):
            salvage.complete = True
            break
        if opcode == OP_CHUNK:
            records = _chunk_records(body)
            if records is None:  # a torn chunk (CRC mismatch): nothing after it is trusted
                break
            for inner_opcode, inner_body, _ in iter_records(records, 0):
                _take_record(salvage, inner_opcode, inner_body)
        else:
            _take_record(salvage, opcode, body)
        salvage.kept_bytes = end
    return salvage


def _chunk_records(body: memoryview) -> memoryview | None:
    """The records inside a chunk; None if its CRC does not match."""
    cursor = _Cursor(body)
    cursor.u64()  # message start time
    cursor.u64()  # message end time
    uncompressed_size = cursor.u64()
    crc = cursor.u32()
    compression = cursor.string()
    records = cursor.take(cursor.u64())
    if compression:
        raise BagRecoveryError(f"chunk compression {compression!r} is not supported")
    if len(records) != uncompressed_size:
        return None
    if crc and zlib.crc32(records) != crc:
        return None
    return records


def _take_record(salvage: Salvage, opcode: int, body: memoryview) -> None:
    cursor = _Cursor(body)
    if opcode == OP_SCHEMA:
        schema_id = cursor.u16()
        name = cursor.string()
        cursor.string()  # encoding: ros2msg or ros2idl, told apart again by the writer
        salvage.schemas[schema_id] = (name, bytes(cursor.take(cursor.u32())).decode("utf-8"))
    elif opcode == OP_CHANNEL:
        channel_id = cursor.u16()
        schema_id = cursor.u16()
        topic = cursor.string()
        encoding = cursor.string()
        metadata = _Cursor(cursor.take(cursor.u32()))
        qos_yaml = ""
        while metadata.pos < len(metadata.data):
            key, value = metadata.string(), metadata.string()
            if key == QOS_KEY:
                qos_yaml = value
        salvage.channels[channel_id] = McapChannel(topic, schema_id, encoding, qos_yaml)
    elif opcode == OP_MESSAGE:
        channel_id = cursor.u16()
        cursor.u32()  # sequence
        log_time_ns = cursor.u64()
        cursor.u64()  # publish time
        salvage.messages.append((channel_id, log_time_ns, cursor.rest()))


def mcap_is_complete(path: Path) -> bool:
    """True when the file ends with an MCAP footer and the closing magic."""
    size = path.stat().st_size
    if size < len(MAGIC) + FOOTER_SIZE:
        return False
    with path.open("rb") as stream:
        stream.seek(size - FOOTER_SIZE)
        tail = stream.read(FOOTER_SIZE)
    return tail[0] == OP_FOOTER and tail.endswith(MAGIC)


def find_mcap(bag: Path) -> Path:
    """The one MCAP file of a bag folder.

    Raises:
        BagRecoveryError: No folder, or not exactly one `.mcap` file in it.
    """
    if not bag.is_dir():
        raise BagRecoveryError(f"bag {bag}: {FOLDER_NOT_FOUND}")
    files = sorted(p for p in bag.glob("*.mcap") if p.is_file())
    if len(files) != 1:
        found = ", ".join(p.name for p in files) or "none"
        raise BagRecoveryError(f"bag {bag}: expected one .mcap file, found {found}")
    return files[0]


def recover_bag(bag: Path) -> Recovery:
    """Rewrite a killed recording's bag from its complete chunks (see the module doc).

    Raises:
        BagRecoveryError: The bag cannot be read or rewritten.
    """
    mcap = find_mcap(bag)
    if mcap_is_complete(mcap) and (bag / "metadata.yaml").is_file():
        return Recovery({}, 0, was_complete=True)
    data = mcap.read_bytes()
    salvage = scan_mcap(data)
    work = bag / WORK_DIR
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir()
    try:
        rebuilt = work / mcap.stem  # the writer names the file after its folder
        counts = _rewrite(salvage, rebuilt)
        (rebuilt / f"{mcap.stem}.mcap").replace(mcap)
        (rebuilt / "metadata.yaml").replace(bag / "metadata.yaml")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return Recovery(counts, len(data) - salvage.kept_bytes, was_complete=False)


def _rewrite(salvage: Salvage, output: Path) -> dict[str, int]:
    """Write the salvaged channels and messages as a new bag at `output`; counts per topic."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    writer = Writer(output, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP)
    counts: dict[str, int] = {}
    try:
        writer.open()
        connections = {}
        for channel_id, channel in salvage.channels.items():
            msgtype, msgdef = salvage.schemas.get(channel.schema_id, ("", ""))
            if not msgtype:
                raise BagRecoveryError(f"channel {channel.topic} has no schema record")
            connections[channel_id] = writer.add_connection(
                channel.topic,
                msgtype,
                typestore=_typestore_for(typestore, msgtype, msgdef),
                serialization_format=channel.encoding,
                offered_qos_profiles=parse_qos(channel.qos_yaml),
            )
            counts[channel.topic] = 0
        for channel_id, stamp_ns, raw in salvage.messages:
            connection = connections.get(channel_id)
            if connection is not None:  # a message before its channel cannot be placed
                writer.write(connection, stamp_ns, raw)
                counts[connection.topic] += 1
        writer.close()
    except WriterError as exc:
        raise BagRecoveryError(f"cannot rewrite the bag: {exc}") from None
    return counts


def _typestore_for(jazzy: Typestore, msgtype: str, msgdef: str) -> Typestore:
    """The Jazzy typestore, or one that knows `msgtype` from the bag's own definition."""
    if msgtype in jazzy.types:
        return jazzy
    store = get_typestore(Stores.EMPTY)
    try:
        store.register(get_types_from_msg(msgdef, msgtype))
    except Exception as exc:  # rosbags raises its own parse errors
        raise BagRecoveryError(f"cannot parse the definition of {msgtype}: {exc}") from None
    return store


def recover_and_report(bag: Path) -> int:
    """Recover `bag` and print what was kept; the exit code (2: cannot be recovered)."""
    try:
        result = recover_bag(bag)
    except (BagRecoveryError, OSError) as exc:
        print(f"lca-record: error: {exc}", file=sys.stderr, flush=True)
        return EXIT_BAD_INPUT
    if result.was_complete:
        print(f"lca-record: {bag} is complete; nothing to recover", file=sys.stderr, flush=True)
        return EXIT_OK
    total = sum(result.counts.values())
    lines = [
        f"lca-record: recovered {total} messages in {bag} "
        f"({result.dropped_bytes} bytes of a cut-off chunk dropped)"
    ]
    width = max((len(t) for t in result.counts), default=0)
    lines += [f"  {topic:<{width}}  {n}" for topic, n in result.counts.items()]
    print("\n".join(lines), file=sys.stderr, flush=True)
    return EXIT_OK


def recover_main(own_args: Sequence[str]) -> int:
    """`lca-record --recover BAG` (the script's own arguments, no ROS ones)."""
    parser = record_parser()
    args = parser.parse_args(list(own_args))
    if args.topics or args.all:
        parser.error("--recover takes no TOPIC and no --all")
    return recover_and_report(args.recover)
