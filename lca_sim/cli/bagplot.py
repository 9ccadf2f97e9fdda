"""`lca-plot`: plot a recorded bag's joint, motor and drive-chain states as PNG files.

    lca-plot out/run1                 # PNGs next to the bag's metadata.yaml
    lca-plot out/run1 --out out/plots --namespace /robot1

Reads a rosbag2 bag (MCAP or SQLite) with `rosbags`, deserializing with the ROS 2 Jazzy typestore,
and writes, for each topic present:

| file                | topic                | what |
|---------------------|----------------------|------|
| `positions.png`     | `joint_states`       | position per joint (deg; m for the `lift`) |
| `velocities.png`    | `joint_states`       | velocity per joint (deg/s; m/s for the `lift`) |
| `currents.png`      | `motor_states`       | effort per joint = armature current (A) |
| `drive_states.png`  | `drive_chain_states` | drive state per axis, the state names as y ticks |
| `efficiencies.png`  | `drive_chain_states` | eta_m and eta_l per axis (gaps while stopped: nan) |

The time axis (`--time`): `header` uses the messages' header stamps (the plant's own time,
simulated or wall; seconds from the earliest sample plotted), `bag` the recorder's reception
stamps (its node clock: simulated time when it ran with `use_sim_time:=true`, all 0 if no /clock
came; seconds from the bag's first message). `auto`, the default, takes the header stamps when
every plotted message has one and the bag stamps otherwise. A zero stamp counts as none, except
at the start of a series: simulated time starts at exactly 0 (the lockstep simulator's first
state). A missing topic skips its plots with a note.

Exit codes: 0 success, 2 the bag cannot be read (one line on stderr).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from lca_control.contract import (
    DRIVE_CHAIN_STATES,
    DRIVE_STATUS_PREFIX,
    JOINT_STATES,
    MOTOR_STATES,
)
from lca_sim.cli.output import save_png
from lca_sim.model.state_machine import StopState

if TYPE_CHECKING:
    from matplotlib.axes import Axes

EXIT_OK = 0
EXIT_BAD_INPUT = 2
NS_PER_S = 1_000_000_000
TIME_BASES = ("auto", "header", "bag")
# Joints whose position is a length (m); the others are angles (rad, plotted in degrees).
LINEAR_JOINTS = frozenset({"lift"})
DRIVE_STATE_KEY = "drive_state"
ETA_KEYS = ("eta_m", "eta_l")


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
class BagData:
    """What lca-plot reads from a bag, per joint in first-seen order."""

    joints: dict[str, JointSeries] = field(default_factory=dict)
    motors: dict[str, JointSeries] = field(default_factory=dict)
    drives: dict[str, DriveSeries] = field(default_factory=dict)
    topics: list[str] = field(default_factory=list)
    time_base: str = "bag"
    bag_start_ns: int = 0  # the bag's first message (any topic): the origin of bag time

    def series(self) -> list[_Stamped]:
        """Every series read, of all three topics."""
        return [*self.joints.values(), *self.motors.values(), *self.drives.values()]

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


def read_bag(path: Path, namespace: str = "/", time_base: str = "auto") -> BagData:
    """Read the joint, motor and drive-chain states of the bag at `path`.

    `time_base` picks the time axis: "header", "bag" or "auto" (see the module docstring).

    Raises:
        BagReadError: The path is not a readable rosbag2 bag.
    """
    typestore = get_typestore(Stores.ROS2_JAZZY)
    wanted = {
        _topic_name(namespace, JOINT_STATES): "joints",
        _topic_name(namespace, MOTOR_STATES): "motors",
        _topic_name(namespace, DRIVE_CHAIN_STATES): "drives",
    }
    if not path.is_dir():
        raise BagReadError(f"bag {path}: no such folder")
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
                kind = wanted[conn.topic]
                if kind == "drives":
                    _add_drive_array(data.drives, stamp_ns, msg)
                else:
                    series = data.joints if kind == "joints" else data.motors
                    _add_joint_state(series, stamp_ns, msg)
    except BagReadError:
        raise
    except Exception as exc:  # rosbags raises several error types (and OSError, KeyError)
        text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise BagReadError(f"cannot read bag {path}: {text}") from None
    data.set_time_base(time_base)
    return data


def _add_joint_state(series: dict[str, JointSeries], bag_ns: int, msg: Any) -> None:
    for i, name in enumerate(msg.name):
        entry = series.setdefault(name, JointSeries())
        entry.stamp(bag_ns, msg.header)
        for key in ("position", "velocity", "effort"):
            array = getattr(msg, key)
            entry.values[key].append(float(array[i]) if i < len(array) else math.nan)


def _add_drive_array(series: dict[str, DriveSeries], bag_ns: int, msg: Any) -> None:
    for status in msg.status:
        if not status.name.startswith(DRIVE_STATUS_PREFIX):
            continue
        values = {kv.key: kv.value for kv in status.values}
        entry = series.setdefault(status.name[len(DRIVE_STATUS_PREFIX) :], DriveSeries())
        entry.stamp(bag_ns, msg.header)
        entry.state.append(values.get(DRIVE_STATE_KEY, status.message) or "?")
        for key in ETA_KEYS:
            entry.eta[key].append(_float(values.get(key, "nan")))


def state_order(seen: Sequence[str]) -> list[str]:
    """The y-axis order of drive states: the stop states first, then the others as first seen."""
    order = [s.name.lower() for s in StopState]
    for name in seen:
        if name not in order:
            order.append(name)
    return order


def _unit(joint: str, per_s: bool) -> tuple[float, str]:
    """Scale and unit of a joint's position (or velocity if per_s) for plotting."""
    scale, unit = (1.0, "m") if joint in LINEAR_JOINTS else (180.0 / math.pi, "deg")
    return scale, f"{unit}/s" if per_s else unit


class _Figures:
    """The figures of one bag: titled, one panel per row, saved as PNG files into `out_dir`."""

    def __init__(self, plt: Any, title: str, time_base: str, out_dir: Path) -> None:
        self.plt = plt
        self.title = title
        self.time_base = time_base
        self.out_dir = out_dir
        self.written: list[Path] = []

    def figure(self, n_rows: int, what: str) -> tuple[Any, list[Axes]]:
        """A figure of `n_rows` panels sharing the time axis, titled with `what`."""
        fig, panels = self.plt.subplots(
            n_rows, 1, figsize=(9, 1.0 + 2.0 * n_rows), sharex=True, squeeze=False
        )
        fig.suptitle(f"{self.title}: {what}")
        return fig, [row[0] for row in panels]

    def save(self, fig: Any, panels: list[Axes], name: str) -> None:
        """Label the time axis, grid the panels, write `name` and close the figure."""
        panels[-1].set_xlabel(f"time (s, {self.time_base} stamps)")
        for panel in panels:
            panel.grid(True, alpha=0.3)
        path = self.out_dir / name
        save_png(fig, path)
        self.plt.close(fig)
        self.written.append(path)


def _plot_joints(figures: _Figures, data: BagData) -> None:
    """positions.png and velocities.png from joint_states."""
    for key, name, per_s in (
        ("position", "positions.png", False),
        ("velocity", "velocities.png", True),
    ):
        fig, panels = figures.figure(len(data.joints), f"joint {key} ({JOINT_STATES})")
        for panel, (joint, series) in zip(panels, data.joints.items(), strict=True):
            scale, unit = _unit(joint, per_s)
            panel.plot(series.time_s, [v * scale for v in series.values[key]])
            panel.set_ylabel(f"{joint} ({unit})")
        figures.save(fig, panels, name)


def _plot_currents(figures: _Figures, data: BagData) -> None:
    """currents.png from motor_states."""
    fig, panels = figures.figure(len(data.motors), f"current ({MOTOR_STATES})")
    for panel, (joint, series) in zip(panels, data.motors.items(), strict=True):
        panel.plot(series.time_s, series.values["effort"])
        panel.set_ylabel(f"{joint} (A)")
    figures.save(fig, panels, "currents.png")


def _plot_drives(figures: _Figures, data: BagData) -> None:
    """drive_states.png and efficiencies.png from drive_chain_states."""
    fig, panels = figures.figure(len(data.drives), "drive state")
    for panel, (axis, drive) in zip(panels, data.drives.items(), strict=True):
        order = state_order(drive.state)
        index = {name: i for i, name in enumerate(order)}
        panel.step(drive.time_s, [index[s] for s in drive.state], where="post")
        panel.set_yticks(range(len(order)))
        panel.set_yticklabels(order, fontsize=7)
        panel.set_ylabel(axis)
    figures.save(fig, panels, "drive_states.png")
    fig, panels = figures.figure(len(data.drives), "efficiency (eq. 10)")
    for panel, (axis, drive) in zip(panels, data.drives.items(), strict=True):
        for key in ETA_KEYS:
            panel.plot(drive.time_s, drive.eta[key], label=key)
        panel.set_ylabel(axis)
        panel.legend(loc="upper left", fontsize=7)
    figures.save(fig, panels, "efficiencies.png")


def write_plots(data: BagData, out_dir: Path, title: str) -> tuple[list[Path], list[str]]:
    """Write the PNG files of `data` into `out_dir`; the paths written and notes on skips."""
    import matplotlib  # noqa: PLC0415  # about a second to import: only when plotting

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    figures = _Figures(plt, title, data.time_base, out_dir)
    notes: list[str] = []
    # Per topic: whether the bag has it, what plots it, and the note when it does not.
    sections: tuple[tuple[bool, Callable[[_Figures, BagData], None], str], ...] = (
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
            plot(figures, data)
        else:
            notes.append(skipped)
    return figures.written, notes


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of lca-plot."""
    parser = argparse.ArgumentParser(
        prog="lca-plot", description="Plot joint, motor and drive-chain states of a bag as PNG."
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
        written, notes = write_plots(data, out_dir, bag.resolve().name)
    except OSError as exc:
        print(f"lca-plot: error: cannot write to {out_dir}: {exc.strerror or exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    for note in notes:
        print(f"lca-plot: note: {note}", file=sys.stderr)
    for path in written:
        print(f"wrote {path}")
    if not written:
        print(f"lca-plot: note: nothing to plot; topics in the bag: {data.topics}", file=sys.stderr)
    return EXIT_OK
