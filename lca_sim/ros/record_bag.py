"""The bag `lca-record` writes: rosbag2 version 9, MCAP, its open chunk flushed often.

`BagFile`, the writer part of `lca_sim.ros.record.BagRecorder`, writes with `rosbags` and the
ROS 2 Jazzy typestore (message definitions, RIHS01 type hashes), as `ros2 bag record` does.
Crash safety: rosbags alone closes a chunk only at 1 MiB, so a killed recorder lost everything
after the last full one. Here the open chunk is closed and flushed every `FLUSH_SHARE` (0.4) of
the loss bound `--flush-period-s`: at the first message after that interval, and from a steady
timer when messages stop; the rest of the bound is left for that callback or timer to come late
on a loaded machine. `lca_sim.ros.bag_recover` reads such a bag. A write costs about 5 us, so
the subscription callbacks write directly, under the bag's lock. No rclpy here.
"""

from __future__ import annotations

import math
import threading
import time
from enum import Enum
from pathlib import Path
from typing import Any, cast

from rosbags.interfaces import (
    Connection,
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import StoragePlugin, Writer, WriterError
from rosbags.rosbag2.storage_mcap import McapWriter
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from lca_sim.errors import LcaHilError

NS_PER_S = 1_000_000_000
# The open chunk is flushed every FLUSH_SHARE of the loss bound; the rest of the bound is left
# for the callback or timer that does it to come late (the module doc).
FLUSH_SHARE = 0.4


class RecorderError(LcaHilError):
    """The recorder cannot start: bad output folder, bad topic name or message type."""


def _qos_time(duration_ns: int) -> QosTime:
    sec, nsec = divmod(duration_ns, NS_PER_S)
    return QosTime(sec=sec, nsec=nsec)


def bag_qos(profile: Any) -> Qos:
    """A publisher's rclpy QoS profile as the rosbags metadata record (offered_qos_profiles)."""

    def pick(enum_type: type[Enum], name: str) -> Any:
        return enum_type[name] if name in enum_type.__members__ else enum_type["UNKNOWN"]

    return Qos(
        history=pick(QosHistory, profile.history.name),
        depth=int(profile.depth),
        reliability=pick(QosReliability, profile.reliability.name),
        durability=pick(QosDurability, profile.durability.name),
        deadline=_qos_time(profile.deadline.nanoseconds),
        lifespan=_qos_time(profile.lifespan.nanoseconds),
        liveliness=pick(QosLiveliness, profile.liveliness.name),
        liveliness_lease_duration=_qos_time(profile.liveliness_lease_duration.nanoseconds),
        avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions),
    )


class BagFile:
    """A new bag folder, written under one lock by subscription callbacks of any thread.

    Args:
        output: the bag folder to create; it must not exist.
        max_loss_s: the most a killed recorder may lose of what it received, s: the open MCAP
            chunk is closed and flushed every `FLUSH_SHARE` of it (steady clock).

    Raises:
        RecorderError: the loss bound is not > 0 and finite.
    """

    def __init__(self, output: Path, max_loss_s: float) -> None:
        if not max_loss_s > 0 or math.isinf(max_loss_s):
            raise RecorderError(f"the loss bound must be > 0 and finite, not {max_loss_s}")
        self.output = output
        self.max_loss_s = max_loss_s
        self.flush_interval_s = FLUSH_SHARE * max_loss_s
        self.typestore: Typestore = get_typestore(Stores.ROS2_JAZZY)
        # Guards the writer and what callers count with it (their message counts).
        self.lock = threading.Lock()
        self._writer: Writer | None = None
        self._next_flush_s = math.inf

    @property
    def is_open(self) -> bool:
        """True between `open` and `close`."""
        return self._writer is not None

    def open(self) -> None:
        """Create the bag.

        Raises:
            RecorderError: the output folder exists or cannot be created.
        """
        try:
            writer = Writer(self.output, version=9, storage_plugin=StoragePlugin.MCAP)
            writer.open()
        except (WriterError, OSError) as exc:
            raise RecorderError(f"cannot create bag {self.output}: {exc}") from None
        if not isinstance(writer.storage, McapWriter):  # the flush uses its chunk interface
            writer.abort()
            raise RecorderError("rosbags' MCAP writer has changed; cannot flush chunks")
        self._writer = writer
        self._next_flush_s = time.monotonic() + self.flush_interval_s

    def add_connection(self, topic: str, msgtype: str, offered_qos: list[Any]) -> Connection:
        """A new connection (topic and type) with its publishers' rclpy QoS profiles."""
        assert self._writer is not None
        with self.lock:
            return self._writer.add_connection(
                topic,
                msgtype,
                typestore=self.typestore,
                offered_qos_profiles=[bag_qos(p) for p in offered_qos],
            )

    def write_locked(self, connection: Connection, stamp_ns: int, data: bytes) -> bool:
        """Write one message (`lock` held); False once the bag is closed. Flushes when due."""
        writer = self._writer
        if writer is None:
            return False
        writer.write(connection, stamp_ns, data)
        if time.monotonic() >= self._next_flush_s:
            self._flush_locked()
        return True

    def flush(self) -> None:
        """Close the open MCAP chunk (if it holds anything) and flush the file to the OS.

        What is flushed survives a SIGKILL of the recorder (`lca-record --recover` reads it).
        """
        with self.lock:
            self._flush_locked()

    def _flush_locked(self) -> None:
        writer = self._writer
        if writer is None:
            return
        storage = cast("McapWriter", writer.storage)
        if storage.chunk.bio.tell():
            storage.close_chunk()
        storage.bio.flush()
        self._next_flush_s = time.monotonic() + self.flush_interval_s

    def close(self) -> None:
        """Close the bag (writes metadata.yaml); idempotent."""
        with self.lock:
            writer, self._writer = self._writer, None
            if writer is not None:
                writer.close()
