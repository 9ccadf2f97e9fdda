"""Plot helpers the tools share: units as a reader writes them, robust y limits, event labels.

* `joint_unit`: a joint's position or velocity in deg and deg/s (revolute) or m and m/s (lift).
* `metric_unit`: a sweep metric's unit as an axis label says it (`deg`, `m`, `0 or 1`).
* `clip_spikes`: y limits that hold the bulk of a panel's samples; a short spike beyond them
  (a -20 A braking peak beside 0-2.5 A of tracking) is clipped and marked at the panel's edge
  with its extreme value, in the legend and beside the marker.
* `merge_events`: event times grouped so that labels drawn at each group's first time stay a
  readable gap apart (eight drive-state changes in 48 ms make one label).
* `save_png`: a figure written as PNG, atomically (`lca_sim.output`).

matplotlib is imported by the callers (it costs about a second); nothing here needs the model.
docs/plotting.md shows the figures.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lca_sim.output import atomic_path

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from numpy.typing import ArrayLike

PNG_DPI = 110  # every PNG the tools write
# Joints whose position is a length (m); the others are angles (rad, plotted in degrees).
LINEAR_JOINTS = frozenset({"lift"})
# The bulk of a panel's samples: between these quantiles. A sample beyond the bulk by more than
# SPIKE_SPANS times its span is a spike, drawn clipped. 0.5 % on each side keeps a spike of up
# to 16 of the main job's 3251 states out of the limits, and the ramp's own ends in.
BULK_QUANTILES = (0.005, 0.995)
SPIKE_SPANS = 0.5
MARGIN_SPANS = 0.08  # room between the bulk (or the extreme, when not clipped) and the edge
CLIPPED_GID = "clipped"  # the gid of the markers of clipped samples (tests find them by it)
# A label's thickness across its text line, in multiples of its font size: the gap between
# two rotated labels that keeps them apart.
LABEL_GAP_FONT_SIZES = 1.6


def joint_unit(joint: str, per_s: bool = False) -> tuple[float, str]:
    """Scale from SI and unit of a joint's position (velocity if `per_s`) in a plot.

    Returns:
        (180/pi, "deg") for a revolute joint, (1, "m") for the lift; "/s" appended if `per_s`.
    """
    scale, unit = (1.0, "m") if joint in LINEAR_JOINTS else (180.0 / math.pi, "deg")
    return scale, f"{unit}/s" if per_s else unit


def metric_unit(unit: str, axis: str | None, reference_signal: str = "") -> tuple[float, str]:
    """Scale from the metric library's unit and the unit a plot's axis label says.

    Args:
        unit: `METRICS[...].unit`: "rad (m)", "1 (0 or 1)", "unit of the reference", "A", ...
        axis: the metric's axis (the lift's lengths are m, the others' angles deg).
        reference_signal: what the run's reference is for (`velocity`, `current_a`, ""), for
            the tracking metrics.

    Returns:
        (scale, unit); unit "" for a plain count.
    """
    linear = axis in LINEAR_JOINTS
    if unit == "rad (m)":
        return (1.0, "m") if linear else (180.0 / math.pi, "deg")
    if unit == "unit of the reference":
        if reference_signal == "current_a":
            return 1.0, "A"
        return (1.0, "m/s") if linear else (180.0 / math.pi, "deg/s")
    if unit.startswith("1 (") and unit.endswith(")"):
        return 1.0, unit[3:-1]  # "1 (0 or 1)": say what the number is
    if unit == "1":
        return 1.0, ""
    return 1.0, unit


# Unit suffixes of the names users give metrics (house style: the SI unit in the name), by the
# unit a plot shows instead: a name's suffix that says another unit is dropped from the label.
_NAME_SUFFIXES = ("_rad_s", "_rad", "_m_s", "_deg_s", "_deg", "_m")


def metric_label(name: str, plot_unit: str) -> str:
    """An axis label of a metric: its name without a unit suffix it no longer has, and the unit.

    `travel_after_cut_rad` drawn in deg reads `travel_after_cut (deg)`; `peak_current_a` in A
    stays `peak_current_a (A)`; a count has no unit in brackets.
    """
    stem = name
    own = plot_unit.replace("/", "_")
    for suffix in _NAME_SUFFIXES:
        if name.endswith(suffix) and suffix != f"_{own}":
            stem = name[: -len(suffix)]
            break
    return f"{stem} ({plot_unit})" if plot_unit else stem


@dataclass(frozen=True, slots=True)
class Clipped:
    """A side of a panel whose samples beyond the limit were clipped.

    Attributes:
        side: "low" or "high".
        limit: the y limit, in the plot's unit.
        extreme: the most extreme sample beyond it.
        time: its time.
        count: samples beyond the limit.
    """

    side: str
    limit: float
    extreme: float
    time: float
    count: int


def robust_limits(values: np.ndarray) -> tuple[float, float, bool, bool] | None:
    """Y limits that hold the bulk of `values` (finite ones), and which sides clip a spike.

    Returns:
        (low, high, low clipped, high clipped), or None without two finite values.
    """
    finite = values[np.isfinite(values)]
    if finite.size < 2:
        return None
    q_low, q_high = np.quantile(finite, BULK_QUANTILES)
    v_min, v_max = float(finite.min()), float(finite.max())
    span = float(q_high - q_low)
    if span <= 0.0:
        span = max(abs(float(q_low)) * 0.1, 1e-9)
    clip_low = v_min < q_low - SPIKE_SPANS * span
    clip_high = v_max > q_high + SPIKE_SPANS * span
    shown_low = float(q_low) if clip_low else v_min
    shown_high = float(q_high) if clip_high else v_max
    full = max(shown_high - shown_low, span)
    low = q_low - MARGIN_SPANS * span if clip_low else v_min - MARGIN_SPANS * full
    high = q_high + MARGIN_SPANS * span if clip_high else v_max + MARGIN_SPANS * full
    return float(low), float(high), bool(clip_low), bool(clip_high)


def clip_spikes(
    panel: Axes, series: Sequence[tuple[ArrayLike, ArrayLike]], unit: str
) -> list[Clipped]:
    """Set `panel`'s y limits to the bulk of `series` and mark what they clip.

    Each clipped side gets triangle markers on its edge at the times of the samples beyond it
    (gid `CLIPPED_GID`, labelled with the extreme for the legend) and a text with the extreme
    and its time. Without a spike the limits are the data's, with a margin.

    Args:
        panel: the axes, after everything is drawn on it.
        series: (times, values) of every line of the panel, in the plot's unit.
        unit: the values' unit, for the labels.

    Returns:
        The clipped sides (empty when nothing is clipped).
    """
    if not series:
        return []
    times = np.concatenate([np.asarray(t, dtype=float) for t, _ in series])
    values = np.concatenate([np.asarray(v, dtype=float) for _, v in series])
    limits = robust_limits(values)
    if limits is None:
        return []
    low, high, clip_low, clip_high = limits
    panel.set_ylim(low, high)
    clipped: list[Clipped] = []
    for side, on, beyond, pick in (
        ("low", clip_low, values < low, np.argmin),
        ("high", clip_high, values > high, np.argmax),
    ):
        if not on:
            continue
        index = np.flatnonzero(beyond)  # finite by construction: nan compares False
        k = int(index[pick(values[index])])
        edge = low if side == "low" else high
        what = Clipped(side, edge, float(values[k]), float(times[k]), int(np.sum(beyond)))
        clipped.append(what)
        text = f"{'min' if side == 'low' else 'max'} {what.extreme:.3g} {unit}".strip()
        at = np.unique(times[beyond])
        panel.plot(
            at,
            np.full(at.shape, edge),
            "v" if side == "low" else "^",
            color="tab:red",
            markersize=6,
            clip_on=False,
            zorder=5,
            gid=CLIPPED_GID,
            label=f"clipped: {text}",
        )
        panel.annotate(
            f"{text} at {what.time:.3f} s (clipped)",
            xy=(what.time, edge),
            xytext=(-6, 8 if side == "low" else -8),
            textcoords="offset points",
            ha="right",
            va="bottom" if side == "low" else "top",
            fontsize=7,
            color="tab:red",
        )
    return clipped


def label_gap(panel: Axes, fontsize: float) -> float:
    """The x distance (data units) two labels rotated 90 deg need so they do not overlap."""
    fig = panel.get_figure()
    assert fig is not None
    width_px = panel.get_window_extent().width
    x0, x1 = panel.get_xlim()
    label_px = LABEL_GAP_FONT_SIZES * fontsize * fig.dpi / 72.0
    return abs(x1 - x0) * label_px / max(width_px, 1.0)


def merge_events(times: Sequence[float], gap: float) -> list[list[int]]:
    """Indices of ascending `times` in groups: a group starts at least `gap` after the last one.

    A label drawn at each group's first time is then at least `gap` from the next label.
    """
    groups: list[list[int]] = []
    start = -math.inf
    for k, t in enumerate(times):
        if groups and t - start < gap:
            groups[-1].append(k)
        else:
            groups.append([k])
            start = t
    return groups


def save_png(fig: Figure, path: Path) -> None:
    """Lay out and write a matplotlib figure as PNG, atomically."""
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=PNG_DPI)
