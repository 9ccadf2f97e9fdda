"""`lca-plot`: plot a recorded bag's joint, motor and drive-chain states as PNG files.

    lca-plot out/run1                 # PNGs next to the bag's metadata.yaml
    lca-plot out/run1 --out out/plots --namespace /robot1 --all-axes

Reads a rosbag2 bag (MCAP or SQLite, through `lca_sim.ros.bag_read`) and writes, for the topics
present, positions.png, velocities.png, currents.png (each signal beside its reference:
`velocity_commands`, `velocity_reference`, `current_commands`), drive_states.png and
efficiencies.png. Every panel of a joint marks its drive-state changes and shades the times a
/diagnostics status of that joint was above OK; its y limits clip and mark a spike
(`lca_sim.cli.plotting`). Axes whose position range is at most `MOVE_THRESHOLD` are left out
unless `--all-axes`. A missing topic or reference is said in a note, not left out silently.
docs/plotting.md ("lca-plot") has the files, the marks, the time axis (`--time`) and the units.

Exit codes: 0 success, 2 the bag cannot be read (one line on stderr).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lca_control.contract import (
    CURRENT_COMMANDS,
    DRIVE_CHAIN_STATES,
    JOINT_STATES,
    MOTOR_STATES,
    VELOCITY_COMMANDS,
    VELOCITY_REFERENCE,
    VOLTAGE_COMMANDS,
)
from lca_sim.cli.bag_events import (
    MOVE_THRESHOLD,
    FaultBand,
    PlotSpec,
    plot_spec,
    state_order,
)
from lca_sim.cli.plotting import Clipped, clip_spikes, joint_unit, label_gap, merge_events, save_png
from lca_sim.errors import EXIT_OK, fail
from lca_sim.ros.bag_read import (
    ETA_KEYS,
    TIME_BASES,
    ArraySeries,
    BagData,
    BagReadError,
    DriveSeries,
    JointSeries,
    read_bag,
)

if TYPE_CHECKING:
    from matplotlib.axes import Axes

    from lca_sim.analysis.closed_loop import ClosedLoopResult

LABEL_FONT_SIZE = 6  # drive-state change and fault band labels
STATE_LABEL_GID = "drive_state_label"  # gids of the labels (the tests find them by it)
BAND_LABEL_GID = "fault_band_label"
BAND_LABEL_GAPS = 12.0  # a band label's length, in the gap two rotated labels need
PROG = "lca-plot"
SIMULATED = "simulated"  # the time base of a composed run (lca-hil run --plot)


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
    """Write the PNG files of `data` into `out_dir` (docs/plotting.md, "lca-plot").

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
        prog=PROG,
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
        return fail(PROG, str(exc))
    out_dir: Path = args.out if args.out is not None else bag
    try:
        plots = write_plots(data, out_dir, bag.resolve().name, all_axes=args.all_axes)
    except OSError as exc:
        return fail(PROG, f"cannot write to {out_dir}: {exc.strerror or exc}")
    for note in plots.notes:
        print(f"{PROG}: note: {note}", file=sys.stderr)
    for path in plots.written:
        print(f"wrote {path}")
    if not plots.written:
        print(f"{PROG}: note: nothing to plot; topics in the bag: {data.topics}", file=sys.stderr)
    return EXIT_OK
