"""Writing scenario results: the result.csv table and a Fig. 9/10-style PNG (the I/O edge).

Both are written atomically (`lca_sim.output`), so an interrupted run never leaves a
half-written result behind.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lca_control.contract import MOTION_STATE_NAMES
from lca_sim.cli.plotting import save_png
from lca_sim.model.simulator import SIGNAL_NAMES
from lca_sim.output import number_cell, write_table

if TYPE_CHECKING:
    from matplotlib.patches import Patch

    from lca_sim.model.scenario import ScenarioResult

# Per-axis CSV columns after the axis-name prefix, in order.
CSV_AXIS_COLUMNS: tuple[str, ...] = (
    "position",
    "velocity",
    "motor_velocity_rad_s",
    "current_a",
    "voltage_v",
    "motor_torque_nm",
    "load_torque_nm",
    "friction_torque_nm",
    "motion_state",
    "drive_state",
    "eta_m",
    "eta_l",
)


def csv_header(axis_names: tuple[str, ...]) -> list[str]:
    """The result.csv header: t_s, then NAME_<column> for every axis."""
    return ["t_s"] + [f"{axis}_{col}" for axis in axis_names for col in CSV_AXIS_COLUMNS]


def csv_rows(result: ScenarioResult) -> Iterator[list[str]]:
    """The rows of result.csv; floats in shortest round-trip form, states as names."""
    signal_columns = [
        result.signals[:, row, :]
        for row in (
            _signal_row("motor_velocity_rad_s"),
            _signal_row("current_a"),
            _signal_row("voltage_v"),
            _signal_row("motor_torque_nm"),
            _signal_row("load_torque_nm"),
            _signal_row("friction_torque_nm"),
        )
    ]
    eta_m = result.signals[:, _signal_row("eta_m"), :]
    eta_l = result.signals[:, _signal_row("eta_l"), :]
    for k in range(len(result.time_s)):
        row = [number_cell(result.time_s[k])]
        for a in range(len(result.axis_names)):
            row.append(number_cell(result.position[k, a]))
            row.append(number_cell(result.velocity[k, a]))
            row.extend(number_cell(col[k, a]) for col in signal_columns)
            row.append(MOTION_STATE_NAMES[int(result.motion[k, a])])
            row.append(result.state_names[int(result.drive[k, a])])
            row.append(number_cell(eta_m[k, a]))
            row.append(number_cell(eta_l[k, a]))
        yield row


def _signal_row(name: str) -> int:
    return SIGNAL_NAMES.index(name)


def write_csv(result: ScenarioResult, path: Path) -> None:
    """Write result.csv atomically."""
    write_table(path, csv_header(result.axis_names), csv_rows(result))


def active_axes(result: ScenarioResult) -> list[int]:
    """Axes that received a voltage or moved (the ones worth plotting)."""
    volts = result.signals[:, _signal_row("voltage_v"), :]
    moved = np.any(result.motion != 0, axis=0) | np.any(volts != 0.0, axis=0)
    return [a for a in range(len(result.axis_names)) if moved[a]] or [0]


def write_plot(result: ScenarioResult, path: Path, title: str) -> None:
    """Plot voltage, current, velocity, position and drive state over time (Figs 9-10).

    With one active axis its drive-state phases are shaded.
    """
    # Imported here: matplotlib costs about a second, and only plotting needs it.
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    axes_idx = active_axes(result)
    fig, panels = plt.subplots(5, 1, figsize=(9, 12), sharex=True)
    t = result.time_s
    for a in axes_idx:
        name = result.axis_names[a]
        unit_scale = 1.0 if name == "lift" else 180.0 / math.pi
        unit = "m" if name == "lift" else "deg"
        panels[0].plot(t, result.signals[:, _signal_row("voltage_v"), a], label=name)
        panels[1].plot(t, result.signals[:, _signal_row("current_a"), a], label=name)
        panels[2].plot(t, result.velocity[:, a] * unit_scale, label=f"{name} ({unit}/s)")
        panels[3].plot(t, result.position[:, a] * unit_scale, label=f"{name} ({unit})")
        panels[4].step(t, result.drive[:, a], where="post", label=name)
    panels[0].set_ylabel("voltage (V)")
    panels[1].set_ylabel("current (A)")
    units = {"m" if result.axis_names[a] == "lift" else "deg" for a in axes_idx}
    unit = f" ({units.pop()})" if len(units) == 1 else ""  # else each curve's label says it
    panels[2].set_ylabel(f"velocity{unit[:-1] + '/s)' if unit else ''}")
    panels[3].set_ylabel(f"position{unit}")
    panels[4].set_ylabel("drive state")
    panels[4].set_yticks(range(len(result.state_names)))
    panels[4].set_yticklabels(result.state_names, fontsize=7)
    panels[4].set_xlabel("time (s)")
    for panel in panels:
        panel.grid(True, alpha=0.3)
        panel.legend(loc="upper left", fontsize=7)
    if len(axes_idx) == 1:
        shaded = _shade_phases(result, axes_idx[0], panels)
        # The shades' key below the time axis, where it hides no curve.
        panels[4].legend(
            handles=shaded,
            title=f"{result.axis_names[axes_idx[0]]}: shaded",
            loc="upper center",
            bbox_to_anchor=(0.5, -0.3),
            ncol=3,
            fontsize=7,
            title_fontsize=7,
        )
    fig.suptitle(title)
    save_png(fig, path)
    plt.close(fig)


def _shade_phases(result: ScenarioResult, axis: int, panels: np.ndarray) -> list[Patch]:
    """Shade each drive-state phase of `axis` on every panel; one legend patch per state."""
    from matplotlib.patches import Patch  # noqa: PLC0415

    name = result.axis_names[axis]
    phases = result.phases(name)
    colours = [
        "#dddddd",
        "#cfe8ff",
        "#ffe2c6",
        "#d8f5d0",
        "#f3d1f4",
        "#fff6b3",
        "#e0e0ff",
        "#ffd0d0",
        "#d0fff4",
    ]
    end_time = float(result.time_s[-1])
    keys: dict[str, Patch] = {}
    for i, phase in enumerate(phases):
        start = phase.time_s
        stop = phases[i + 1].time_s if i + 1 < len(phases) else end_time
        colour = colours[result.state_names.index(phase.state) % len(colours)]
        for panel in panels:
            panel.axvspan(start, stop, color=colour, alpha=0.5, linewidth=0)
        if phase.state not in keys:
            keys[phase.state] = Patch(color=colour, alpha=0.5, label=phase.state)
    return list(keys.values())
