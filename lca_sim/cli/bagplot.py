"""`lca-plot`: plot a recorded bag's joint, motor and drive-chain states as PNG files.

    lca-plot out/run1                 # PNGs next to the bag's metadata.yaml
    lca-plot out/run1 --out out/plots --namespace /robot1 --all-axes

Reads a rosbag2 bag (MCAP or SQLite) with `rosbags`, deserializing with the ROS 2 Jazzy typestore,
and writes, for each topic present:

| file                | topic                | what |
|---------------------|----------------------|------|
| `positions.png`     | `joint_states`       | position per joint (deg; m for the `lift`) |
| `velocities.png`    | `joint_states`       | velocity per joint (deg/s; m/s), beside reference* |
| `currents.png`      | `motor_states`       | effort = armature current (A), beside reference* |
| `drive_states.png`  | `drive_chain_states` | drive state per axis, the state names as y ticks |
| `efficiencies.png`  | `drive_chain_states` | eta_m and eta_l per axis (gaps while stopped: nan) |

*The references: `velocity_commands` (the setpoint the controller's velocity loop follows) and,
if a user sent one, `velocity_reference`, dashed and dotted beside each velocity;
`current_commands` dashed beside each current.

On every panel of a joint: a dotted vertical line at each change of its drive state (from
`drive_chain_states`, labelled with the new state; changes closer than a label's thickness share one
label, "5 changes in 48 ms -> stop_motor_reverse"), y limits that hold the bulk of the samples with
a spike beyond them clipped and marked (`lca_sim.cli.plotting`), and a shaded band over each time a
status of that joint was above OK (WARN orange, ERROR or STALE red), labelled with the status
message: on `/diagnostics` the statuses whose name ends in `/<joint>` (the simulator's
`lca_hil/simulator/<joint>`: "back-driving", "end stop hit"), and `drive_chain/<joint>` itself when
its level is above OK. An injected fault that reports on /diagnostics under its joint's name appears
the same way. A status of no joint above OK (a node's own) is listed in a note.

A reference topic missing from the bag (the controller publishes `velocity_commands` only while
something subscribes to it, so a bag recorded without it has none) is said in the panel's legend
and in a note, not left out silently. Command arrays (std_msgs/Float64MultiArray) carry no joint
names: element i belongs to the i-th joint of `joint_states` (the controller's `joints`
parameter, l_arm, pivot, c_arc, lift by default, is the robot's axis order).

Axes that did not move, their `joint_states` position range at most `MOVE_THRESHOLD` (1e-4 rad;
1e-4 m for the lift), are left out of every figure (listed in a note) unless `--all-axes`; if no
axis moved, all are plotted.

The time axis (`--time`): `header` uses the messages' header stamps (the plant's own time,
simulated or wall; seconds from the earliest sample plotted), `bag` the recorder's reception
stamps (its node clock: simulated time when it ran with `use_sim_time:=true`, all 0 if no /clock
came; seconds from the bag's first message). `auto`, the default, takes the header stamps when
every plotted state message has one and the bag stamps otherwise. A zero stamp counts as none,
except at the start of a series: simulated time starts at exactly 0 (the lockstep simulator's
first state). Messages of other clocks or without a header (the command arrays, /diagnostics,
whose stamps are each node's own clock) are put, on the header time axis, at the time of the
plant state the recorder received last before them: in lockstep the command that answers a
state. A missing topic skips its plots with a note.

Exit codes: 0 success, 2 the bag cannot be read (one line on stderr).
"""

from __future__ import annotations

import argparse
import math
import sys
from bisect import bisect_right
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

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
from lca_sim.cli.plotting import Clipped, clip_spikes, joint_unit, label_gap, merge_events, save_png
from lca_sim.errors import EXIT_BAD_INPUT, EXIT_OK, FOLDER_NOT_FOUND
from lca_sim.model.state_machine import StopState

if TYPE_CHECKING:
    from matplotlib.axes import Axes

    from lca_sim.analysis.closed_loop import ClosedLoopResult

NS_PER_S = 1_000_000_000
TIME_BASES = ("auto", "header", "bag")
DRIVE_STATE_KEY = "drive_state"
ETA_KEYS = ("eta_m", "eta_l")
# An axis whose joint_states position range is at most this (rad, or m for the lift) did not
# move: left out of the figures unless --all-axes. Well above the encoder noise of a held axis,
# far below any commanded motion.
MOVE_THRESHOLD = 1e-4
# The command arrays lca-plot draws beside the measured signals.
REFERENCE_TOPICS = (VELOCITY_COMMANDS, VELOCITY_REFERENCE, CURRENT_COMMANDS, VOLTAGE_COMMANDS)
# diagnostic_msgs/DiagnosticStatus levels.
LEVEL_OK = 0
LEVEL_NAMES = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}
FAULT_KEY = "fault"  # a status value naming the fault (the simulator's per-axis statuses)
LABEL_FONT_SIZE = 6  # drive-state change and fault band labels
STATE_LABEL_GID = "drive_state_label"  # gids of the labels (the tests find them by it)
BAND_LABEL_GID = "fault_band_label"
BAND_LABEL_GAPS = 12.0  # a band label's length, in the gap two rotated labels need
SIMULATED = "simulated"  # the time base of a composed run (lca-hil run --plot)


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


@dataclass(frozen=True, slots=True)
class StateChange:
    """A change of an axis's drive state.

    Attributes:
        joint: the axis.
        time_s: the first sample in the new state, on the plot's time axis.
        before, after: the drive-state names.
        position: the joint's position at (the joint_states sample nearest to) that time, rad
            (m for the lift); nan without joint_states.
    """

    joint: str
    time_s: float
    before: str
    after: str
    position: float


@dataclass(frozen=True, slots=True)
class FaultBand:
    """A time a status was above OK without a change of level or fault.

    Attributes:
        status: the DiagnosticStatus name (`lca_hil/simulator/pivot`, `drive_chain/pivot`).
        joint: the joint it belongs to, "" for a node's own status.
        level: 1 WARN, 2 ERROR, 3 STALE.
        message: the status message of its first sample.
        start_s, end_s: from its first sample to the next sample of another level or fault (or
            the status's last sample), on the plot's time axis.
    """

    status: str
    joint: str
    level: int
    message: str
    start_s: float
    end_s: float

    @property
    def level_name(self) -> str:
        """WARN, ERROR or STALE."""
        return LEVEL_NAMES.get(self.level, str(self.level))


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


class BagReadError(Exception):
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


def state_order(seen: Sequence[str]) -> list[str]:
    """The y-axis order of drive states: the stop states first, then the others as first seen."""
    order = [s.name.lower() for s in StopState]
    for name in seen:
        if name not in order:
            order.append(name)
    return order


def _nearest(times: list[float], t: float) -> int:
    """Index of the sample of `times` (ascending) nearest to `t`."""
    k = bisect_right(times, t)
    if k == 0:
        return 0
    if k == len(times) or t - times[k - 1] <= times[k] - t:
        return k - 1
    return k


def drive_state_changes(data: BagData) -> dict[str, list[StateChange]]:
    """Per axis of drive_chain_states, every change of its drive state, in time order."""
    changes: dict[str, list[StateChange]] = {}
    for joint, drive in data.drives.items():
        found: list[StateChange] = []
        series = data.joints.get(joint)
        for k in range(1, len(drive.state)):
            if drive.state[k] == drive.state[k - 1]:
                continue
            t = drive.time_s[k]
            position = math.nan
            if series is not None and series.time_s:
                position = series.values["position"][_nearest(series.time_s, t)]
            found.append(StateChange(joint, t, drive.state[k - 1], drive.state[k], position))
        changes[joint] = found
    return changes


def _status_joint(name: str, joints: Sequence[str]) -> str:
    """The joint a status belongs to: its name's last part (`.../pivot`), else ""."""
    last = name.rsplit("/", 1)[-1]
    return last if "/" in name and last in joints else ""


def fault_bands(data: BagData) -> list[FaultBand]:
    """Every time a status of /diagnostics (or drive_chain_states) was above OK, by start time.

    A band lasts while the level and the fault (the status's `fault` value, else its message)
    stay the same: a message whose numbers change (a speed) does not split it.
    """
    joints = data.joint_names()
    bands: list[FaultBand] = []
    for name, series in data.statuses.items():
        joint = _status_joint(name, joints)
        start: int | None = None
        for k in range(len(series.level) + 1):
            ended = k == len(series.level)
            same = (
                not ended
                and start is not None
                and (series.level[k], series.kind[k]) == (series.level[start], series.kind[start])
            )
            if start is not None and not same:
                end_s = series.time_s[k] if not ended else series.time_s[-1]
                bands.append(
                    FaultBand(
                        name,
                        joint,
                        series.level[start],
                        series.message[start],
                        series.time_s[start],
                        end_s,
                    )
                )
                start = None
            if not ended and start is None and series.level[k] != LEVEL_OK:
                start = k
    return sorted(bands, key=lambda b: (b.start_s, b.status))


def moved_joints(data: BagData, threshold: float = MOVE_THRESHOLD) -> list[str]:
    """The joints whose joint_states position range exceeds `threshold` (rad, or m).

    A joint without joint_states samples counts as moved (nothing says it did not).
    """
    moved = []
    for joint in data.joint_names():
        series = data.joints.get(joint)
        positions = [] if series is None else series.values["position"]
        finite = [x for x in positions if not math.isnan(x)]
        if series is None or (finite and max(finite) - min(finite) > threshold):
            moved.append(joint)
    return moved


@dataclass
class PlotSpec:
    """What the figures show: the joints with a panel, the ones left out, and notes."""

    joints: list[str]
    left_out: list[str]
    changes: dict[str, list[StateChange]]
    bands: list[FaultBand]
    notes: list[str] = field(default_factory=list)


def plot_spec(data: BagData, all_axes: bool = False) -> PlotSpec:
    """The panels of the figures of `data`: every joint if `all_axes`, else the moved ones."""
    names = data.joint_names()
    notes: list[str] = []
    joints = names
    if not all_axes:
        moved = moved_joints(data)
        if moved:
            joints = moved
            if len(moved) < len(names):
                still = [j for j in names if j not in moved]
                notes.append(
                    f"left out axes that did not move (position range <= {MOVE_THRESHOLD:g}): "
                    f"{', '.join(still)} (--all-axes plots them)"
                )
        elif names:
            notes.append(f"no axis moved more than {MOVE_THRESHOLD:g}: plotting all")
    bands = fault_bands(data)
    for band in bands:
        if not band.joint:
            notes.append(
                f"{band.level_name} {band.status}: {band.message} "
                f"({band.start_s:.3f} s to {band.end_s:.3f} s)"
            )
    return PlotSpec(
        joints=list(joints),
        left_out=[j for j in names if j not in joints],
        changes=drive_state_changes(data),
        bands=bands,
        notes=notes,
    )


class _Figures:
    """The figures of one bag: titled, one panel per row, saved as PNG files into `out_dir`.

    Every figure spans the same time range (the states'), keeps its legend beside the panels
    (so no label or line hides under it), and labels the drive-state changes of each panel once
    its layout is known: changes closer than a label's thickness share one label.
    """

    def __init__(
        self,
        plt: Any,
        title: str,
        time_base: str,
        out_dir: Path,
        spec: PlotSpec,
        time_range: tuple[float, float] | None,
    ) -> None:
        self.plt = plt
        self.title = title
        self.time_base = time_base
        self.out_dir = out_dir
        self.spec = spec
        self.time_range = time_range
        self.written: list[Path] = []
        self.panels: dict[str, list[str]] = {}  # file name -> the joint of each panel
        self.clipped: dict[str, list[Clipped]] = {}  # "file:joint" -> its clipped sides

    def figure(self, joints: Sequence[str], what: str) -> tuple[Any, list[Axes]]:
        """A figure of one panel per joint sharing the time axis, titled with `what`."""
        n_rows = max(len(joints), 1)
        fig, panels = self.plt.subplots(
            n_rows, 1, figsize=(10.5, 1.2 + 2.3 * n_rows), sharex=True, squeeze=False
        )
        fig.suptitle(f"{self.title}: {what}")
        return fig, [row[0] for row in panels]

    def clip(
        self,
        name: str,
        panel: Axes,
        joint: str,
        lines: Sequence[tuple[Sequence[float], Sequence[float]]],
        unit: str,
    ) -> None:
        """Robust y limits of `panel` from its `lines`, a spike beyond them marked."""
        found = clip_spikes(panel, lines, unit)
        if found:
            self.clipped[f"{name}:{joint}"] = found

    def _lines(self, panel: Axes, joint: str) -> None:
        """Drive-state changes (dotted lines) and fault bands (shaded) of `joint` on `panel`."""
        for k, change in enumerate(self.spec.changes.get(joint, [])):
            panel.axvline(
                change.time_s,
                color="0.45",
                linestyle=":",
                linewidth=0.8,
                label="drive-state change" if k == 0 else None,
            )
        shown: set[int] = set()
        for band in (b for b in self.spec.bands if b.joint == joint):
            panel.axvspan(
                band.start_s,
                band.end_s,
                color=_band_colour(band),
                alpha=0.18,
                linewidth=0,
                label=None if band.level in shown else f"{band.level_name} on /diagnostics",
            )
            shown.add(band.level)

    def _labels(self, panel: Axes, joint: str) -> None:
        """The labels of `joint`'s changes and bands; those closer than a label share one."""
        changes = self.spec.changes.get(joint, [])
        gap = label_gap(panel, LABEL_FONT_SIZE)
        for group in merge_events([c.time_s for c in changes], gap):
            first, last = changes[group[0]], changes[group[-1]]
            text = first.after
            if len(group) > 1:
                span_ms = (last.time_s - first.time_s) * 1e3
                text = f"{len(group)} changes in {span_ms:.0f} ms -> {last.after}"
            label = panel.annotate(
                text,
                xy=(first.time_s, 0.98),
                xycoords=("data", "axes fraction"),
                rotation=90,
                fontsize=LABEL_FONT_SIZE,
                va="top",
                ha="right",
                color="0.3",
                gid=STATE_LABEL_GID,
            )
            label.set_in_layout(False)
        bands = [b for b in self.spec.bands if b.joint == joint]
        # A band's label runs along the time axis: the next one starts a label's length later.
        for group in merge_events([b.start_s for b in bands], BAND_LABEL_GAPS * gap):
            band = bands[group[0]]
            more = f" (+{len(group) - 1} more)" if len(group) > 1 else ""
            label = panel.annotate(
                f"{band.level_name}: {band.message}{more}",
                xy=(band.start_s, 0.02),
                xycoords=("data", "axes fraction"),
                fontsize=LABEL_FONT_SIZE,
                va="bottom",
                color=_band_colour(band),
                gid=BAND_LABEL_GID,
            )
            label.set_in_layout(False)

    def save(self, fig: Any, panels: list[Axes], name: str, joints: Sequence[str]) -> None:
        """Mark, label and grid the panels, write `name` and close the figure."""
        panels[-1].set_xlabel(
            "simulated time (s)"
            if self.time_base == SIMULATED
            else f"time (s, {self.time_base} stamps)"
        )
        if self.time_range is not None:
            t0, t1 = self.time_range
            pad = 0.01 * (t1 - t0) if t1 > t0 else 0.5
            panels[0].set_xlim(t0 - pad, t1 + pad)
        for panel, joint in zip(panels, joints, strict=False):
            panel.grid(True, alpha=0.3)
            self._lines(panel, joint)
            if panel.get_legend_handles_labels()[1]:  # beside the panel: it hides nothing
                panel.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=7)
        fig.tight_layout()  # the panels' final width sets how close two labels may be
        for panel, joint in zip(panels, joints, strict=False):
            self._labels(panel, joint)
        path = self.out_dir / name
        save_png(fig, path)
        self.plt.close(fig)
        self.written.append(path)
        self.panels[name] = list(joints)


def _band_colour(band: FaultBand) -> str:
    return "tab:orange" if band.level == 1 else "tab:red"


def _reference(
    panel: Axes,
    data: BagData,
    topic: str,
    joint: str,
    scale: float,
    style: str,
    notes: list[str],
) -> tuple[list[float], list[float]] | None:
    """Draw `topic`'s element of `joint` on `panel`; say so in the legend if the bag has none.

    Returns:
        The line drawn (times, values in the plot's unit), None if the bag has no `topic`.
    """
    series = data.references.get(topic)
    names = data.joint_names()
    if series is None:
        panel.plot([], [], " ", label=f"no {topic} in the bag")
        note = f"no {topic} in the bag: its reference is not drawn"
        if note not in notes:
            notes.append(note)
        return None
    index = names.index(joint)
    values = [v * scale for v in series.column(index)]
    panel.plot(series.time_s, values, style, color="k", linewidth=1.0, label=f"{topic} (reference)")
    return series.time_s, values


def _plot_joints(figures: _Figures, data: BagData, notes: list[str]) -> None:
    """positions.png and velocities.png from joint_states; velocities beside the references."""
    joints = [j for j in figures.spec.joints if j in data.joints]
    for key, name, per_s in (
        ("position", "positions.png", False),
        ("velocity", "velocities.png", True),
    ):
        fig, panels = figures.figure(joints, f"joint {key} ({JOINT_STATES})")
        for panel, joint in zip(panels, joints, strict=False):
            series = data.joints[joint]
            scale, unit = joint_unit(joint, per_s)
            values = [v * scale for v in series.values[key]]
            panel.plot(series.time_s, values, label=key)
            lines = [(series.time_s, values)]
            if per_s:
                drawn = _reference(panel, data, VELOCITY_COMMANDS, joint, scale, "--", notes)
                if VELOCITY_REFERENCE in data.references:  # only when a user sent one
                    user = _reference(panel, data, VELOCITY_REFERENCE, joint, scale, ":", notes)
                    drawn = drawn or user
                lines += [drawn] if drawn is not None else []
            panel.set_ylabel(f"{joint} {key} ({unit})")
            figures.clip(name, panel, joint, lines, unit)
        figures.save(fig, panels, name, joints)


def _plot_currents(figures: _Figures, data: BagData, notes: list[str]) -> None:
    """currents.png from motor_states, beside current_commands."""
    joints = [j for j in figures.spec.joints if j in data.motors]
    fig, panels = figures.figure(joints, f"current ({MOTOR_STATES})")
    for panel, joint in zip(panels, joints, strict=False):
        motor = data.motors[joint]
        panel.plot(motor.time_s, motor.values["effort"], label="current")
        lines = [(motor.time_s, motor.values["effort"])]
        if CURRENT_COMMANDS not in data.references and VOLTAGE_COMMANDS in data.references:
            panel.plot([], [], " ", label=f"no {CURRENT_COMMANDS}: {VOLTAGE_COMMANDS} in the bag")
            note = f"no {CURRENT_COMMANDS} in the bag ({VOLTAGE_COMMANDS}: voltage control)"
            if note not in notes:
                notes.append(note)
        else:
            drawn = _reference(panel, data, CURRENT_COMMANDS, joint, 1.0, "--", notes)
            lines += [drawn] if drawn is not None else []
        panel.set_ylabel(f"{joint} current (A)")
        figures.clip("currents.png", panel, joint, lines, "A")
    figures.save(fig, panels, "currents.png", joints)


def _plot_drives(figures: _Figures, data: BagData, notes: list[str]) -> None:
    """drive_states.png and efficiencies.png from drive_chain_states."""
    joints = [j for j in figures.spec.joints if j in data.drives]
    fig, panels = figures.figure(joints, "drive state")
    for panel, joint in zip(panels, joints, strict=False):
        drive = data.drives[joint]
        order = state_order(drive.state)
        index = {name: i for i, name in enumerate(order)}
        panel.step(drive.time_s, [index[s] for s in drive.state], where="post")
        panel.set_yticks(range(len(order)))
        panel.set_yticklabels(order, fontsize=7)
        panel.set_ylabel(f"{joint} drive state")
    figures.save(fig, panels, "drive_states.png", joints)
    if not any(math.isfinite(x) for j in joints for k in ETA_KEYS for x in data.drives[j].eta[k]):
        notes.append("no efficiencies (eta_m, eta_l) recorded: efficiencies.png skipped")
        return
    fig, panels = figures.figure(joints, "efficiency (eq. 10)")
    for panel, joint in zip(panels, joints, strict=False):
        drive = data.drives[joint]
        for key in ETA_KEYS:
            panel.plot(drive.time_s, drive.eta[key], label=key)
        panel.set_ylabel(f"{joint} efficiency")
        figures.clip(
            "efficiencies.png", panel, joint, [(drive.time_s, drive.eta[k]) for k in ETA_KEYS], ""
        )
    figures.save(fig, panels, "efficiencies.png", joints)


@dataclass
class Plots:
    """What `write_plots` did: the files written, notes on what was skipped, each file's panels.

    Attributes:
        clipped: "file:joint" -> the sides of that panel whose spike was clipped.
    """

    written: list[Path]
    notes: list[str]
    panels: dict[str, list[str]]
    clipped: dict[str, list[Clipped]] = field(default_factory=dict)


def write_plots(data: BagData, out_dir: Path, title: str, *, all_axes: bool = False) -> Plots:
    """Write the PNG files of `data` into `out_dir` (see the module docstring).

    Args:
        data: what `read_bag` read (or `run_data` made of a composed run).
        out_dir: the folder to write into.
        title: the figures' title (the bag's name).
        all_axes: also plot the axes that did not move.
    """
    import matplotlib  # noqa: PLC0415  # about a second to import: only when plotting

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    spec = plot_spec(data, all_axes)
    times = [t for s in data.series() for t in (s.time_s[:1] + s.time_s[-1:])]
    time_range = (min(times), max(times)) if times else None
    figures = _Figures(plt, title, data.time_base, out_dir, spec, time_range)
    notes: list[str] = list(spec.notes)
    # Per topic: whether the bag has it, what plots it, and the note when it does not.
    sections: tuple[tuple[bool, Callable[[_Figures, BagData, list[str]], None], str], ...] = (
        (
            bool(data.joints),
            _plot_joints,
            f"no {JOINT_STATES} in the bag: positions.png, velocities.png skipped",
        ),
        (bool(data.motors), _plot_currents, f"no {MOTOR_STATES} in the bag: currents.png skipped"),
        (
            bool(data.drives),
            _plot_drives,
            f"no {DRIVE_CHAIN_STATES} in the bag: drive_states.png, efficiencies.png skipped",
        ),
    )
    for present, plot, skipped in sections:
        if present:
            plot(figures, data, notes)
        else:
            notes.append(skipped)
    for key, sides in figures.clipped.items():
        for side in sides:
            notes.append(
                f"{key}: {side.count} samples beyond the y range clipped "
                f"({'min' if side.side == 'low' else 'max'} {side.extreme:.4g} at "
                f"{side.time:.3f} s)"
            )
    return Plots(figures.written, notes, figures.panels, figures.clipped)


def run_data(result: ClosedLoopResult) -> BagData:
    """What a bag of the composed run `result` (lca-hil run) would hold, for `write_plots`.

    joint_states and motor_states from its states, drive_chain_states' drive states (no
    efficiencies: the run does not keep them), velocity_commands and the command arrays in
    joint_states order (NaN on the axes the controller does not drive), all on simulated time.
    """
    data = BagData(time_base=SIMULATED)
    time_s = [float(t) for t in result.time_s]
    for a, axis in enumerate(result.axes):
        joint = JointSeries(time_s=time_s)
        joint.values["position"] = [float(x) for x in result.position[:, a]]
        joint.values["velocity"] = [float(x) for x in result.velocity[:, a]]
        data.joints[axis] = joint
        motor = JointSeries(time_s=time_s)
        motor.values["effort"] = [float(x) for x in result.current_a[:, a]]
        data.motors[axis] = motor
        drive = DriveSeries(time_s=time_s)
        drive.state = [result.state_names[int(k)] for k in result.drive_state[:, a]]
        drive.eta = {key: [math.nan] * len(time_s) for key in ETA_KEYS}
        data.drives[axis] = drive
    command = CURRENT_COMMANDS if result.command_interface == "current" else VOLTAGE_COMMANDS
    for topic, values in (
        (VELOCITY_COMMANDS, result.velocity_reference),
        (command, result.command),
    ):
        rows = []
        for k in range(len(time_s)):
            by_joint = dict(zip(result.joints, values[k], strict=True))
            rows.append([float(by_joint.get(axis, math.nan)) for axis in result.axes])
        data.references[topic] = ArraySeries(time_s=list(time_s), rows=rows)
    data.topics = sorted(
        f"/{t}"
        for t in (JOINT_STATES, MOTOR_STATES, DRIVE_CHAIN_STATES, VELOCITY_COMMANDS, command)
    )
    return data


def plot_run(result: ClosedLoopResult, out_dir: Path, title: str) -> Plots:
    """`lca-hil run --plot DIR`: the run's figures, drawn as lca-plot draws a bag's."""
    return write_plots(run_data(result), out_dir, title)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of lca-plot."""
    parser = argparse.ArgumentParser(
        prog="lca-plot",
        description="Plot joint, motor and drive-chain states of a bag as PNG, beside the "
        "references, with drive-state changes and faults marked.",
    )
    parser.add_argument("bag", type=Path, metavar="BAG", help="rosbag2 folder (metadata.yaml)")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: BAG)")
    parser.add_argument("--namespace", default="/", help="namespace of the topics (default /)")
    parser.add_argument(
        "--time",
        choices=TIME_BASES,
        default="auto",
        help="time axis: header stamps, bag (reception) stamps, or auto (header if all set)",
    )
    parser.add_argument(
        "--all-axes",
        action="store_true",
        help=f"also plot axes that did not move (position range <= {MOVE_THRESHOLD:g})",
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the lca-plot console script."""
    args = build_parser().parse_args(argv)
    bag: Path = args.bag
    try:
        data = read_bag(bag, args.namespace, args.time)
    except BagReadError as exc:
        print(f"lca-plot: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    out_dir: Path = args.out if args.out is not None else bag
    try:
        plots = write_plots(data, out_dir, bag.resolve().name, all_axes=args.all_axes)
    except OSError as exc:
        print(f"lca-plot: error: cannot write to {out_dir}: {exc.strerror or exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    for note in plots.notes:
        print(f"lca-plot: note: {note}", file=sys.stderr)
    for path in plots.written:
        print(f"wrote {path}")
    if not plots.written:
        print(f"lca-plot: note: nothing to plot; topics in the bag: {data.topics}", file=sys.stderr)
    return EXIT_OK
