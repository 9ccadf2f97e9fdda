"""`lca-hil sweep --plot DIR`: a sweep's results as PNGs, one figure per metric.

A line over one varying grid parameter; over two, lines (one per value of `plot.lines_by`, of
the parameter with at most 4 values, or of the one that is not a number) or a heatmap; a
histogram of the metric for a random sweep. docs/sweeps.md shows them.
"""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from lca_sim.batch.checks import is_number
from lca_sim.batch.store import OK, RECORD, RESULTS, pyarrow_modules
from lca_sim.cli.plotting import metric_label, metric_unit, save_png
from lca_sim.errors import OutputError


def plot_sweep(out: Path) -> list[Path]:
    """PNGs of DIR's results: a metric over one or two grid parameters, histograms for random.

    One figure per metric in DIR/plots/: a line over one varying parameter; over two, lines
    (one per value of `plot.lines_by`, of the parameter with at most 4 values, or of the one
    that is not a number) or a heatmap; a histogram of the metric for a random sweep.
    `plot.mark` ({parameter: value}) marks a point (e.g. the paper's gains) on a heatmap.

    Raises:
        OutputError: DIR has no results, or a grid these plots cannot draw (more than two
            varying parameters, or two that are not numbers): the figure would mix points.
    """
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    _pa, pq = pyarrow_modules()

    if not (out / RESULTS).is_file() or not (out / RECORD).is_file():
        raise OutputError(f"{out}: no {RESULTS} and {RECORD} (run the sweep first)")
    record = json.loads((out / RECORD).read_text(encoding="utf-8"))
    rows = pq.read_table(out / RESULTS).to_pylist()
    ok = [r for r in rows if r["status"] == OK]
    written = []
    varying = [
        p["name"] for p in record["parameters"] if p["values"] is None or len(p["values"]) > 1
    ]
    if record["sampling"] != "random" and len(varying) > 2:
        raise OutputError(
            f"{out}: the plots draw a metric over one or two parameters, this grid varies "
            f"{len(varying)} ({', '.join(varying)}): read {RESULTS} with pandas or pyarrow"
        )
    title = Path(record["spec"]).stem
    degrees = set(record["plot"].get("degrees", []))
    for metric in record["metrics"]:
        name = metric["name"]
        scale, unit = metric_unit(metric["unit"], metric.get("axis"), _REFERENCE[record["kind"]])
        if name in degrees:  # plot.degrees: a radian metric drawn in degrees
            scale, unit = 180.0 / math.pi, "deg"
        label = metric_label(name, unit)
        fig, ax = plt.subplots(figsize=(7.0, 4.6))
        if scale != 1.0:
            ok = [{**r, name: None if r[name] is None else r[name] * scale} for r in ok]
        if record["sampling"] == "random" or not varying:
            _histogram(ax, [r[name] for r in ok], label, len(rows) - len(ok))
        elif len(varying) == 1:
            _line(ax, ok, varying[0], name, label)
        else:
            _lines_or_heatmap(ax, fig, ok, record, varying[:2], name, label)
        ax.set_title(f"{title}: {name}")
        path = out / "plots" / f"{name}.png"
        save_png(fig, path)
        plt.close(fig)
        written.append(path)
    return written


# What the reference of each kind of run is for (the tracking metrics' unit).
_REFERENCE = {"closed_loop": "velocity", "current_step": "current_a", "open_loop": ""}


def _finite(values: Sequence[Any]) -> list[float]:
    return [float(v) for v in values if v is not None and math.isfinite(float(v))]


def _histogram(ax: Any, values: Sequence[Any], label: str, failed: int) -> None:
    import numpy as np  # noqa: PLC0415

    data = _finite(values)
    ax.hist(data, bins=min(50, max(5, len(data) // 20)), color="tab:blue", alpha=0.8)
    if data:
        q = np.percentile(data, [5, 50, 95])
        for x, style in zip(q, (":", "-", ":"), strict=True):
            ax.axvline(x, color="k", linestyle=style, linewidth=1)
        ax.text(
            0.98,
            0.95,
            f"n = {len(data)} ({failed} failed, {len(values) - len(data)} NaN)\n"
            f"5/50/95 %: {q[0]:.6g} / {q[1]:.6g} / {q[2]:.6g}",
            transform=ax.transAxes,
            ha="right",
            va="top",
            fontsize=8,
        )
    ax.ticklabel_format(axis="x", useOffset=False)
    ax.set_xlabel(label)
    ax.set_ylabel("points")


def _line(ax: Any, rows: Sequence[Mapping[str, Any]], x: str, name: str, label: str) -> None:
    pairs = sorted((r[x], r[name]) for r in rows)
    ax.plot([p[0] for p in pairs], [p[1] for p in pairs], "o-")
    ax.set_xlabel(x)
    ax.set_ylabel(label)
    ax.grid(True, alpha=0.3)


def _lines_or_heatmap(
    ax: Any,
    fig: Any,
    rows: Sequence[Mapping[str, Any]],
    record: Mapping[str, Any],
    varying: list[str],
    name: str,
    label: str,
) -> None:
    """A metric over two grid parameters: a line per value of one, or a heatmap of both."""
    import numpy as np  # noqa: PLC0415

    values = {p["name"]: p["values"] for p in record["parameters"]}
    lines_by = record["plot"].get("lines_by")
    words = [v for v in varying if not all(is_number(x) for x in values[v])]
    if len(words) == 2:
        raise OutputError(f"no plot of {name} over two parameters that are not numbers: {words}")
    if words and lines_by not in varying:
        lines_by = words[0]  # a heatmap needs numbers on both axes
    if lines_by is None:
        small = [v for v in varying if len(values[v]) <= 4]
        lines_by = small[-1] if small else None
    if lines_by in varying:
        x = varying[0] if lines_by == varying[1] else varying[1]
        for value in values[lines_by]:
            pairs = sorted((r[x], r[name]) for r in rows if r[lines_by] == value)
            ax.plot(
                [p[0] for p in pairs],
                [p[1] for p in pairs],
                "o-",
                label=f"{lines_by} = {value:g}" if is_number(value) else f"{lines_by} = {value}",
            )
        ax.set_xlabel(x)
        ax.set_ylabel(label)
        ax.legend()
        ax.grid(True, alpha=0.3)
        return
    xs, ys = sorted(values[varying[1]]), sorted(values[varying[0]])
    grid = np.full((len(ys), len(xs)), np.nan)
    for r in rows:
        v = r[name]
        grid[ys.index(r[varying[0]]), xs.index(r[varying[1]])] = np.nan if v is None else v
    mesh = ax.pcolormesh(_edges(xs), _edges(ys), grid, shading="flat", cmap="viridis")
    fig.colorbar(mesh, ax=ax, label=label)
    for axis_set, vals in ((ax.set_xscale, xs), (ax.set_yscale, ys)):
        if _is_log(vals):
            axis_set("log")
    ax.set_xlabel(varying[1])
    ax.set_ylabel(varying[0])
    mark = record["plot"].get("mark")
    if isinstance(mark, Mapping) and varying[1] in mark and varying[0] in mark:
        ax.plot(
            [mark[varying[1]]],
            [mark[varying[0]]],
            "r*",
            markersize=14,
            label=str(mark.get("label", "mark")),
        )
        ax.legend(loc="upper right")


def _is_log(values: Sequence[float]) -> bool:
    """Sorted values spaced by a constant ratio (a `range: {log: true}`)."""
    if len(values) < 3 or min(values) <= 0.0:
        return False
    ratios = [b / a for a, b in itertools.pairwise(values)]
    return max(ratios) - min(ratios) < 1e-6 * max(ratios) and ratios[0] > 1.0


def _edges(values: Sequence[float]) -> list[float]:
    """Cell edges around sorted centres (geometric for a log-spaced set)."""
    import numpy as np  # noqa: PLC0415

    v = np.asarray(values, dtype=float)
    if len(v) == 1:
        return [v[0] * 0.9, v[0] * 1.1] if v[0] else [-0.5, 0.5]
    log = _is_log(values)
    w = np.log(v) if log else v
    mid = (w[1:] + w[:-1]) / 2
    edges = np.concatenate([[w[0] - (mid[0] - w[0])], mid, [w[-1] + (w[-1] - mid[-1])]])
    return list(np.exp(edges) if log else edges)
