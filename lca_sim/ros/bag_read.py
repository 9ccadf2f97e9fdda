"""Reading a recorded bag's plant states, references and /diagnostics, without rclpy.

Reads a rosbag2 bag (MCAP or SQLite) with `rosbags`, deserializing with the ROS 2 Jazzy
typestore, into plain series per joint (`BagData`); `lca-plot`, `lca-hil fig15`, `identify` and
`paper` read bags through it, with ROS 2 absent. Beside the recorder (`lca_sim.ros.record`).

The time axis (`time_base`): `header` uses the messages' header stamps (the plant's own time,
simulated or wall; seconds from the earliest sample), `bag` the recorder's reception stamps
(its node clock: simulated time when it ran with `use_sim_time:=true`; seconds from the bag's
first message). `auto` takes the header stamps when every state message has one, else the bag
stamps. A zero stamp counts as none, except at the start of a series (simulated time starts at
0). Messages of other clocks or without a header (the command arrays, /diagnostics) are put, on
the header time axis, at the time of the plant state the recorder received last before them.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from lca_control.contract import (
    CURRENT_COMMANDS,
    DIAGNOSTICS,
    DRIVE_CHAIN_STATES,
    DRIVE_STATUS_PREFIX,
    JOINT_STATES,
    MOTOR_STATES,
    VELOCITY_COMMANDS,
    VELOCITY_REFERENCE,
    VOLTAGE_COMMANDS,
)
from lca_sim.errors import FOLDER_NOT_FOUND, LcaHilError

NS_PER_S = 1_000_000_000
TIME_BASES = ("auto", "header", "bag")
DRIVE_STATE_KEY = "drive_state"
ETA_KEYS = ("eta_m", "eta_l")
# The command arrays lca-plot draws beside the measured signals.
REFERENCE_TOPICS = (VELOCITY_COMMANDS, VELOCITY_REFERENCE, CURRENT_COMMANDS, VOLTAGE_COMMANDS)
# diagnostic_msgs/DiagnosticStatus levels.
LEVEL_OK = 0
LEVEL_NAMES = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}
FAULT_KEY = "fault"  # a status value naming the fault (the simulator's per-axis statuses)


@dataclass
class _Stamped:
    """Sample times of a series: both stamps in ns while reading, then the chosen one in s."""

    bag_ns: list[int] = field(default_factory=list)
    header_ns: list[int] = field(default_factory=list)
    time_s: list[float] = field(default_factory=list)

    def stamp(self, bag_ns: int, header: Any) -> None:
        self.bag_ns.append(bag_ns)
        self.header_ns.append(int(header.stamp.sec) * NS_PER_S + int(header.stamp.nanosec))


@dataclass
class JointSeries(_Stamped):
    """Samples of one joint (or axis) over time: time in s and named value lists."""

    values: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))


@dataclass
class DriveSeries(_Stamped):
    """Drive-chain samples of one axis: time in s, state names, and eta_m / eta_l."""

    state: list[str] = field(default_factory=list)
    eta: dict[str, list[float]] = field(default_factory=lambda: {k: [] for k in ETA_KEYS})


@dataclass
class ArraySeries:
    """A std_msgs/Float64MultiArray topic: one row per message, element i = the i-th joint.

    Attributes:
        bag_ns: reception stamps (the arrays have no header).
        rows: the messages' data.
        time_s: on the chosen time axis (see the module docstring: aligned with the states).
    """

    bag_ns: list[int] = field(default_factory=list)
    rows: list[list[float]] = field(default_factory=list)
    time_s: list[float] = field(default_factory=list)

    def column(self, index: int) -> list[float]:
        """Element `index` of every row (nan where a row is shorter)."""
        return [row[index] if index < len(row) else math.nan for row in self.rows]


@dataclass
class StatusSeries:
    """One DiagnosticStatus name over time: reception stamps, levels, messages, fault labels."""

    bag_ns: list[int] = field(default_factory=list)
    level: list[int] = field(default_factory=list)
    message: list[str] = field(default_factory=list)
    kind: list[str] = field(default_factory=list)  # the `fault` value, else the message
    time_s: list[float] = field(default_factory=list)


@dataclass
class BagData:
    """What lca-plot reads from a bag, per joint in first-seen order."""

    joints: dict[str, JointSeries] = field(default_factory=dict)
    motors: dict[str, JointSeries] = field(default_factory=dict)
    drives: dict[str, DriveSeries] = field(default_factory=dict)
    references: dict[str, ArraySeries] = field(default_factory=dict)  # by REFERENCE_TOPICS name
    statuses: dict[str, StatusSeries] = field(default_factory=dict)  # /diagnostics, drive_chain
    topics: list[str] = field(default_factory=list)
    time_base: str = "bag"
    bag_start_ns: int = 0  # the bag's first message (any topic): the origin of bag time

    def series(self) -> list[_Stamped]:
        """Every state series read (with header stamps), of all three topics."""
        return [*self.joints.values(), *self.motors.values(), *self.drives.values()]

    def joint_names(self) -> list[str]:
        """The joints in the bag, in joint_states order (else motor_states, drive_chain)."""
        for group in (self.joints, self.motors, self.drives):
            if group:
                return list(group)
        return []

    def set_time_base(self, base: str) -> None:
        """Fill every series' `time_s` from `base` ("header", "bag" or "auto", see the module)."""
        every = self.series()
        if base == "auto":
            stamped = all(_stamped(s.header_ns) for s in every)
            base = "header" if stamped and every else "bag"
        self.time_base = base
        stamps = [s.header_ns if base == "header" else s.bag_ns for s in every]
        if base == "header":
            start_ns = min((min(ns) for ns in stamps if ns), default=0)
        else:
            start_ns = self.bag_start_ns
        for series, ns in zip(every, stamps, strict=True):
            series.time_s = [(t - start_ns) / NS_PER_S for t in ns]
        headerless: list[ArraySeries | StatusSeries] = [
            *self.references.values(),
            *self.statuses.values(),
        ]
        clock = self._state_clock() if base == "header" else None
        for other in headerless:
            if clock is None:
                other.time_s = [(t - self.bag_start_ns) / NS_PER_S for t in other.bag_ns]
            else:
                other.time_s = [_aligned(clock, t) for t in other.bag_ns]

    def _state_clock(self) -> tuple[list[int], list[float]] | None:
        """Reception stamps (sorted) and plot times of the plant states, to align others with."""
        every = self.series()
        if not every:
            return None
        ref = every[0]
        pairs = sorted(zip(ref.bag_ns, ref.time_s, strict=True))
        return [b for b, _ in pairs], [t for _, t in pairs]


def _aligned(clock: tuple[list[int], list[float]], bag_ns: int) -> float:
    """The plot time of the plant state received last at or before `bag_ns` (else the first)."""
    received, times = clock
    k = bisect_right(received, bag_ns) - 1
    return times[max(k, 0)]


def _stamped(header_ns: list[int]) -> bool:
    """Every message has a header stamp: none is zero after the first non-zero one."""
    first = next((k for k, ns in enumerate(header_ns) if ns), None)
    return first is not None and 0 not in header_ns[first:]


class BagReadError(LcaHilError):
    """The bag cannot be opened or decoded."""


def _topic_name(namespace: str, name: str) -> str:
    """The fully qualified topic name of `name` under `namespace`."""
    if name.startswith("/"):
        return name
    return f"{namespace.rstrip('/')}/{name}"


def _float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        return math.nan


def _level(level: Any) -> int:
    """A DiagnosticStatus level as an int (rosbags gives int; a `byte` may come as bytes)."""
    if isinstance(level, bytes | bytearray):
        return int.from_bytes(level, "little")
    return int(level)


def read_bag(path: Path, namespace: str = "/", time_base: str = "auto") -> BagData:
    """Read the joint, motor and drive-chain states, the references and /diagnostics of a bag.

    Args:
        path: the bag folder (metadata.yaml).
        namespace: the namespace of the relative topic names (not of /diagnostics).
        time_base: the time axis, "header", "bag" or "auto" (see the module docstring).

    Raises:
        BagReadError: The path is not a readable rosbag2 bag.
    """
    typestore = get_typestore(Stores.ROS2_JAZZY)
    wanted = {
        _topic_name(namespace, JOINT_STATES): "joints",
        _topic_name(namespace, MOTOR_STATES): "motors",
        _topic_name(namespace, DRIVE_CHAIN_STATES): "drives",
        DIAGNOSTICS: "diagnostics",
    }
    for name in REFERENCE_TOPICS:
        wanted[_topic_name(namespace, name)] = name
    if not path.is_dir():
        raise BagReadError(f"bag {path}: {FOLDER_NOT_FOUND}")
    if not (path / "metadata.yaml").is_file():
        if any(path.glob("*.mcap")):  # what a recorder killed before it closed leaves behind
            raise BagReadError(
                f"bag {path}: MCAP data but no metadata.yaml (a recording cut short, e.g. "
                f"by SIGKILL): `lca-record --recover {path}` makes it readable"
            )
        raise BagReadError(f"bag {path}: not a rosbag2 bag (no metadata.yaml)")
    data = BagData()
    try:
        with Reader(path) as reader:
            data.topics = sorted(reader.topics)
            data.bag_start_ns = reader.start_time if reader.message_count else 0
            connections = [c for c in reader.connections if c.topic in wanted]
            for conn, stamp_ns, raw in reader.messages(connections=connections):
                msg = typestore.deserialize_cdr(raw, conn.msgtype)
                _add_message(data, wanted[conn.topic], stamp_ns, msg)
    except BagReadError:
        raise
    except Exception as exc:  # rosbags raises several error types (and OSError, KeyError)
        text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise BagReadError(f"cannot read bag {path}: {text}") from None
    data.set_time_base(time_base)
    return data


def _add_message(data: BagData, kind: str, bag_ns: int, msg: Any) -> None:
    if kind == "drives":
        _add_drive_array(data, bag_ns, msg)
    elif kind == "diagnostics":
        for status in msg.status:
            _add_status(data.statuses, bag_ns, status)
    elif kind in ("joints", "motors"):
        _add_joint_state(data.joints if kind == "joints" else data.motors, bag_ns, msg)
    else:
        series = data.references.setdefault(kind, ArraySeries())
        series.bag_ns.append(bag_ns)
        series.rows.append([float(x) for x in msg.data])


def _add_joint_state(series: dict[str, JointSeries], bag_ns: int, msg: Any) -> None:
    for i, name in enumerate(msg.name):
        entry = series.setdefault(name, JointSeries())
        entry.stamp(bag_ns, msg.header)
        for key in ("position", "velocity", "effort"):
            array = getattr(msg, key)
            entry.values[key].append(float(array[i]) if i < len(array) else math.nan)


def _add_drive_array(data: BagData, bag_ns: int, msg: Any) -> None:
    for status in msg.status:
        if not status.name.startswith(DRIVE_STATUS_PREFIX):
            continue
        values = {kv.key: kv.value for kv in status.values}
        entry = data.drives.setdefault(status.name[len(DRIVE_STATUS_PREFIX) :], DriveSeries())
        entry.stamp(bag_ns, msg.header)
        entry.state.append(values.get(DRIVE_STATE_KEY, status.message) or "?")
        for key in ETA_KEYS:
            entry.eta[key].append(_float(values.get(key, "nan")))
        # A drive-chain status above OK (a fault reported there) is a band like /diagnostics';
        # kept only from its first one, so a fault-free bag carries no copy of every state.
        if _level(status.level) != LEVEL_OK or status.name in data.statuses:
            _add_status(data.statuses, bag_ns, status)


def _add_status(statuses: dict[str, StatusSeries], bag_ns: int, status: Any) -> None:
    entry = statuses.setdefault(status.name, StatusSeries())
    entry.bag_ns.append(bag_ns)
    entry.level.append(_level(status.level))
    entry.message.append(str(status.message))
    values = {kv.key: kv.value for kv in status.values}
    entry.kind.append(values.get(FAULT_KEY) or str(status.message))
