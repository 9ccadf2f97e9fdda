"""`lca-hil sweep --plot`: what each figure draws, read back from the figure.

The results are written here by hand (the table a sweep writes, `merge`'s columns), so each
test knows every value the figure must show: a heatmap's cells, one line per value of a text
parameter, a histogram's counts, a metric drawn in degrees; and a grid the plots cannot draw is
refused with the reason instead of a figure that mixes points.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from lca_sim.batch.spec import parse_spec
from lca_sim.batch.store import RECORD, RESULTS, sweep_record
from lca_sim.cli import sweep_plots
from lca_sim.errors import OutputError
from lca_sim.output import write_json


def _results(
    tmp_path: Path, spec_doc: dict[str, Any], rows: list[dict[str, Any]]
) -> tuple[Path, list[Any]]:
    """A sweep folder with these rows, and the list the figures will be captured into."""
    import pyarrow as pa  # type: ignore[import-untyped]
    import pyarrow.parquet as pq  # type: ignore[import-untyped]

    spec = parse_spec(spec_doc, str(tmp_path / "study.yaml"))
    out = tmp_path / "out"
    out.mkdir()
    write_json(out / RECORD, sweep_record(spec, len(rows), "0"))
    columns = {key: [row[key] for row in rows] for key in rows[0]}
    pq.write_table(pa.table(columns), out / RESULTS)
    return out, []


def _capture(monkeypatch: pytest.MonkeyPatch, figures: list[Any]) -> None:
    def keep(fig: Any, path: Path) -> None:
        figures.append(fig)
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path)

    monkeypatch.setattr(sweep_plots, "save_png", keep)


def _row(index: int, **values: Any) -> dict[str, Any]:
    return {"index": index, "seed": 0, **values, "status": "ok", "error": "", "key": str(index)}


def _grid_spec(*parameters: dict[str, Any], metric: str = "peak_current_a") -> dict[str, Any]:
    return {
        "base": {"kind": "current_step", "axis": "pivot"},
        "parameters": list(parameters),
        "metrics": [{"metric": metric}],
    }


KP = [10.0, 20.0, 40.0, 80.0, 160.0]
TI = [1e-3, 2e-3, 3e-3, 4e-3, 5e-3]


def test_two_numeric_parameters_make_a_heatmap_with_its_mark(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """5 x 5 values: every cell holds its point's metric; the mark sits at its values."""
    spec = _grid_spec(
        {"name": "kp", "path": "base.current_kp_v_per_a", "values": KP},
        {"name": "ti", "path": "base.current_ti_s", "values": TI},
    )
    spec["plot"] = {"mark": {"kp": 40.0, "ti": 2e-3, "label": "paper"}}
    rows = [
        _row(5 * i + j, kp=kp, ti=ti, peak_current_a=kp * ti * 1e3)
        for i, kp in enumerate(KP)
        for j, ti in enumerate(TI)
    ]
    out, figures = _results(tmp_path, spec, rows)
    _capture(monkeypatch, figures)
    (path,) = sweep_plots.plot_sweep(out)
    assert path.is_file() and path.stat().st_size > 0
    ax = figures[0].axes[0]
    (mesh,) = ax.collections
    np.testing.assert_array_equal(
        np.asarray(mesh.get_array()).reshape(5, 5), np.outer(KP, TI) * 1e3
    )
    assert ax.get_xscale() == "linear" and ax.get_yscale() == "log"  # KP doubles: log-spaced
    (star,) = ax.lines
    assert (star.get_xdata()[0], star.get_ydata()[0], star.get_label()) == (2e-3, 40.0, "paper")


def test_a_text_parameter_gives_one_line_per_value(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A robot name by Kp: two lines labelled by name (its label once raised a ValueError)."""
    spec = _grid_spec(
        {"name": "robot_name", "path": "base.axis", "values": ["pivot", "c_arc"]},
        {"name": "kp", "path": "base.current_kp_v_per_a", "values": KP},
    )
    rows = [
        _row(5 * i + j, robot_name=name, kp=kp, peak_current_a=kp + 1000.0 * i)
        for i, name in enumerate(["pivot", "c_arc"])
        for j, kp in enumerate(KP)
    ]
    out, figures = _results(tmp_path, spec, rows)
    _capture(monkeypatch, figures)
    sweep_plots.plot_sweep(out)
    lines = figures[0].axes[0].lines
    assert [line.get_label() for line in lines] == ["robot_name = pivot", "robot_name = c_arc"]
    np.testing.assert_array_equal(lines[1].get_ydata(), np.array(KP) + 1000.0)


def test_a_grid_of_three_parameters_is_refused_with_the_reason(tmp_path: Path) -> None:
    """Three varying parameters: no figure that would mix points, an error naming them."""
    spec = _grid_spec(
        {"name": "kp", "path": "base.current_kp_v_per_a", "values": [10.0, 20.0]},
        {"name": "ti", "path": "base.current_ti_s", "values": [1e-3, 2e-3]},
        {"name": "amps", "path": "base.setpoint_a", "values": [1.0, 5.0]},
    )
    rows = [_row(i, kp=10.0, ti=1e-3, amps=1.0, peak_current_a=1.0) for i in range(8)]
    out, _ = _results(tmp_path, spec, rows)
    with pytest.raises(OutputError, match=r"varies 3 \(kp, ti, amps\)"):
        sweep_plots.plot_sweep(out)
    assert not (out / "plots").exists()


def test_a_random_sweep_is_a_histogram_of_its_finite_values(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """200 draws, 3 NaN and 2 failed: the bars count the 195 others, the text says so."""
    spec = _grid_spec(
        {"name": "r", "path": "base.setpoint_a",
         "distribution": {"kind": "uniform", "low": 1.0, "high": 2.0}},
    )  # fmt: skip
    spec.update(samples=200, seed=3)
    values = np.random.default_rng(0).normal(10.0, 1.0, 200)
    rows = [_row(i, r=1.0, peak_current_a=float(v)) for i, v in enumerate(values)]
    for i in (4, 5, 6):
        rows[i]["peak_current_a"] = math.nan
    for i in (7, 8):
        rows[i].update(status="failed", error="RuntimeError: x", peak_current_a=math.nan)
    out, figures = _results(tmp_path, spec, rows)
    _capture(monkeypatch, figures)
    sweep_plots.plot_sweep(out)
    ax = figures[0].axes[0]
    assert sum(patch.get_height() for patch in ax.patches) == 195
    assert "n = 195 (2 failed, 3 NaN)" in ax.texts[0].get_text()


def test_a_radian_metric_is_drawn_in_degrees_when_asked(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """plot.degrees: the line's values are the metric's radians times 180 / pi."""
    spec = _grid_spec(
        {"name": "kp", "path": "base.current_kp_v_per_a", "values": KP}, metric="travel"
    )
    spec["plot"] = {"degrees": ["travel"]}
    rows = [_row(i, kp=kp, travel=0.01 * i) for i, kp in enumerate(KP)]
    out, figures = _results(tmp_path, spec, rows)
    _capture(monkeypatch, figures)
    sweep_plots.plot_sweep(out)
    ax = figures[0].axes[0]
    np.testing.assert_allclose(ax.lines[0].get_ydata(), np.degrees(0.01 * np.arange(5)))
    assert ax.get_ylabel() == "travel (deg)"


def test_sweep_axes_say_deg_and_what_a_flag_means(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """gear_wear's metrics: travel in deg without `_rad`, end_stop_contact as `0 or 1`."""
    spec = _grid_spec(
        {"name": "wear", "path": "base.current_kp_v_per_a", "values": KP}, metric="travel"
    )
    spec["metrics"] = [
        {"name": "travel_after_cut_rad", "metric": "travel", "from_s": 0.5},
        {"name": "end_stop_contact", "metric": "end_stop_contact"},
    ]
    rows = [
        _row(i, wear=kp, travel_after_cut_rad=0.01 * i, end_stop_contact=float(i > 2))
        for i, kp in enumerate(KP)
    ]
    out, figures = _results(tmp_path, spec, rows)
    _capture(monkeypatch, figures)
    sweep_plots.plot_sweep(out)
    travel, contact = (fig.axes[0] for fig in figures)
    assert travel.get_ylabel() == "travel_after_cut (deg)"
    np.testing.assert_allclose(travel.lines[0].get_ydata(), np.degrees(0.01 * np.arange(5)))
    assert contact.get_ylabel() == "end_stop_contact (0 or 1)"
